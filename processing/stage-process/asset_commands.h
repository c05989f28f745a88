// `stage-process asset ...`: the neural asset's commands (docs/asset.md).
#pragma once

#include <CLI/CLI.hpp>

#include "stage/processing/asset_dataset.h"
#include "stage/processing/asset_infer.h"
#include "stage/processing/asset_train.h"

namespace stage::process {

class AssetCommands {
 public:
  void Add(CLI::App& parent);
  // True when one of them was given on the command line.
  bool Parsed() const;
  int Run();

 private:
  void AddTrain();
  void AddTrainNetworkOptions();
  void AddEvaluate();
  void AddInfer();
  int BuildDataset();
  int Train();
  int TrainExpression();
  int TrainMapping();
  int FineTune();
  int TrainTexture();
  int TrainTextureMapping();
  // A mapping's or fine-tuning's result, as JSON or a table (1 and the error on failure).
  int PrintDriven(const std::string& what, const absl::StatusOr<processing::MappingTrainResult>& result);
  int Evaluate();
  int Infer();

  CLI::App* app_ = nullptr;
  CLI::App* build_dataset_ = nullptr;
  CLI::App* train_ = nullptr;
  CLI::App* evaluate_ = nullptr;
  std::string evaluate_dataset_, evaluate_run_, evaluate_geometry_run_, evaluate_expression_run_, evaluate_picture_,
      evaluate_mapping_run_, evaluate_texture_run_;
  std::string evaluate_network_ = "geometry";
  // The geometry job holds the options the networks share (the schedule, the trunks, threads and seed) as the command
  // line gives them; another network takes those given and keeps its own defaults for the rest (TakeGivenSchedule).
  processing::AssetTrainJob train_job_;
  processing::ExpressionTrainJob expression_job_;
  processing::MappingTrainJob mapping_job_;
  processing::FineTuneJob finetune_job_;
  processing::TextureTrainJob texture_job_;
  processing::TextureMappingJob texture_mapping_job_;
  bool freeze_encoder_ = false;
  std::string network_ = "geometry";
  processing::DatasetOptions dataset_;
  CLI::App* infer_app_ = nullptr;
  processing::AssetInferOptions infer_;
  std::string infer_frames_ = "0:";
  bool no_meshes_ = false;
  std::string frames_ = "0:", source_ = "truth";
  bool json_ = false;
};

}  // namespace stage::process
