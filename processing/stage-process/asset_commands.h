// `stage-process asset ...`: the neural asset's commands (docs/asset.md).
#pragma once

#include <CLI/CLI.hpp>

#include "stage/processing/asset_dataset.h"

namespace stage::process {

class AssetCommands {
 public:
  void Add(CLI::App& parent);
  // True when one of them was given on the command line.
  bool Parsed() const;
  int Run();

 private:
  int BuildDataset();

  CLI::App* app_ = nullptr;
  CLI::App* build_dataset_ = nullptr;
  processing::DatasetOptions dataset_;
  std::string frames_ = "0:", source_ = "truth";
  bool json_ = false;
};

}  // namespace stage::process
