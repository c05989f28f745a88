#include "alarms.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>

#include "stage/v1/controller.pb.h"

namespace stage::console {
namespace {

v1::StageStatus Status(bool cam_down, bool estop, double thermal, int64_t lost) {
  v1::StageStatus s;
  v1::NodeStatus* cam = s.add_nodes();
  cam->set_id("mv-01");
  cam->set_state(cam_down ? v1::NODE_STATE_DOWN : v1::NODE_STATE_UP);
  cam->set_reason(cam_down ? "connection refused" : "");
  s.add_nodes()->set_id("mv-02");  // UNSPECIFIED: not polled yet, no alarm
  s.set_estop_latched(estop);
  s.set_estop_reason("console: ana");
  v1::NodeDevice* light = s.add_devices();
  light->set_id("light-1");
  light->mutable_light()->set_max_thermal_load(thermal);
  v1::NodeDevice* camera = s.add_devices();
  camera->set_id("mv-01");
  camera->mutable_camera()->set_take_id("take-1");
  camera->mutable_camera()->set_take_frames_lost(lost);
  camera->mutable_camera()->set_take_frames_expected(100);
  return s;
}

TEST(AlarmsTest, ConditionsComeFromTheStatus) {
  EXPECT_TRUE(ConditionsOf(Status(false, false, 0.5, 0), {}).empty());
  auto c = ConditionsOf(Status(true, true, 0.95, 3), {});
  ASSERT_EQ(c.size(), 4u);
  EXPECT_EQ(c[0].key, "estop");
  EXPECT_EQ(c[0].message, "emergency stop: console: ana");
  v1::StageStatus said = Status(false, true, 0, 0);
  said.set_estop_reason("emergency stop: console: bo");  // the controller's words already say what it is
  EXPECT_EQ(ConditionsOf(said, {})[0].message, "emergency stop: console: bo");
  EXPECT_EQ(c[1].key, "node-down:mv-01");
  EXPECT_EQ(c[1].message, "mv-01 is down: connection refused");
  EXPECT_EQ(c[2].kind, AlarmKind::kThermal);
  EXPECT_EQ(c[3].message, "mv-01 lost 3 of 100 frames of take take-1");
}

TEST(AlarmsTest, AlarmsRiseClearAndKeepTheirAcknowledgementAcrossARestart) {
  const std::string path = ::testing::TempDir() + "/alarms_test_" + std::to_string(::getpid()) + ".sqlite";
  std::filesystem::remove(path);
  // The file and SQLite's journal beside it go when the test ends, after the books are closed.
  struct Cleanup {
    std::string path;
    ~Cleanup() {
      for (const char* suffix : {"", "-wal", "-shm"}) std::filesystem::remove(path + suffix);
    }
  } cleanup{path};
  int64_t id = 0;
  {
    auto book = AlarmBook::Open(path);
    ASSERT_TRUE(book.ok()) << book.status();
    auto changed = (*book)->Update(ConditionsOf(Status(true, true, 0, 0), {}), 100);
    ASSERT_TRUE(changed.ok());
    ASSERT_EQ(changed->size(), 2u);
    // The same conditions again: nothing changes.
    EXPECT_TRUE((*book)->Update(ConditionsOf(Status(true, true, 0, 0), {}), 200)->empty());
    for (const Alarm& a : (*book)->Active()) {
      if (a.key == "node-down:mv-01") id = a.id;
    }
    ASSERT_GT(id, 0);
    auto acked = (*book)->Acknowledge(id, "ana", 300);
    ASSERT_TRUE(acked.ok());
    EXPECT_EQ(acked->acked_by, "ana");
    EXPECT_EQ((*book)->Acknowledge(id, "bo", 400)->acked_by, "ana");  // the first acknowledgement stands
    EXPECT_EQ((*book)->Acknowledge(9999, "ana", 400).status().code(), absl::StatusCode::kNotFound);
  }
  // A restarted console: the open alarms are active again, the acknowledgement with them.
  auto book = AlarmBook::Open(path);
  ASSERT_TRUE(book.ok());
  auto active = (*book)->Active();
  ASSERT_EQ(active.size(), 2u);
  for (const Alarm& a : active) {
    if (a.id == id) {
      EXPECT_EQ(a.acked_unix_ns, 300);
    }
  }
  // The camera came back, the estop holds: one clears; the history keeps both.
  auto changed = (*book)->Update(ConditionsOf(Status(false, true, 0, 0), {}), 500);
  ASSERT_TRUE(changed.ok());
  ASSERT_EQ(changed->size(), 1u);
  EXPECT_EQ((*changed)[0].id, id);
  EXPECT_EQ((*changed)[0].cleared_unix_ns, 500);
  EXPECT_EQ((*book)->Active().size(), 1u);
  auto history = (*book)->History(10);
  ASSERT_TRUE(history.ok());
  EXPECT_EQ(history->size(), 2u);
  EXPECT_THAT(history->back().ToJson(), ::testing::HasSubstr("\"kind\":\"EMERGENCY_STOP\""));
}

}  // namespace
}  // namespace stage::console
