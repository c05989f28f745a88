// Light node: info, stats from the driver, and dark on destruction.
#include "light_node.h"

#include <chrono>
#include <thread>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "light_backends.h"
#include "stage/common/rig.h"
#include "stage/sim/sim_light_driver.h"

namespace stage::light {
namespace {

v1::LightNodeConfig TestNode() {
  auto rig = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(rig.ok());
  return rig->rig.light_nodes(0);
}

v1::ArmLightRequest Request(const std::string& take, const v1::PatternTable& table, int64_t slots = 0,
                            uint32_t heartbeat_ms = 0) {
  v1::ArmLightRequest r;
  r.set_take_id(take);
  *r.mutable_table() = table;
  r.set_take_slots(slots);
  r.set_heartbeat_timeout_ms(heartbeat_ms);
  return r;
}

// 38 rows; `lit` rows of full drive on channel 0 (led-001 parallel), the rest dark.
v1::PatternTable TableLighting(uint32_t channels, int lit, bool bunched) {
  v1::PatternTable table;
  for (int r = 0; r < 38; ++r) {
    v1::PatternRow* row = table.add_rows();
    row->set_name(absl::StrCat("p", r));
    for (uint32_t c = 0; c < channels; ++c) row->add_levels(0);
    const bool on = bunched ? r < lit : (r * lit) / 38 != ((r + 1) * lit) / 38;
    if (on) row->set_levels(0, 65535);
  }
  return table;
}

TEST(LightNodeTest, InfoAndStats) {
  v1::LightNodeConfig config = TestNode();
  auto node =
      LightNode::Create(config, std::make_unique<sim::SimLightDriver>(config.id(), config.channel_count()), "h");
  ASSERT_TRUE(node.ok()) << node.status();
  EXPECT_EQ((*node)->Info().id(), config.id());
  EXPECT_EQ((*node)->Info().kind(), v1::NODE_KIND_LIGHT);
  EXPECT_EQ((*node)->Info().backend(), "sim");
  EXPECT_EQ((*node)->Stats().mode(), v1::LIGHT_MODE_IDLE);
}

TEST(LightNodeTest, ArmLoadsTheTableStepsFromItsFirstRowAndDisarmGoesDark) {
  v1::LightNodeConfig config = TestNode();
  auto driver = std::make_unique<sim::SimLightDriver>(config.id(), config.channel_count());
  sim::SimLightDriver* sim = driver.get();
  auto node = LightNode::Create(config, std::move(driver), "h");
  ASSERT_TRUE(node.ok());
  v1::PatternTable table;
  for (int r = 0; r < 3; ++r) {
    v1::PatternRow* row = table.add_rows();
    row->set_name(absl::StrCat("p", r));
    for (uint32_t c = 0; c < config.channel_count(); ++c) row->add_levels(static_cast<uint32_t>(1000 * r + c));
  }
  ASSERT_TRUE((*node)->Arm(Request("t1", table)).ok());
  EXPECT_EQ((*node)->Stats().mode(), v1::LIGHT_MODE_ARMED);
  sim->Step();
  sim->Step();
  EXPECT_EQ(sim->Outputs()[2], 1002);  // row 1 on the second edge
  // Armed again for the next take: back to the first row, whatever it was on.
  ASSERT_TRUE((*node)->Arm(Request("t2", table)).ok());
  sim->Step();
  EXPECT_EQ(sim->Outputs()[2], 2);
  ASSERT_TRUE((*node)->Disarm("t2").ok());
  EXPECT_EQ((*node)->Stats().mode(), v1::LIGHT_MODE_IDLE);
  EXPECT_EQ(sim->Outputs()[2], 0);
  table.mutable_rows(1)->set_levels(5, 70000);
  const absl::Status bad = (*node)->Arm(Request("t3", table));
  EXPECT_TRUE(absl::IsInvalidArgument(bad));
  EXPECT_NE(bad.message().find("row 1 (p1) channel 5: level 70000 is above 65535"), std::string::npos) << bad;
}

TEST(LightNodeTest, ATableAboveAChannelsDutyOrThermalBudgetIsRefused) {
  v1::LightNodeConfig config = TestNode();  // max_duty_cycle 0.5, thermal time constant 2 s
  auto driver = std::make_unique<sim::SimLightDriver>(config.id(), config.channel_count());
  sim::SimLightDriver* sim = driver.get();
  auto node = LightNode::Create(config, std::move(driver), "h");
  ASSERT_TRUE(node.ok());
  // 20 of 38 rows at full drive: a duty of 0.526 > 0.5.
  absl::Status s = (*node)->Arm(Request("t", TableLighting(config.channel_count(), 20, false)));
  EXPECT_EQ(s.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(s.message()),
              ::testing::HasSubstr("channel 0 (led-001 parallel) would average 0.526 of full drive over the 38-row "
                                   "table, above its max_duty_cycle 0.5; not armed"));
  EXPECT_EQ((*node)->Stats().mode(), v1::LIGHT_MODE_IDLE);
  // 18 of 38 spread out (0.474, its thermal ripple small against a 2 s time constant): armed.
  ASSERT_TRUE((*node)->Arm(Request("t", TableLighting(config.channel_count(), 18, false))).ok());
  // The stats carry the armed table's load, as the controller shows it; none once disarmed.
  EXPECT_NEAR((*node)->Stats().max_channel_duty(), 18.0 / 38, 1e-9);
  EXPECT_GT((*node)->Stats().max_thermal_load(), 0.0);
  EXPECT_LT((*node)->Stats().max_thermal_load(), 1.0);
  ASSERT_TRUE((*node)->Disarm("t").ok());
  EXPECT_EQ((*node)->Stats().max_channel_duty(), 0.0);
  // Within duty on average but hotter than the limit: a thermal time constant of 2 ms (a tiny heat sink) with 19 rows
  // in a row heats the emitter to nearly full load.
  config.mutable_unit_limits()->set_thermal_time_constant_s(0.002);
  auto hot = LightNode::Create(config, std::make_unique<sim::SimLightDriver>(config.id(), config.channel_count()), "h");
  ASSERT_TRUE(hot.ok());
  s = (*hot)->Arm(Request("t", TableLighting(config.channel_count(), 19, true), 912));
  EXPECT_EQ(s.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(s.message()), ::testing::HasSubstr("would reach a thermal load of 1.000 of full drive during "
                                                             "the 1.00 s take (thermal_time_constant_s 0.002)"));
  (void)sim;
}

TEST(LightNodeTest, WithoutTheControllersHeartbeatAnArmedNodeGoesDarkAndSaysWhy) {
  v1::LightNodeConfig config = TestNode();
  auto driver = std::make_unique<sim::SimLightDriver>(config.id(), config.channel_count());
  sim::SimLightDriver* sim = driver.get();
  auto node = LightNode::Create(config, std::move(driver), "h");
  ASSERT_TRUE(node.ok());
  const v1::PatternTable table = TableLighting(config.channel_count(), 10, true);
  ASSERT_TRUE((*node)->Arm(Request("take-1", table, 0, 200)).ok());
  // Heartbeats keep it armed past its timeout...
  for (int i = 0; i < 6; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(80));
    (*node)->Heartbeat("take-1");
  }
  EXPECT_EQ((*node)->Stats().mode(), v1::LIGHT_MODE_ARMED);
  sim->Step();
  EXPECT_EQ(sim->Outputs()[0], 65535);
  // ...and their absence blacks it out within the timeout (and a poll period).
  std::this_thread::sleep_for(std::chrono::milliseconds(400));
  const v1::LightStats stats = (*node)->Stats();
  EXPECT_EQ(stats.mode(), v1::LIGHT_MODE_BLACKOUT);
  EXPECT_EQ(stats.blackout_reason(), "controller heartbeat lost: none for 200 ms while armed for take take-1");
  EXPECT_EQ(sim->Outputs()[0], 0);
  EXPECT_EQ((*node)->watchdog_trips(), 1u);
  // The take's table can no longer start, and the refusal says why (not "armed for" the take it names).
  const absl::Status late = (*node)->StartTable("take-1", 0);
  EXPECT_EQ(late.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(late.message()),
              ::testing::HasSubstr("no longer armed for take \"take-1\": in blackout (controller heartbeat lost"));
  // Latched: the next take is refused until the blackout is reset.
  const absl::Status again = (*node)->Arm(Request("take-2", table));
  EXPECT_EQ(again.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(again.message()), ::testing::HasSubstr("in blackout (controller heartbeat lost"));
  ASSERT_TRUE((*node)->ResetBlackout().ok());
  ASSERT_TRUE((*node)->Arm(Request("take-2", table)).ok());
  // Disarmed, the watchdog rests: no heartbeat needed.
  ASSERT_TRUE((*node)->Disarm("take-2").ok());
  EXPECT_THAT(std::string((*node)->StartTable("take-2", 0).message()),
              ::testing::HasSubstr("no longer armed for take \"take-2\": disarmed"));
  EXPECT_THAT(std::string((*node)->StartTable("take-3", 0).message()),
              ::testing::HasSubstr("not armed for take \"take-3\" (armed for \"take-2\")"));
  std::this_thread::sleep_for(std::chrono::milliseconds(1200));
  EXPECT_EQ((*node)->Stats().mode(), v1::LIGHT_MODE_IDLE);
  EXPECT_EQ((*node)->watchdog_trips(), 1u);
}

TEST(LightNodeTest, ChannelCountMismatchIsRefused) {
  v1::LightNodeConfig config = TestNode();
  auto node = LightNode::Create(config, std::make_unique<sim::SimLightDriver>(config.id(), 3), "h");
  EXPECT_FALSE(node.ok());
}

TEST(LightNodeTest, BackendsByName) {
  EXPECT_EQ(*ParseLightBackend("modbus"), v1::LIGHT_BACKEND_MODBUS);
  EXPECT_FALSE(ParseLightBackend("dmx").ok());
  LightBackends backends;
  RegisterHardwareLightBackends(&backends);
  LightBackendContext context;
  v1::LightNodeConfig config = TestNode();
  // The simulator's backend is registered only by a program built with it: asked for, the error names what there is.
  auto sim = backends.Create(v1::LIGHT_BACKEND_SIM, config, context);
  ASSERT_FALSE(sim.ok());
  EXPECT_THAT(std::string(sim.status().message()), ::testing::HasSubstr("this program has no sim backend (it has: "));
  EXPECT_THAT(std::string(sim.status().message()), ::testing::HasSubstr(config.id()));
  // The shipped rig's boards are not on this machine's network: the error names the board, with no fallback.
  auto modbus = backends.Create(v1::LIGHT_BACKEND_MODBUS, config, context);
  ASSERT_FALSE(modbus.ok());
  EXPECT_THAT(std::string(modbus.status().message()),
              ::testing::AnyOf(::testing::HasSubstr("led-board-1.stage.lan"),
                               ::testing::HasSubstr("this program has no modbus backend")));
  // A gpiod node on a chip this machine does not have: the error names the node and the chip.
  config.set_backend(v1::LIGHT_BACKEND_GPIOD);
  auto* g = config.mutable_gpiod();
  g->set_chip("gpiochip-fastage-absent");
  for (uint32_t c = 0; c < config.channel_count(); ++c) g->add_channel_lines(c);
  g->set_slot_clock_line(config.channel_count());
  auto gpiod = backends.Create(v1::LIGHT_BACKEND_GPIOD, config, context);
  ASSERT_FALSE(gpiod.ok());
  EXPECT_THAT(std::string(gpiod.status().message()), ::testing::HasSubstr(config.id()));
  EXPECT_THAT(std::string(gpiod.status().message()),
              ::testing::AnyOf(::testing::HasSubstr("gpiochip-fastage-absent"),
                               ::testing::HasSubstr("this build has no gpiod backend")));
  // Without its slot clock line the options are refused by name.
  g->clear_slot_clock_line();
  auto no_clock = backends.Create(v1::LIGHT_BACKEND_GPIOD, config, context);
  ASSERT_FALSE(no_clock.ok());
  EXPECT_THAT(std::string(no_clock.status().message()), ::testing::HasSubstr("gpiod.slot_clock_line"));
}

}  // namespace
}  // namespace stage::light

namespace stage::light {
namespace {

using std::chrono::milliseconds;

TEST(HeartbeatWatchTest, ExpiresAfterTheTimeoutOfTheNodesRunningTime) {
  HeartbeatWatch w(milliseconds(1000));
  EXPECT_EQ(w.tick(), milliseconds(100));
  const auto t0 = HeartbeatWatch::Clock::time_point() + std::chrono::hours(1);
  w.Beat(t0);
  // Looking every tick, as a running node does: the controller is gone after the timeout.
  auto t = t0;
  for (int i = 1; i < 10; ++i) {
    t = t0 + i * w.tick();
    EXPECT_FALSE(w.Expired(t)) << i;
  }
  EXPECT_TRUE(w.Expired(t0 + milliseconds(1000)));
  // A heartbeat puts it off by a full timeout.
  w.Beat(t0 + milliseconds(1000));
  EXPECT_FALSE(w.Expired(t0 + milliseconds(1050)));
  EXPECT_EQ(w.NextLook(t0 + milliseconds(1050)), t0 + milliseconds(1150));
  EXPECT_EQ(w.NextLook(t0 + milliseconds(1950)), t0 + milliseconds(2000));
}

TEST(HeartbeatWatchTest, TimeTheNodeDidNotRunCountsAgainstNobody) {
  // The node's process is stopped for 10 s (SIGSTOP, a starved machine): when it runs again the controller has a
  // full timeout for its heartbeats (they may be waiting to be read) before the lights go dark.
  HeartbeatWatch w(milliseconds(1000));
  const auto t0 = HeartbeatWatch::Clock::time_point() + std::chrono::hours(1);
  w.Beat(t0);
  EXPECT_FALSE(w.Expired(t0 + milliseconds(100)));
  EXPECT_FALSE(w.Expired(t0 + milliseconds(10100)));  // back after 10 s away
  EXPECT_FALSE(w.Expired(t0 + milliseconds(10200)));
  // Without heartbeats it still goes dark: a timeout of running time after the last one.
  auto t = t0 + milliseconds(10200);
  bool expired = false;
  while (!expired && t < t0 + milliseconds(12000)) {
    t += w.tick();
    expired = w.Expired(t);
  }
  EXPECT_TRUE(expired);
  // 100 ms ran before the stop, the gap counts as one tick, 800 ms after it.
  EXPECT_EQ(t, t0 + milliseconds(10900));
}

TEST(HeartbeatWatchTest, OnlyOneAbsenceIsForgivenBetweenHeartbeats) {
  // A node starved again and again while the controller is gone: the second absence counts, and the lights go dark
  // within the timeout plus one absence.
  HeartbeatWatch w(milliseconds(1000));
  const auto t0 = HeartbeatWatch::Clock::time_point() + std::chrono::hours(1);
  w.Beat(t0);
  EXPECT_FALSE(w.Expired(t0 + milliseconds(5000)));  // away 5 s: forgiven
  EXPECT_TRUE(w.Expired(t0 + milliseconds(10000)));  // away 5 s again, no heartbeat between: not
  // A heartbeat between two absences forgives the next one again.
  w.Beat(t0 + milliseconds(20000));
  EXPECT_FALSE(w.Expired(t0 + milliseconds(25000)));
  w.Beat(t0 + milliseconds(25050));
  EXPECT_FALSE(w.Expired(t0 + milliseconds(30000)));
}

TEST(HeartbeatWatchTest, ALateLookWithinAFewTicksIsNotAnAbsence) {
  // A loaded machine wakes the watchdog late; that is not the node being away, and it does not postpone the verdict.
  HeartbeatWatch w(milliseconds(1000));
  const auto t0 = HeartbeatWatch::Clock::time_point() + std::chrono::hours(1);
  w.Beat(t0);
  EXPECT_FALSE(w.Expired(t0 + milliseconds(250)));
  EXPECT_FALSE(w.Expired(t0 + milliseconds(500)));
  EXPECT_FALSE(w.Expired(t0 + milliseconds(750)));
  EXPECT_TRUE(w.Expired(t0 + milliseconds(1000)));
}

}  // namespace
}  // namespace stage::light
