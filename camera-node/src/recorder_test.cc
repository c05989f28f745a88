// The take recorder on synthetic frames: tagged by timestamp whatever their arrival order, written to the frame file
// with their slot and pattern, every expected slot accounted for (stored, dropped by the camera per its frame counter,
// trigger missed), frames that match no slot counted, the camera's clock mapped, burst mode offloading after the take
// with progress, and its memory budget enforced.
#include "recorder.h"

#include <algorithm>
#include <filesystem>
#include <random>
#include <span>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::camera {
namespace {

using storage::LossReason;
constexpr int64_t kSlot = 1'096'491;  // ns, 912 Hz rounded (the plan's slot_start_ns is not set: k * slot_ns)

TakePlan Plan(const std::string& name, int64_t slots, uint32_t divider = 1, uint32_t phase = 0) {
  TakePlan p;
  p.path = ::testing::TempDir() + "/recorder-" + name + "/hs-1.h5";
  std::filesystem::remove_all(std::filesystem::path(p.path).parent_path());
  p.info.camera_id = "hs-1";
  p.info.take_id = "t-" + name;
  p.info.width = 16;
  p.info.height = 8;
  p.info.bytes_per_pixel = 1;
  p.info.pixel_format = "Mono8";
  p.t0_ns = 5'000'000'000;
  p.slot_ns = kSlot;
  p.slots = slots;
  p.divider = divider;
  p.phase = phase;
  p.trigger_delay_ns = 20'000;
  p.black_level = 4;
  p.first_frame_id = 0;
  return p;
}

// The frame the camera gives for slot k with counter `id`: every pixel 10 + k % 38 (brightness above black: 6 + k%38).
std::shared_ptr<Frame> FrameFor(const TakePlan& p, int64_t k, uint64_t id, int64_t jitter_ns = 0) {
  auto f = std::make_shared<Frame>();
  f->frame_id = id;
  const long double bus = p.t0_ns + k * p.slot_ns + p.trigger_delay_ns + jitter_ns;
  f->device_timestamp_ns =
      static_cast<int64_t>(std::llround(bus * (1 + p.clock_drift_ppm * 1e-6L))) + p.clock_offset_ns;
  f->width = p.info.width;
  f->height = p.info.height;
  f->pixel_format = "Mono8";
  f->data.assign(static_cast<size_t>(f->width) * f->height, static_cast<uint8_t>(10 + k % 38));
  return f;
}

TEST(RecorderTest, EveryFrameIsTaggedByItsTimestampAndWritten) {
  TakePlan plan = Plan("all", 76);
  plan.clock_offset_ns = 2'000'000;  // the camera's clock is 2 ms ahead and runs 100 ppm fast
  plan.clock_drift_ppm = 100;
  auto rec = TakeRecorder::Start(plan);
  ASSERT_TRUE(rec.ok()) << rec.status();
  // Frames arrive out of order (two cameras' threads, a late buffer): the slot comes from the timestamp.
  std::vector<int64_t> order(76);
  for (int64_t k = 0; k < 76; ++k) order[static_cast<size_t>(k)] = k;
  std::shuffle(order.begin(), order.end(), std::mt19937(3));
  for (int64_t k : order) (*rec)->OnFrame(FrameFor(plan, k, static_cast<uint64_t>(k), (k % 7) * 1000 - 3000));
  const TakeRecording r = (*rec)->Finish();
  EXPECT_EQ(r.frames_received, 76);
  EXPECT_EQ(r.frames_written, 76);
  EXPECT_EQ(r.frames_unmatched, 0);
  EXPECT_LE(r.max_timing_error_ns, 3000);
  EXPECT_TRUE(r.error.empty()) << r.error;
  ASSERT_EQ(r.slots.size(), 76u);
  for (const SlotOutcome& s : r.slots) {
    EXPECT_EQ(s.reason, LossReason::kNone) << s.slot;
    EXPECT_EQ(s.frame_id, static_cast<uint64_t>(s.slot));
    EXPECT_EQ(s.pattern, s.slot % 38);
  }
  ASSERT_EQ(r.brightness.size(), 76u);
  EXPECT_DOUBLE_EQ(r.brightness.at(40), 6 + 2);
  auto file = storage::FrameFileReader::Open(plan.path);
  ASSERT_TRUE(file.ok()) << file.status();
  auto records = (*file)->Records();
  ASSERT_TRUE(records.ok());
  ASSERT_EQ(records->size(), 76u);
  std::vector<int64_t> slots;
  for (const auto& rec_row : *records) {
    slots.push_back(rec_row.slot);
    EXPECT_EQ(rec_row.pattern, rec_row.slot % 38);
    EXPECT_EQ(rec_row.frame_id, static_cast<uint64_t>(rec_row.slot));
    EXPECT_NEAR(static_cast<double>(rec_row.controller_time_ns),
                static_cast<double>(rec_row.slot * kSlot + plan.trigger_delay_ns), 3000);
  }
  EXPECT_EQ(std::set<int64_t>(slots.begin(), slots.end()).size(), 76u);
  auto pixels = (*file)->Pixels(0);
  ASSERT_TRUE(pixels.ok());
  EXPECT_EQ((*pixels)[0], 10 + (*records)[0].slot % 38);
}

TEST(RecorderTest, AnIncompleteFrameIsKeptMarkedAndLostWithItsReasonAndLentPixelsAreWritten) {
  TakePlan plan = Plan("incomplete", 6);
  auto rec = TakeRecorder::Start(plan);
  ASSERT_TRUE(rec.ok()) << rec.status();
  // A device that lends its buffers: the frame points into memory it gets back when the last reference goes.
  auto released = std::make_shared<int>(0);
  for (int64_t k = 0; k < 6; ++k) {
    auto f = FrameFor(plan, k, static_cast<uint64_t>(k));
    auto buffer = std::shared_ptr<std::vector<uint8_t>>(new std::vector<uint8_t>(std::move(f->data)),
                                                        [released](std::vector<uint8_t>* b) {
                                                          ++*released;
                                                          delete b;
                                                        });
    f->data.clear();
    f->lent = std::span<const uint8_t>(*buffer);
    f->lent_owner = buffer;
    if (k == 2) f->incomplete = "missing packets: 3 of 40";
    (*rec)->OnFrame(std::move(f));
  }
  const TakeRecording r = (*rec)->Finish();
  EXPECT_EQ(*released, 6);  // every buffer went back once written
  EXPECT_EQ(r.frames_written, 6);
  ASSERT_EQ(r.slots.size(), 6u);
  EXPECT_EQ(r.slots[2].reason, LossReason::kIncomplete);
  EXPECT_EQ(r.slots[2].detail, "missing packets: 3 of 40");
  EXPECT_EQ(r.slots[2].frame_id, 2u);
  for (int k : {0, 1, 3, 4, 5}) EXPECT_EQ(r.slots[static_cast<size_t>(k)].reason, LossReason::kNone) << k;
  EXPECT_EQ(r.brightness.count(2), 0u);  // its zeroed part would bias the alignment self-test
  auto file = storage::FrameFileReader::Open(plan.path);
  ASSERT_TRUE(file.ok()) << file.status();
  auto records = (*file)->Records();
  ASSERT_TRUE(records.ok());
  ASSERT_EQ(records->size(), 6u);
  for (const auto& row : *records) {
    EXPECT_EQ(row.status, row.slot == 2 ? storage::FrameStatus::kIncomplete : storage::FrameStatus::kOk) << row.slot;
  }
  auto pixels = (*file)->Pixels(5);
  ASSERT_TRUE(pixels.ok());
  EXPECT_EQ((*pixels)[0], 10 + (*records)[5].slot % 38);
}

TEST(RecorderTest, EverySilentSlotGetsItsReasonFromTheFrameCounter) {
  TakePlan plan = Plan("losses", 20);
  auto rec = TakeRecorder::Start(plan);
  ASSERT_TRUE(rec.ok()) << rec.status();
  uint64_t id = 0;
  for (int64_t k = 0; k < 20; ++k) {
    if (k == 3 || k == 4) {  // exposed, lost before delivery: the counter moves on
      ++id;
      continue;
    }
    if (k == 10) continue;  // the trigger never reached the sensor: no exposure, no count
    if (k == 19) continue;  // after the last delivered frame: the counter cannot tell
    (*rec)->OnFrame(FrameFor(plan, k, id++));
  }
  // A frame between slots, a second frame for slot 5, and frames before slot 0 and after the take's end (a clock
  // that runs free): none is the take's, and none counts as received.
  (*rec)->OnFrame(FrameFor(plan, 5, 99, kSlot / 2 - 1000));
  (*rec)->OnFrame(FrameFor(plan, 5, 100));
  (*rec)->OnFrame(FrameFor(plan, -3, 101));
  (*rec)->OnFrame(FrameFor(plan, 25, 102));
  EXPECT_EQ((*rec)->frames_received(), 16);
  EXPECT_EQ((*rec)->frames_lost(), 2);  // live: the counter ran two ahead of what came
  const TakeRecording r = (*rec)->Finish();
  EXPECT_EQ(r.frames_unmatched, 4);
  EXPECT_EQ(r.frames_received, 16);
  std::map<int64_t, LossReason> lost;
  for (const SlotOutcome& s : r.slots) {
    if (s.reason != LossReason::kNone) lost[s.slot] = s.reason;
  }
  EXPECT_THAT(lost, ::testing::ElementsAre(::testing::Pair(3, LossReason::kCameraDropped),
                                           ::testing::Pair(4, LossReason::kCameraDropped),
                                           ::testing::Pair(10, LossReason::kTriggerMissed),
                                           ::testing::Pair(19, LossReason::kTriggerMissed)));
  EXPECT_THAT(r.slots[19].detail, ::testing::HasSubstr("after the last frame"));
  EXPECT_EQ(r.frames_written, 16);
}

// A frame whose leader was lost (GigE Vision) has no id and cannot be delivered, but the device says one came: after
// the last delivered frame, where the counter says nothing, such frames beyond the counter's gaps mark the first
// silent slots as exposed; what is left after them is unknown.
TEST(RecorderTest, FramesWithoutTheirLeaderAccountForTheTakesTail) {
  TakePlan plan = Plan("leaderless", 20);
  auto rec = TakeRecorder::Start(plan);
  ASSERT_TRUE(rec.ok()) << rec.status();
  uint64_t id = 0;
  for (int64_t k = 0; k < 17; ++k) {
    if (k == 3) {  // inside the take: the counter's gap shows it
      ++id;
      (*rec)->OnFrameLost();
      continue;
    }
    (*rec)->OnFrame(FrameFor(plan, k, id++));
  }
  (*rec)->OnFrameLost();  // slot 17: exposed, its leader lost; 18 and 19 sent nothing
  const TakeRecording r = (*rec)->Finish();
  std::map<int64_t, LossReason> lost;
  for (const SlotOutcome& s : r.slots) {
    if (s.reason != LossReason::kNone) lost[s.slot] = s.reason;
  }
  EXPECT_THAT(lost, ::testing::ElementsAre(::testing::Pair(3, LossReason::kCameraDropped),
                                           ::testing::Pair(17, LossReason::kCameraDropped),
                                           ::testing::Pair(18, LossReason::kTriggerMissed),
                                           ::testing::Pair(19, LossReason::kTriggerMissed)));
  EXPECT_THAT(r.slots[3].detail, ::testing::HasSubstr("frame counter"));
  EXPECT_THAT(r.slots[17].detail, ::testing::HasSubstr("without its leader"));
  EXPECT_THAT(r.slots[18].detail, ::testing::StartsWith("no frame after the last frame"));
}

// The camera's link went down and came back (the device says so on the first frame after): the silent slots before
// that frame are the outage's, whatever the counter says; a link still down as the take ends takes the tail.
TEST(RecorderTest, TheSlotsOfALinkOutageAreLostAsLinkDown) {
  TakePlan plan = Plan("outage", 20);
  auto rec = TakeRecorder::Start(plan);
  ASSERT_TRUE(rec.ok()) << rec.status();
  uint64_t id = 0;
  for (int64_t k = 0; k < 16; ++k) {
    if (k >= 5 && k <= 8) continue;  // off the link
    auto f = FrameFor(plan, k, id++);
    if (k == 9) f->after_outage = "link down 12:00:01.000 for 0.40 s";
    (*rec)->OnFrame(std::move(f));
  }
  (*rec)->ReportLinkOutages(2, "control of the camera lost; reconnecting");  // one came back, one did not
  const TakeRecording r = (*rec)->Finish();
  std::map<int64_t, std::string> lost;
  for (const SlotOutcome& s : r.slots) {
    if (s.reason != LossReason::kNone) {
      EXPECT_EQ(s.reason, LossReason::kLinkDown) << s.slot;
      lost[s.slot] = s.detail;
    }
  }
  EXPECT_THAT(lost, ::testing::ElementsAre(
                        ::testing::Pair(5, "link down 12:00:01.000 for 0.40 s"),
                        ::testing::Pair(6, "link down 12:00:01.000 for 0.40 s"),
                        ::testing::Pair(7, "link down 12:00:01.000 for 0.40 s"),
                        ::testing::Pair(8, "link down 12:00:01.000 for 0.40 s"),
                        ::testing::Pair(16, "control of the camera lost; reconnecting"),
                        ::testing::Pair(17, "control of the camera lost; reconnecting"),
                        ::testing::Pair(18, "control of the camera lost; reconnecting"),
                        ::testing::Pair(19, "control of the camera lost; reconnecting")));
  EXPECT_EQ(r.frames_written, 12);
}

TEST(RecorderTest, AMachineVisionCameraFiresInItsSlotsOnly) {
  TakePlan plan = Plan("mv", 912, 38, 19);
  auto rec = TakeRecorder::Start(plan);
  ASSERT_TRUE(rec.ok());
  ASSERT_EQ((*rec)->expected_slots().size(), 24u);
  EXPECT_EQ((*rec)->expected_slots()[1], 57);
  for (int64_t i = 0; i < 24; ++i) (*rec)->OnFrame(FrameFor(plan, 19 + 38 * i, static_cast<uint64_t>(i)));
  (*rec)->OnFrame(FrameFor(plan, 20, 24));  // a stray trigger in a slot it does not fire in
  const TakeRecording r = (*rec)->Finish();
  EXPECT_EQ(r.frames_written, 24);
  EXPECT_EQ(r.frames_unmatched, 1);
  for (const SlotOutcome& s : r.slots) {
    EXPECT_EQ(s.reason, LossReason::kNone);
    EXPECT_EQ(s.pattern, 19);
  }
}

TEST(RecorderTest, BurstHoldsFramesUntilTheTakeEndsThenOffloadsWithProgress) {
  TakePlan plan = Plan("burst", 50);
  plan.burst = true;
  plan.burst_bytes = 40 * 16 * 8;  // room for 40 frames
  auto rec = TakeRecorder::Start(plan);
  ASSERT_TRUE(rec.ok());
  for (int64_t k = 0; k < 50; ++k) (*rec)->OnFrame(FrameFor(plan, k, static_cast<uint64_t>(k)));
  EXPECT_EQ((*rec)->frames_written(), 0);  // nothing touches the disk during the take
  std::vector<std::pair<int64_t, int64_t>> progress;
  const TakeRecording r = (*rec)->Finish([&](int64_t done, int64_t total) { progress.emplace_back(done, total); });
  EXPECT_EQ(r.frames_written, 40);
  ASSERT_EQ(progress.size(), 40u);
  EXPECT_EQ(progress.back(), std::make_pair(int64_t{40}, int64_t{40}));
  int full = 0;
  for (const SlotOutcome& s : r.slots) {
    if (s.reason == LossReason::kWriteFailed) {
      ++full;
      EXPECT_THAT(s.detail, ::testing::HasSubstr("burst memory full"));
      EXPECT_GE(s.slot, 40);
    }
  }
  EXPECT_EQ(full, 10);
}

// Armed before the take starts: no frame belongs to it until T0 is given; a pause's gap is neither expected nor
// lost and is listed as paused; the frame counter runs on across the gap; an abort cuts the take at its slot.
TEST(RecorderTest, APlanChangedDuringTheTakeStartsItPausesItAndCutsItShort) {
  TakePlan plan = Plan("update", 76);
  plan.started = false;
  plan.preview_pattern = 0;
  const int64_t t0 = plan.t0_ns;
  plan.t0_ns = 0;
  auto rec = TakeRecorder::Start(plan);
  ASSERT_TRUE(rec.ok()) << rec.status();
  plan.t0_ns = t0;
  (*rec)->OnFrame(FrameFor(plan, 0, 0));  // before the start: not the take's
  EXPECT_EQ((*rec)->frames_received(), 0);
  EXPECT_FALSE((*rec)->LatestPreview().has_value());
  PlanUpdate start;
  start.t0_ns = t0;
  start.first_frame_id = 1;
  ASSERT_TRUE((*rec)->Update(start).ok());
  uint64_t id = 1;
  for (int64_t k = 0; k < 38; ++k) (*rec)->OnFrame(FrameFor(plan, k, id++));
  // Paused after one cycle, resumed two cycles later: 38 more slots, then an abort after 10 of them.
  PlanUpdate resume;
  resume.slots = 76 + 76;
  resume.paused = {{38, 114}};
  ASSERT_TRUE((*rec)->Update(resume).ok());
  EXPECT_EQ((*rec)->expected_frames(), 76);
  for (int64_t k = 114; k < 124; ++k) (*rec)->OnFrame(FrameFor(plan, k, id++));
  PlanUpdate abort = resume;
  abort.slots = 124;
  ASSERT_TRUE((*rec)->Update(abort).ok());
  EXPECT_EQ((*rec)->expected_frames(), 48);
  ASSERT_TRUE((*rec)->LatestPreview().has_value());
  EXPECT_EQ((*rec)->LatestPreview()->slot, 114);  // pattern 0's latest frame
  PlanUpdate bad;
  bad.paused = {{100, 90}};
  EXPECT_EQ((*rec)->Update(bad).code(), absl::StatusCode::kInvalidArgument);

  const TakeRecording r = (*rec)->Finish();
  EXPECT_EQ(r.frames_written, 48);
  ASSERT_EQ(r.slots.size(), 124u);
  for (const SlotOutcome& s : r.slots) {
    const bool gap = s.slot >= 38 && s.slot < 114;
    EXPECT_EQ(s.reason, gap ? LossReason::kPaused : LossReason::kNone) << s.slot;
  }
}

TEST(RecorderTest, BadPlansAreRefused) {
  TakePlan plan = Plan("bad", 0);
  EXPECT_FALSE(TakeRecorder::Start(plan).ok());
  plan = Plan("bad2", 10, 38, 38);
  auto r = TakeRecorder::Start(plan);
  ASSERT_FALSE(r.ok());
  EXPECT_THAT(r.status().message(), ::testing::HasSubstr("phase 38 is not below the divider 38"));
}

}  // namespace
}  // namespace stage::camera
