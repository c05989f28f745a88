// Logging: level specs are validated, and named loggers take their configured level.
#include "stage/common/logging.h"

#include "gtest/gtest.h"

namespace stage {
namespace {

TEST(LoggingTest, ValidatesLevelSpecs) {
  EXPECT_TRUE(ValidateLogLevels("debug").ok());
  EXPECT_TRUE(ValidateLogLevels("info,camera.sim=TRACE").ok());
  EXPECT_TRUE(ValidateLogLevels("off").ok());
  absl::Status bad = ValidateLogLevels("info,camera.sim=loud");
  EXPECT_FALSE(bad.ok());
  EXPECT_NE(std::string(bad.message()).find("\"loud\""), std::string::npos);
}

TEST(LoggingTest, NamedLoggersTakeTheirLevel) {
  ASSERT_TRUE(InitLogging("logging_test", "warn,test.chatty=trace").ok());
  EXPECT_EQ(Logger("test.chatty")->level(), spdlog::level::trace);
  EXPECT_EQ(Logger("test.quiet")->level(), spdlog::level::warn);
  // The same logger object is returned for the same name.
  EXPECT_EQ(Logger("test.chatty").get(), Logger("test.chatty").get());
  EXPECT_FALSE(InitLogging("logging_test", "verbose").ok());
}

}  // namespace
}  // namespace stage
