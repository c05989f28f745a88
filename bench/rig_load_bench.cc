// How long loading the shipped rig takes (parse into the schema, defaults, validation), next to its baseline in the
// same run: yaml-cpp parsing the same text into a bare node tree. The difference is FaStage's cost.
// Run: build/bin/rig_load_bench
#include <benchmark/benchmark.h>
#include <yaml-cpp/yaml.h>

#include <string>

#include "stage/common/rig.h"
#include "stage/common/yaml_proto.h"

namespace {

void BM_Baseline_YamlCppParseOnly(benchmark::State& state) {
  std::string text(stage::BuiltinRigText());
  for (auto _ : state) {
    YAML::Node node = YAML::Load(text);
    benchmark::DoNotOptimize(node);
  }
  state.SetBytesProcessed(static_cast<int64_t>(state.iterations()) * text.size());
}
BENCHMARK(BM_Baseline_YamlCppParseOnly)->Unit(benchmark::kMicrosecond);

void BM_YamlToRigProto(benchmark::State& state) {
  std::string text(stage::BuiltinRigText());
  for (auto _ : state) {
    stage::v1::RigConfig rig;
    stage::SourceMap map;
    absl::Status s = stage::ParseYamlToProto(text, "fastage.yaml", &rig, &map);
    if (!s.ok()) state.SkipWithError(std::string(s.message()).c_str());
    benchmark::DoNotOptimize(rig);
  }
  state.SetBytesProcessed(static_cast<int64_t>(state.iterations()) * text.size());
}
BENCHMARK(BM_YamlToRigProto)->Unit(benchmark::kMicrosecond);

void BM_LoadRigComplete(benchmark::State& state) {
  for (auto _ : state) {
    auto loaded = stage::LoadRig(stage::kBuiltinRigName);
    if (!loaded.ok()) state.SkipWithError(std::string(loaded.status().message()).c_str());
    benchmark::DoNotOptimize(loaded);
  }
}
BENCHMARK(BM_LoadRigComplete)->Unit(benchmark::kMicrosecond);

}  // namespace

BENCHMARK_MAIN();
