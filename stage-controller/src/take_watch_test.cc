// TakeWatch: a take waits for devices that work on it, however long they take, and ends when nothing more can come.
#include "take_watch.h"

#include <gtest/gtest.h>

namespace stage::controller {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;

TakeSnapshot::Camera Cam(const std::string& id, int64_t expected, int64_t received, int64_t owed = 0, uint64_t work = 0,
                         std::string activity = "") {
  TakeSnapshot::Camera c;
  c.id = id;
  c.answered = true;
  c.expected = expected;
  c.received = received;
  c.owed = owed;
  c.work = work;
  c.activity = std::move(activity);
  return c;
}

TakeSnapshot Snap(std::vector<TakeSnapshot::Camera> cameras, std::optional<int64_t> edges, int64_t run_slots = 38) {
  TakeSnapshot s;
  s.cameras = std::move(cameras);
  s.clock_edges = edges;
  s.clock_run_slots = run_slots;
  return s;
}

class TakeWatchTest : public ::testing::Test {
 protected:
  TakeWatchOptions Options() {
    TakeWatchOptions o;
    o.drain = milliseconds(3000);
    o.stall = seconds(120);
    return o;
  }
  const TakeWatch::TimePoint t0_ = std::chrono::steady_clock::time_point() + seconds(1000);
};

TEST_F(TakeWatchTest, CompleteOnceEveryFrameIsIn) {
  TakeWatch w(Options(), t0_);
  EXPECT_EQ(w.Observe(Snap({Cam("a", 2, 1), Cam("b", 1, 1)}, 38), t0_ + seconds(1)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(Snap({Cam("a", 2, 2), Cam("b", 1, 1)}, 38), t0_ + seconds(2)), TakeVerdict::kComplete);
}

TEST_F(TakeWatchTest, WaitsPastEveryLimitForACameraThatWorksOnWhatItOwes) {
  // The clock has ended; the camera owes its frame and renders it for ten minutes, its work counter moving.
  TakeWatch w(Options(), t0_);
  for (int s = 1; s <= 600; s += 5) {
    const TakeVerdict v =
        w.Observe(Snap({Cam("mv-01", 1, 0, 1, static_cast<uint64_t>(s), "precomputing: 3 %")}, 38), t0_ + seconds(s));
    ASSERT_EQ(v, TakeVerdict::kUnderWay) << "at " << s << " s";
  }
  EXPECT_EQ(w.owed(), 1);
  EXPECT_NE(w.waiting_for().find("mv-01 owes 1 frame (precomputing: 3 %)"), std::string::npos) << w.waiting_for();
  EXPECT_EQ(w.Observe(Snap({Cam("mv-01", 1, 1, 0, 700)}, 38), t0_ + seconds(601)), TakeVerdict::kComplete);
}

TEST_F(TakeWatchTest, StallsWhenNothingMovesWhileAFrameIsOwed) {
  TakeWatch w(Options(), t0_);
  const auto snap = Snap({Cam("hs-1", 38, 37, 1, 500, "rendering slot 37")}, 38);
  EXPECT_EQ(w.Observe(snap, t0_ + seconds(1)), TakeVerdict::kUnderWay);
  // Well past the drain: it still owes the frame, so the take waits.
  EXPECT_EQ(w.Observe(snap, t0_ + seconds(60)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(snap, t0_ + seconds(122)), TakeVerdict::kStalled);
  EXPECT_NE(w.waiting_for().find("hs-1 owes 1 frame (rendering slot 37)"), std::string::npos);
}

TEST_F(TakeWatchTest, NoStallLimitWaitsForever) {
  TakeWatchOptions o = Options();
  o.stall = seconds(0);
  TakeWatch w(o, t0_);
  const auto snap = Snap({Cam("hs-1", 38, 37, 1, 500)}, 38);
  EXPECT_EQ(w.Observe(snap, t0_ + seconds(1)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(snap, t0_ + seconds(100000)), TakeVerdict::kUnderWay);
}

TEST_F(TakeWatchTest, WaitsForASlotClockThatIsStillProducingEdges) {
  // No camera owes anything (they wait for their triggers), the clock creeps on: the take is under way however long
  // each edge takes.
  TakeWatch w(Options(), t0_);
  for (int edge = 1; edge < 38; ++edge) {
    ASSERT_EQ(w.Observe(Snap({Cam("mv-01", 1, 0)}, edge), t0_ + seconds(30 * edge)), TakeVerdict::kUnderWay) << edge;
  }
  EXPECT_NE(w.waiting_for().find("the slot clock: 37 of 38 edges"), std::string::npos) << w.waiting_for();
}

TEST_F(TakeWatchTest, AHeldClockWaitsUntilTheStallLimitNotTheDrain) {
  // The clock stands (a device it waits for is slow): nobody owes a frame, and yet more frames will come.
  TakeWatch w(Options(), t0_);
  EXPECT_EQ(w.Observe(Snap({Cam("mv-01", 1, 0)}, 20), t0_ + seconds(1)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(Snap({Cam("mv-01", 1, 0)}, 20), t0_ + seconds(30)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(Snap({Cam("mv-01", 1, 0)}, 20), t0_ + seconds(122)), TakeVerdict::kStalled);
}

TEST_F(TakeWatchTest, DrainsOnceTheClockEndedAndNothingIsOwed) {
  // Frames were lost (missed triggers): none will come, and the take ends after the drain.
  TakeWatch w(Options(), t0_);
  EXPECT_EQ(w.Observe(Snap({Cam("hs-1", 38, 30)}, 38), t0_ + seconds(1)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(Snap({Cam("hs-1", 38, 30)}, 38), t0_ + milliseconds(3500)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(Snap({Cam("hs-1", 38, 30)}, 38), t0_ + milliseconds(4100)), TakeVerdict::kDrained);
}

TEST_F(TakeWatchTest, ASilentCameraKeepsWhatItLastOwedAGoneOneOwesNothing) {
  TakeWatch w(Options(), t0_);
  EXPECT_EQ(w.Observe(Snap({Cam("mv-01", 1, 0, 1, 10)}, 38), t0_ + seconds(1)), TakeVerdict::kUnderWay);
  TakeSnapshot::Camera silent = Cam("mv-01", 1, 0);
  silent.answered = false;  // slow to answer (a stopped process, a loaded machine)
  EXPECT_EQ(w.Observe(Snap({silent}, 38), t0_ + seconds(30)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.owed(), 1);
  EXPECT_NE(w.waiting_for().find("[not answering]"), std::string::npos) << w.waiting_for();
  TakeSnapshot::Camera gone = silent;
  gone.down = true;  // its process is not there
  EXPECT_EQ(w.Observe(Snap({gone}, 38), t0_ + seconds(31)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.owed(), 0);
  EXPECT_EQ(w.Observe(Snap({gone}, 38), t0_ + seconds(35)), TakeVerdict::kDrained);
}

TEST_F(TakeWatchTest, AnUnknownClockEndsAfterTheDrainAndAGrace) {
  TakeWatch w(Options(), t0_);
  EXPECT_EQ(w.Observe(Snap({Cam("hs-1", 38, 30)}, std::nullopt), t0_ + seconds(1)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(Snap({Cam("hs-1", 38, 30)}, std::nullopt), t0_ + seconds(5)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(Snap({Cam("hs-1", 38, 30)}, std::nullopt), t0_ + seconds(10)), TakeVerdict::kDrained);
}

TEST_F(TakeWatchTest, RestartGivesTheWaitAFreshStart) {
  // A pause holds the take: whatever it waited for starts again when it resumes.
  TakeWatch w(Options(), t0_);
  EXPECT_EQ(w.Observe(Snap({Cam("hs-1", 38, 30)}, 38), t0_ + seconds(1)), TakeVerdict::kUnderWay);
  w.Restart(t0_ + seconds(100));
  EXPECT_EQ(w.Observe(Snap({Cam("hs-1", 38, 30)}, 38), t0_ + seconds(102)), TakeVerdict::kUnderWay);
  EXPECT_EQ(w.Observe(Snap({Cam("hs-1", 38, 30)}, 38), t0_ + seconds(104)), TakeVerdict::kDrained);
}

TEST_F(TakeWatchTest, NamesTheFirstThreeCamerasThatOweAndCountsTheRest) {
  TakeWatch w(Options(), t0_);
  std::vector<TakeSnapshot::Camera> cams;
  for (int i = 1; i <= 5; ++i) cams.push_back(Cam("mv-0" + std::to_string(i), 1, 0, 1, 1));
  w.Observe(Snap(cams, 38), t0_ + seconds(1));
  EXPECT_EQ(w.owed(), 5);
  EXPECT_NE(w.waiting_for().find("mv-03 owes"), std::string::npos);
  EXPECT_EQ(w.waiting_for().find("mv-04 owes"), std::string::npos);
  EXPECT_NE(w.waiting_for().find("and 2 more camera(s)"), std::string::npos) << w.waiting_for();
}

}  // namespace
}  // namespace stage::controller
