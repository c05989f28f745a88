// The processing graph's plans, manifests and tasks on a take of files, with a stand-in for the stages: what is
// stale and why, what a re-run skips, and that a failed task leaves what was in place.
#include "stage/processing/graph.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "graph_internal.h"
#include "stage/common/file_util.h"

namespace stage::processing {
namespace {
namespace fs = std::filesystem;

class GraphTest : public ::testing::Test {
 protected:
  void SetUp() override {
    take_ = (fs::temp_directory_path() / absl::StrCat("graph_test_", getpid(), "_", counter_++)).string();
    fs::create_directories(take_ + "/cameras");
    ASSERT_TRUE(WriteFileAtomically(take_ + "/take.json", R"({"summary": {"frames": "10"}})").ok());
    ASSERT_TRUE(WriteFileAtomically(take_ + "/cameras/mv-01.h5", "frames").ok());
    options_.take_dir = take_;
    options_.chunk_frames = 4;
  }
  void TearDown() override { fs::remove_all(take_); }

  // The stages' stand-in: each output file holds its stage, frame, flags and what it read, so that an input's change
  // shows in every output made from it.
  absl::Status FakeStage(const std::vector<std::string>& argv) {
    ++stage_runs_;
    const std::string name = argv[0];
    int64_t first = 0, last = 0;
    std::string out, flags;
    for (size_t i = 1; i + 1 < argv.size(); ++i) {
      if (argv[i] == "--frames") {
        const std::vector<std::string> ab = absl::StrSplit(argv[i + 1], ':');
        EXPECT_TRUE(absl::SimpleAtoi(ab[0], &first) && absl::SimpleAtoi(ab[1], &last));
      }
      if (argv[i] == "--output") out = argv[i + 1];
    }
    for (size_t i = 7; i < argv.size(); ++i) flags += argv[i] + " ";
    if (name == fail_) return absl::InternalError(name + " failed on purpose");
    auto read = [&](const std::string& path) {
      auto t = ReadFileToString(take_ + "/derived/" + path);
      return t.ok() ? *t : "";
    };
    if (name == "stabilize") {
      std::string all;
      for (int64_t f = first; f < last; ++f) all += read(absl::StrFormat("textures/frame-%06d/out.txt", f));
      return WriteFileAtomically(out + "/out.txt", "stabilize " + flags + all);
    }
    for (int64_t f = first; f < last; ++f) {
      const std::string frame = absl::StrFormat("frame-%06d", f);
      std::string in;
      if (name == "photometric") in = read("mvs/" + frame + "/out.txt");
      if (name == "fit") in = read("mvs/" + frame + "/out.txt");
      if (name == "textures") in = read("fit/" + frame + "/out.txt") + read("photometric/" + frame + "/out.txt");
      fs::create_directories(out + "/" + frame);
      const absl::Status s =
          WriteFileAtomically(out + "/" + frame + "/out.txt", absl::StrCat(name, " ", f, " ", flags, "[", in, "]"));
      if (!s.ok()) return s;
    }
    return WriteFileAtomically(out + "/run.json", absl::StrCat("{\"frames\": [", first, ", ", last, "]}"));
  }

  // Plans and runs every needed task in order: the number of tasks run.
  int RunAll() {
    auto plan = PlanGraph(options_);
    EXPECT_TRUE(plan.ok()) << plan.status();
    if (!plan.ok()) return -1;
    EXPECT_TRUE(WritePlan(*plan).ok());
    int ran = 0;
    for (size_t i = 0; i < plan->tasks.size(); ++i) {
      if (!plan->tasks[i].needed) continue;
      ++ran;
      const absl::Status s = RunGraphTask(*plan, static_cast<int>(i), 1,
                                          [this](const std::vector<std::string>& argv) { return FakeStage(argv); });
      if (!s.ok()) last_error_ = s;
    }
    return ran;
  }

  std::vector<std::string> Needed() {
    auto plan = PlanGraph(options_);
    EXPECT_TRUE(plan.ok()) << plan.status();
    std::vector<std::string> out;
    for (const GraphTask& t : plan->tasks) {
      if (t.needed) out.push_back(plan->TaskName(t));
    }
    return out;
  }

  static inline int counter_ = 0;
  std::string take_, fail_;
  GraphOptions options_;
  int stage_runs_ = 0;
  absl::Status last_error_;
};

TEST_F(GraphTest, APlanChunksTheFramesAndWaitsChunkForChunkWhereItCan) {
  auto plan = PlanGraph(options_);
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_EQ(plan->last_frame, 10);
  // Calibration is not asked for by default; the others are, and every task runs: nothing is there.
  std::vector<std::string> names;
  for (const GraphTask& t : plan->tasks) {
    names.push_back(plan->TaskName(t));
    EXPECT_TRUE(t.needed);
  }
  EXPECT_EQ(names,
            (std::vector<std::string>{"mvs.0", "mvs.1", "mvs.2", "photometric.0", "photometric.1", "photometric.2",
                                      "fit.0", "textures.0", "textures.1", "textures.2", "stabilize.0"}));
  EXPECT_EQ(plan->tasks[2].first, 8);
  EXPECT_EQ(plan->tasks[2].last, 10);
  // photometric.1 reads mvs.1 only; fit reads every mvs chunk; textures.1 reads the fit and photometric.1.
  EXPECT_EQ(plan->DependenciesOf(plan->Find(GraphStage::kPhotometric, 1)), std::vector<int>{1});
  EXPECT_EQ(plan->DependenciesOf(plan->Find(GraphStage::kFit, 0)), (std::vector<int>{0, 1, 2}));
  EXPECT_EQ(plan->DependenciesOf(plan->Find(GraphStage::kTextures, 1)), (std::vector<int>{6, 4}));
  EXPECT_TRUE(plan->ChunkToChunk(GraphStage::kPhotometric));
  EXPECT_FALSE(plan->ChunkToChunk(GraphStage::kTextures));
  EXPECT_FALSE(plan->ChunkToChunk(GraphStage::kMvs));

  // Asking for photometric stereo alone brings in multi-view stereo, nothing else.
  options_.stages = {GraphStage::kPhotometric};
  plan = PlanGraph(options_);
  ASSERT_TRUE(plan.ok());
  EXPECT_EQ(plan->stages, (std::vector<GraphStage>{GraphStage::kMvs, GraphStage::kPhotometric}));
}

TEST_F(GraphTest, ARunLeavesManifestsAndARerunHasNothingToDo) {
  EXPECT_EQ(RunAll(), 11);
  ASSERT_TRUE(last_error_.ok()) << last_error_;
  EXPECT_TRUE(Needed().empty());
  auto manifest = ReadFileToString(take_ + "/derived/textures/frame-000005/manifest.json");
  ASSERT_TRUE(manifest.ok());
  EXPECT_NE(manifest->find("\"out.txt\""), std::string::npos) << *manifest;
  // The stage's own files beside the frames come from its first task alone.
  EXPECT_EQ(*ReadFileToString(take_ + "/derived/mvs/run.json"), "{\"frames\": [0, 4]}");
  // No work directory is left behind.
  EXPECT_FALSE(fs::exists(take_ + "/processing/work/mvs.0-a1"));
  const int runs = stage_runs_;
  EXPECT_EQ(RunAll(), 0);
  EXPECT_EQ(stage_runs_, runs);
}

TEST_F(GraphTest, AChangedFlagRedoesItsStageAndWhatReadsItAndNothingElse) {
  ASSERT_EQ(RunAll(), 11);
  options_.stage_args[GraphStage::kFit] = {"--stiffness=5"};
  auto plan = PlanGraph(options_);
  ASSERT_TRUE(plan.ok());
  EXPECT_EQ(Needed(), (std::vector<std::string>{"fit.0", "textures.0", "textures.1", "textures.2", "stabilize.0"}));
  EXPECT_EQ(plan->tasks[plan->Find(GraphStage::kFit, 0)].reason, "stale: flags changed");
  EXPECT_EQ(plan->tasks[plan->Find(GraphStage::kTextures, 0)].reason, "after fit");
  const std::string mvs_manifest = *ReadFileToString(take_ + "/derived/mvs/frame-000000/manifest.json");
  ASSERT_EQ(RunAll(), 5);
  ASSERT_TRUE(last_error_.ok()) << last_error_;
  EXPECT_EQ(*ReadFileToString(take_ + "/derived/mvs/frame-000000/manifest.json"), mvs_manifest);
  EXPECT_NE(ReadFileToString(take_ + "/derived/textures/frame-000003/out.txt")->find("--stiffness=5"),
            std::string::npos);
  EXPECT_TRUE(Needed().empty());
}

TEST_F(GraphTest, AnOutputChangedByHandIsMadeAgain) {
  ASSERT_EQ(RunAll(), 11);
  ASSERT_TRUE(WriteFileAtomically(take_ + "/derived/photometric/frame-000006/out.txt", "edited").ok());
  auto plan = PlanGraph(options_);
  ASSERT_TRUE(plan.ok());
  const GraphTask& t = plan->tasks[plan->Find(GraphStage::kPhotometric, 1)];
  EXPECT_TRUE(t.needed);
  EXPECT_NE(t.reason.find("outputs changed"), std::string::npos) << t.reason;
  EXPECT_FALSE(plan->tasks[plan->Find(GraphStage::kPhotometric, 0)].needed);
  // A removed frame is missing, and its stage's tasks after it run too.
  fs::remove_all(take_ + "/derived/mvs/frame-000009");
  EXPECT_EQ(Needed(), (std::vector<std::string>{"mvs.2", "photometric.1", "photometric.2", "fit.0", "textures.0",
                                                "textures.1", "textures.2", "stabilize.0"}));
}

TEST_F(GraphTest, AFailedTaskLeavesWhatWasInPlaceAndSaysWhy) {
  ASSERT_EQ(RunAll(), 11);
  const std::string before = *ReadFileToString(take_ + "/derived/fit/frame-000002/out.txt");
  options_.stage_args[GraphStage::kFit] = {"--stiffness=5"};
  fail_ = "fit";
  RunAll();
  EXPECT_EQ(last_error_.code(), absl::StatusCode::kInternal);
  EXPECT_EQ(*ReadFileToString(take_ + "/derived/fit/frame-000002/out.txt"), before);
  auto plan = PlanGraph(options_);
  ASSERT_TRUE(plan.ok());
  auto status = ReadTaskStatus(StatusPath(*plan, plan->tasks[plan->Find(GraphStage::kFit, 0)]));
  ASSERT_TRUE(status.ok()) << status.status();
  EXPECT_EQ(status->state, TaskState::kFailed);
  EXPECT_EQ(status->message, "fit failed on purpose");
}

TEST_F(GraphTest, AGarbledManifestIsStaleAndATaskOfAnotherRunIsRefused) {
  ASSERT_EQ(RunAll(), 11);
  ASSERT_TRUE(WriteFileAtomically(take_ + "/derived/mvs/frame-000001/manifest.json", R"({"key": 3})").ok());
  auto plan = PlanGraph(options_);
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_EQ(plan->tasks[0].reason, "stale: its manifest is unreadable");
  plan->run_id = "run-a";
  ASSERT_TRUE(WritePlan(*plan).ok());
  const absl::Status other = RunGraphTask(
      *plan, 0, 1, [this](const std::vector<std::string>& argv) { return FakeStage(argv); }, "run-b");
  EXPECT_EQ(other.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(other.message().find("a job an earlier run left queued"), std::string::npos) << other;
  EXPECT_TRUE(RunGraphTask(
                  *plan, 0, 1, [this](const std::vector<std::string>& argv) { return FakeStage(argv); }, "run-a")
                  .ok());
  EXPECT_EQ(ReadPlan(plan->run_dir)->run_id, "run-a");
}

TEST_F(GraphTest, APlanReadsBackAsWritten) {
  options_.stage_args[GraphStage::kMvs] = {"--image-scale", "0.25"};
  options_.calibration = "cameras.json";
  ASSERT_TRUE(WriteFileAtomically(take_ + "/cameras.json", "{}").ok());
  auto plan = PlanGraph(options_);
  ASSERT_TRUE(plan.ok()) << plan.status();
  ASSERT_TRUE(WritePlan(*plan).ok());
  auto back = ReadPlan(plan->run_dir);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->stages, plan->stages);
  ASSERT_EQ(back->tasks.size(), plan->tasks.size());
  EXPECT_EQ(back->tasks[4].reason, plan->tasks[4].reason);
  EXPECT_EQ(back->options.stage_args, plan->options.stage_args);
  EXPECT_EQ(back->calibration_sha256, plan->calibration_sha256);
  EXPECT_FALSE(plan->calibration_sha256.empty());
}

TEST_F(GraphTest, BadOptionsAreRefusedNamingThem) {
  options_.stage_args[GraphStage::kMvs] = {"--output=elsewhere"};
  EXPECT_NE(PlanGraph(options_).status().message().find("--output=elsewhere"), std::string::npos);
  options_.stage_args.clear();
  options_.last_frame = 11;
  EXPECT_NE(PlanGraph(options_).status().message().find("holds 10 frame(s)"), std::string::npos);
  options_.last_frame = -1;
  fs::remove(take_ + "/take.json");
  EXPECT_EQ(PlanGraph(options_).status().code(), absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace stage::processing
