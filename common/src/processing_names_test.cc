#include "stage/common/processing_names.h"

#include <gtest/gtest.h>

namespace stage {
namespace {

TEST(ProcessingNamesTest, CommandLineWordsNameTheirStages) {
  EXPECT_EQ(ParseProcessingStage("mvs"), v1::PROCESSING_STAGE_MVS);
  EXPECT_EQ(ParseProcessingStage("asset-train"), v1::PROCESSING_STAGE_ASSET_TRAIN);
  EXPECT_EQ(ParseProcessingStage("textures"), v1::PROCESSING_STAGE_TEXTURES);
  EXPECT_EQ(ParseProcessingStage("calibration"), v1::PROCESSING_STAGE_CALIBRATION);
  EXPECT_EQ(ParseProcessingStage("calibrate"), v1::PROCESSING_STAGE_CALIBRATION);  // stage-process run's word
  EXPECT_EQ(ParseProcessingStage("graph"), v1::PROCESSING_STAGE_GRAPH);
  EXPECT_EQ(ParseProcessingStage("uv-maps"), std::nullopt);
  EXPECT_EQ(ParseProcessingStage("unspecified"), std::nullopt);
  EXPECT_EQ(ParseProcessingStage(""), std::nullopt);
}

}  // namespace
}  // namespace stage
