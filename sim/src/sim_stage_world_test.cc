// The whole simulated stage in one process, in lockstep: the shipped 27-camera rig's light nodes step through their
// tables on the world's slot clock, every camera is triggered by the world's bus and renders what the LEDs did.
// Checked: frame counts per camera over 2 virtual frames (76 slots), each frame's counter and device timestamp, that
// each frame shows the pattern of its slot (and no other), and that a light node that is killed leaves its units dark.
#include <chrono>
#include <condition_variable>
#include <map>
#include <mutex>
#include <set>
#include <thread>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/clock.h"
#include "stage/common/rig.h"
#include "stage/sim/world_devices.h"
#include "stage/timing/schedule.h"

namespace stage::sim {
namespace {

constexpr int64_t kSlots = 76;  // two virtual frames of fastage-38

class Sink : public camera::FrameSink {
 public:
  void OnFrame(std::shared_ptr<const camera::Frame> frame) override {
    std::lock_guard<std::mutex> lock(mutex_);
    frames_.push_back(std::move(frame));
    cv_.notify_all();
  }
  std::vector<std::shared_ptr<const camera::Frame>> WaitFor(size_t n) {
    std::unique_lock<std::mutex> lock(mutex_);
    cv_.wait_for(lock, std::chrono::seconds(120), [&] { return frames_.size() >= n; });
    return frames_;
  }

 private:
  std::mutex mutex_;
  std::condition_variable cv_;
  std::vector<std::shared_ptr<const camera::Frame>> frames_;
};

std::shared_ptr<const SimScene> ShippedScene(const std::function<void(v1::RigConfig*)>& change = nullptr) {
  auto loaded = LoadRig(kBuiltinRigName);
  EXPECT_TRUE(loaded.ok()) << loaded.status();
  // Small images keep the test quick; the physics does not depend on the scale.
  auto small = ApplyRigOverrides(*loaded, {"sim.render_scale=0.03"});
  EXPECT_TRUE(small.ok()) << small.status();
  if (change) {
    change(&small->rig);
    for (const RigError& e : ValidateRig(small->rig, small->base_dir)) ADD_FAILURE() << e.path << ": " << e.message;
  }
  auto scene = SimScene::FromLoadedRig(*small);
  EXPECT_TRUE(scene.ok()) << scene.status();
  return *scene;
}

// Mean digital number over each cell of a 4x4 grid, on the pixels that see the subject: a signature of the image
// whose noise averages out.
std::vector<double> Signature(const PixelResponses& r, const std::function<double(int32_t)>& value) {
  std::vector<double> sum(16, 0), count(16, 0);
  for (int32_t pixel : r.pixels) {
    const int x = pixel % r.width, y = pixel / r.width;
    const int cell = (y * 4 / r.height) * 4 + x * 4 / r.width;
    sum[cell] += value(pixel);
    count[cell] += 1;
  }
  for (int c = 0; c < 16; ++c) sum[c] = count[c] > 20 ? sum[c] / count[c] : 0;
  return sum;
}

// What camera `index` should read out under `levels`, as a signature.
std::vector<double> ExpectedSignature(const SimScene& scene, CameraRenderer& renderer, const EmitterLevels& levels,
                                      int64_t pose_frame) {
  const int index = renderer.camera_index();
  const PixelResponses& r = *renderer.Responses(pose_frame);
  const std::vector<float> rgb = RenderRadiance(r, levels, scene.leakage(index));
  const SensorParams& s = scene.sensor(index);
  const double exposure_s = scene.base().TicksToNs(scene.schedule().cameras(index).exposure_ticks()) * 1e-9;
  const double scale = s.electrons_per_radiance_s * exposure_s / s.Gain();
  return Signature(r, [&](int32_t pixel) {
    const int color = MosaicColor(s.mosaic, pixel % r.width, pixel / r.width);
    return s.black_level_dn + rgb[3 * static_cast<size_t>(pixel) + static_cast<size_t>(color)] * scale;
  });
}

// The worst cell's difference relative to the expected value, or to 20 DN (a fifth of full-on white) where that is
// darker: dim cells have few digital numbers to compare.
double Distance(const std::vector<double>& a, const std::vector<double>& b) {
  double worst = 0;
  for (size_t i = 0; i < a.size(); ++i) worst = std::max(worst, std::abs(a[i] - b[i]) / std::max(20.0, b[i]));
  return worst;
}

struct Stage {
  std::shared_ptr<const SimScene> scene;
  std::unique_ptr<World> world;
  std::unique_ptr<WorldClient> client;
  std::vector<std::unique_ptr<SimLightDriver>> lights;
  std::vector<std::unique_ptr<Sink>> sinks;
  std::vector<std::unique_ptr<SimCameraDevice>> cameras;
  std::vector<std::shared_ptr<CameraRenderer>> renderers;
  // Renderers of every unit's responses, for what a frame should show under any exposure (the cameras' own sum each
  // pose's responses under the patterns of their slots alone).
  std::vector<std::shared_ptr<CameraRenderer>> references;
  SimClock clock;
};

// The shipped rig's stage in one lockstep world: one run of kSlots from slot 0, or (takes) none until Run().
void BuildStage(Stage* stage, const std::function<void(v1::RigConfig*)>& change = nullptr, bool takes = false) {
  stage->scene = ShippedScene(change);
  const SimScene& scene = *stage->scene;
  WorldOptions options = scene.MakeWorldOptions(/*lockstep=*/true, 0);
  options.end_slot = takes ? -1 : kSlots;
  options.open_run = !takes;
  stage->world = std::make_unique<World>(scene.dome(), options);
  ApplyUnitFaults(scene, stage->world.get());
  stage->client = LocalWorldClient(stage->world.get());
  for (const v1::LightNodeConfig& n : scene.rig().light_nodes()) {
    auto driver = std::make_unique<SimLightDriver>(n.id(), n.channel_count());
    ASSERT_TRUE(JoinLightNode(driver.get(), scene, n.id(), stage->client.get()).ok());
    stage->lights.push_back(std::move(driver));
  }
  for (const v1::CameraConfig& c : scene.rig().cameras()) {
    auto device = std::make_unique<SimCameraDevice>(&stage->clock, c.id());
    ASSERT_TRUE(device
                    ->Configure({.width = c.width(),
                                 .height = c.height(),
                                 .pixel_format = PixelFormatName(c.pixel_format()),
                                 .frame_rate_hz = c.frame_rate_hz(),
                                 .exposure_us = c.exposure_us(),
                                 .gain_db = c.gain_db(),
                                 .trigger = camera::TriggerMode::kHardware})
                    .ok());
    auto world = CameraWorld(stage->scene, c.id(), stage->client.get());
    ASSERT_TRUE(world.ok()) << world.status();
    stage->renderers.push_back(world->renderer);
    stage->references.push_back(std::make_shared<CameraRenderer>(stage->scene, world->renderer->camera_index()));
    ASSERT_TRUE(device->AttachWorld(*world).ok());
    stage->sinks.push_back(std::make_unique<Sink>());
    ASSERT_TRUE(device->Start(stage->sinks.back().get()).ok());
    stage->cameras.push_back(std::move(device));
  }
}

// What camera `index`'s frame of slot `slot` shows, and what it should show with light node 0 lit and dark, as
// signatures.
struct LitOrDark {
  std::vector<double> seen, lit, dark;
};
LitOrDark NodeZeroSignatures(const Stage& stage, int index, const camera::Frame& frame, int64_t slot) {
  const int64_t pose = slot / 38;
  CameraRenderer& renderer = *stage.references[static_cast<size_t>(index)];
  const PixelResponses& r = *renderer.Responses(pose);
  LitOrDark out;
  out.seen = Signature(r, [&](int32_t pixel) { return static_cast<double>(frame.data[static_cast<size_t>(pixel)]); });
  out.lit = ExpectedSignature(*stage.scene, renderer, stage.scene->PatternLevels(slot % 38), pose);
  out.dark = ExpectedSignature(*stage.scene, renderer, stage.scene->PatternLevels(slot % 38, /*dark_node=*/0), pose);
  return out;
}

TEST(SimStageWorldTest, TheFullRigInLockstepDeliversEveryFrameShowingThePatternOfItsSlot) {
  Stage stage;
  ASSERT_NO_FATAL_FAILURE(BuildStage(&stage));
  const SimScene& scene = *stage.scene;
  ASSERT_EQ(scene.rig().cameras_size(), 27);
  stage.world->Start();

  const int64_t cycle = timing::CycleLength(scene.schedule());
  ASSERT_EQ(cycle, 38);
  int checked_high_speed = 0;
  for (int i = 0; i < scene.rig().cameras_size(); ++i) {
    const v1::CameraTiming& t = scene.schedule().cameras(i);
    const bool hs = scene.rig().cameras(i).role() == v1::CAMERA_ROLE_HIGH_SPEED;
    const size_t expected = hs ? kSlots : kSlots / 38;
    auto frames = stage.sinks[i]->WaitFor(expected);
    ASSERT_EQ(frames.size(), expected) << t.id();
    const auto stats = stage.cameras[i]->world_stats();
    EXPECT_EQ(stats.missed_triggers, 0u) << t.id();
    EXPECT_EQ(stats.render_errors, 0u) << t.id();
    for (size_t f = 0; f < frames.size(); ++f) {
      const camera::Frame& frame = *frames[f];
      const int64_t slot = hs ? static_cast<int64_t>(f) : 19 + 38 * static_cast<int64_t>(f);
      // The head moves from one virtual frame to the next: expected images of every pattern in this one.
      const int64_t pose = slot / cycle;
      static thread_local std::map<int64_t, std::vector<std::vector<double>>> by_pose;
      if (f == 0) by_pose.clear();
      auto& expected_by_pattern = by_pose[pose];
      if (expected_by_pattern.empty()) {
        for (int64_t p = 0; p < cycle; ++p) {
          expected_by_pattern.push_back(ExpectedSignature(scene, *stage.references[i], scene.PatternLevels(p), pose));
        }
      }
      const PixelResponses& r = *stage.references[i]->Responses(pose);
      // The camera's own renderer summed the pose's responses under its slots' patterns (a machine-vision camera's
      // one, a high-speed camera's 38), and every exposure the world gave it was one of them.
      const PixelResponses& own_sums = *stage.renderers[i]->Responses(pose);
      ASSERT_NE(own_sums.basis, nullptr) << t.id();
      EXPECT_EQ(own_sums.diffuse.cols(), hs ? 38 : 1) << t.id();
      ASSERT_GT(r.pixels.size(), 300u) << t.id() << " sees too little of the subject to check";
      ASSERT_TRUE(timing::FiresInSlot(t, slot));
      EXPECT_EQ(frame.frame_id, f) << t.id();
      EXPECT_EQ(frame.device_timestamp_ns, scene.base().SlotStartNs(slot) + scene.base().TicksToNs(t.trigger_ticks()))
          << t.id() << " frame " << f;
      ASSERT_EQ(static_cast<int>(frame.width), r.width);
      ASSERT_EQ(frame.data.size(), static_cast<size_t>(r.width) * r.height);
      const std::vector<double> seen =
          Signature(r, [&](int32_t pixel) { return static_cast<double>(frame.data[static_cast<size_t>(pixel)]); });
      // Its own pattern within 2 % in every cell (noise and rounding average out over a cell's pixels) ...
      const int64_t own = slot % cycle;
      EXPECT_LT(Distance(seen, expected_by_pattern[own]), 0.02) << t.id() << " frame " << f << " slot " << slot;
      // ... and every other pattern further off: a frame tagged one slot off would be caught.
      for (int64_t p = 0; p < cycle; ++p) {
        if (p == own) continue;
        EXPECT_GT(Distance(seen, expected_by_pattern[p]), 0.04)
            << t.id() << " frame " << f << " (" << scene.schedule().patterns(own).name() << ") looks like pattern "
            << scene.schedule().patterns(p).name();
      }
    }
    if (hs) ++checked_high_speed;
  }
  EXPECT_EQ(checked_high_speed, 3);
  for (auto& c : stage.cameras) ASSERT_TRUE(c->Stop().ok());
}

TEST(SimStageWorldTest, AKilledLightNodeLeavesItsUnitsDarkInTheImages) {
  Stage stage;
  ASSERT_NO_FATAL_FAILURE(BuildStage(&stage));
  const SimScene& scene = *stage.scene;
  // Kill light node 0 once the world reaches slot 38: a watcher device holds the world there while it does.
  const int watcher = stage.world->Register("watcher");
  stage.world->Start();
  auto edge = stage.world->WaitForEdge(watcher, 38);
  ASSERT_TRUE(edge.has_value());
  stage.lights[0]->DetachWorld();
  stage.world->Done(watcher, kSlots);

  const int hs = scene.CameraIndex("hs-2");
  ASSERT_GE(hs, 0);
  auto frames = stage.sinks[hs]->WaitFor(kSlots);
  ASSERT_EQ(frames.size(), static_cast<size_t>(kSlots));
  int dark_frames = 0;
  for (int64_t f = 0; f < kSlots; ++f) {
    if (f == 38 || f == 39) continue;  // the node left while these were being lit
    const auto [seen, lit, dark] = NodeZeroSignatures(stage, hs, *frames[f], f);
    if (f < 38) {
      EXPECT_LT(Distance(seen, lit), 0.02) << "frame " << f;
    } else {
      EXPECT_LT(Distance(seen, dark), 0.02) << "frame " << f;
      // Where node 0's units mattered, the frame must differ from the lit image.
      if (Distance(lit, dark) > 0.05) {
        EXPECT_GT(Distance(seen, lit), 0.04) << "frame " << f;
        ++dark_frames;
      }
    }
  }
  EXPECT_GT(dark_frames, 20) << "node 0 lights too little of what hs-2 sees for the check to mean anything";
  for (auto& c : stage.cameras) ASSERT_TRUE(c->Stop().ok());
}

TEST(SimStageWorldTest, FaultsFromTheRigShowAsTheyWould) {
  Stage stage;
  ASSERT_NO_FATAL_FAILURE(BuildStage(&stage, [](v1::RigConfig* rig) {
    // Every unit of the first light node dead: its light is gone from every image.
    for (const auto& u : rig->light_nodes(0).units()) {
      auto* f = rig->mutable_sim()->add_faults();
      f->set_target(u.id());
      f->set_dead(true);
    }
    auto* hs = rig->mutable_sim()->add_faults();
    hs->set_target("hs-1");
    hs->set_miss_triggers(0.2);
    hs->set_drop_frames(0.1);
    hs->set_clock_offset_us(500);
    hs->set_clock_drift_ppm(100);
    auto* mv = rig->mutable_sim()->add_faults();
    mv->set_target("mv-01");
    mv->set_crash_at_s(0.03);  // after its first frame (slot 19), before its second (slot 57)
  }));
  const SimScene& scene = *stage.scene;
  stage.world->Start();

  // hs-1 misses about a fifth of its triggers and loses about a tenth of what it exposed; every slot is accounted for.
  const int hs1 = scene.CameraIndex("hs-1");
  SimCameraWorldStats stats;
  for (int i = 0; i < 600; ++i) {
    stats = stage.cameras[hs1]->world_stats();
    if (stats.triggers + stats.missed_triggers == kSlots && stats.frames + stats.dropped_frames == stats.triggers)
      break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_EQ(stats.triggers + stats.missed_triggers, static_cast<uint64_t>(kSlots));
  EXPECT_EQ(stats.frames + stats.dropped_frames, stats.triggers);
  EXPECT_GT(stats.missed_triggers, 5u);
  EXPECT_LT(stats.missed_triggers, 30u);
  EXPECT_GT(stats.dropped_frames, 0u);
  auto frames = stage.sinks[hs1]->WaitFor(stats.frames);
  ASSERT_EQ(frames.size(), stats.frames);
  // Counters have gaps where frames were dropped, never where triggers were missed; timestamps carry the clock fault.
  const int64_t trigger_ns = scene.base().TicksToNs(scene.schedule().cameras(hs1).trigger_ticks());
  std::set<int64_t> slots_seen;
  for (const auto& f : frames) {
    // Recover the slot from the timestamp: device = world * (1 + 100 ppm) + 500 us.
    const long double world_ns = (f->device_timestamp_ns - 500'000) / (1 + 100e-6L);
    const int64_t slot = scene.base().SlotAtNs(static_cast<int64_t>(std::llround(world_ns)));
    EXPECT_EQ(
        f->device_timestamp_ns,
        static_cast<int64_t>(static_cast<long double>(scene.base().SlotStartNs(slot) + trigger_ns) * (1 + 100e-6L)) +
            500'000);
    slots_seen.insert(slot);
  }
  EXPECT_EQ(slots_seen.size(), frames.size());
  for (size_t i = 1; i < frames.size(); ++i) EXPECT_GT(frames[i]->frame_id, frames[i - 1]->frame_id);
  EXPECT_LT(frames.back()->frame_id, stats.triggers);

  // mv-01 crashed after its first frame.
  const int mv1 = scene.CameraIndex("mv-01");
  const int mv2 = scene.CameraIndex("mv-02");
  ASSERT_EQ(stage.sinks[mv2]->WaitFor(2).size(), 2u);
  EXPECT_EQ(stage.sinks[mv1]->WaitFor(1).size(), 1u);

  // hs-2's images show node 0's units dark from the first slot.
  const int hs2 = scene.CameraIndex("hs-2");
  auto seen_frames = stage.sinks[hs2]->WaitFor(kSlots);
  ASSERT_EQ(seen_frames.size(), static_cast<size_t>(kSlots));
  int differs = 0;
  for (int64_t f = 0; f < kSlots; ++f) {
    const auto [seen, lit, dark] = NodeZeroSignatures(stage, hs2, *seen_frames[f], f);
    EXPECT_LT(Distance(seen, dark), 0.02) << "frame " << f;
    differs += Distance(lit, dark) > 0.05;
  }
  EXPECT_GT(differs, 20);
  for (auto& c : stage.cameras) ASSERT_TRUE(c->Stop().ok());
}

TEST(SimStageWorldTest, FaultsInjectedAtRunTimeTakeEffectFromTheNextEdge) {
  Stage stage;
  ASSERT_NO_FATAL_FAILURE(BuildStage(&stage));
  const SimScene& scene = *stage.scene;
  World& world = *stage.world;
  // A device of the test's own holds the world at slot 38 while the faults go in, as `stagectl sim fault` would
  // while the stage runs.
  constexpr int64_t kAt = 38, kLateAt = 66;
  const int me = world.Register("test", -1);
  std::vector<absl::Status> injected;
  std::thread injector([&] {
    ASSERT_TRUE(world.WaitForEdge(me, kAt).has_value());
    for (const auto& u : scene.rig().light_nodes(0).units()) {
      v1::SimFault dead;
      dead.set_target(u.id());
      dead.set_dead(true);
      injected.push_back(world.InjectFault(dead));
    }
    v1::SimFault drop;
    drop.set_target("hs-1");
    drop.set_drop_frames(1);
    injected.push_back(world.InjectFault(drop));
    v1::SimFault clock;
    clock.set_target("hs-3");
    clock.set_clock_offset_us(1000);
    injected.push_back(world.InjectFault(clock));
    v1::SimFault nobody;
    nobody.set_target("hs-99");
    const absl::Status not_found = world.InjectFault(nobody);
    world.Done(me, kAt);
    // Later, a light node goes late (it would blend the patterns of the frames above).
    ASSERT_TRUE(world.WaitForEdge(me, kLateAt).has_value());
    v1::SimFault late;
    late.set_target(scene.rig().light_nodes(1).id());
    late.set_delay_us(300);
    injected.push_back(world.InjectFault(late));
    injected.push_back(not_found);
    world.Unregister(me);
  });
  world.Start();
  injector.join();
  ASSERT_FALSE(injected.empty());
  for (size_t i = 0; i + 1 < injected.size(); ++i) EXPECT_TRUE(injected[i].ok()) << injected[i];
  EXPECT_TRUE(absl::IsNotFound(injected.back())) << injected.back();

  // hs-1 loses every frame from the next edge it takes after the injection on.
  const int hs1 = scene.CameraIndex("hs-1");
  SimCameraWorldStats stats;
  for (int i = 0; i < 600; ++i) {
    stats = stage.cameras[hs1]->world_stats();
    if (stats.frames + stats.dropped_frames == kSlots) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_EQ(stats.frames + stats.dropped_frames, static_cast<uint64_t>(kSlots));
  // A lockstep camera lets the world run up to two slots ahead of the edges it has taken (for its exposure's light),
  // so the edge it takes next may be slot 37 or 38 or 39.
  EXPECT_GE(stats.frames, static_cast<uint64_t>(kAt - 1));
  EXPECT_LE(stats.frames, static_cast<uint64_t>(kAt + 1));

  // hs-3's clock jumps by 1 ms from there on.
  const int hs3 = scene.CameraIndex("hs-3");
  auto frames = stage.sinks[hs3]->WaitFor(kSlots);
  ASSERT_EQ(frames.size(), static_cast<size_t>(kSlots));
  const int64_t trigger_ns = scene.base().TicksToNs(scene.schedule().cameras(hs3).trigger_ticks());
  for (int64_t k = 0; k < kSlots; ++k) {
    const int64_t offset = frames[k]->device_timestamp_ns - (scene.base().SlotStartNs(k) + trigger_ns);
    if (k < kAt - 1) {
      EXPECT_EQ(offset, 0) << "slot " << k;
    } else if (k > kAt) {
      EXPECT_EQ(offset, 1'000'000) << "slot " << k;
    }
  }

  // hs-2 sees node 0's units lit early on and dark after the injection (frames still in the renderer's queue at the
  // injection may go either way: the units' state is the world's, not a time line).
  const int hs2 = scene.CameraIndex("hs-2");
  auto seen_frames = stage.sinks[hs2]->WaitFor(kSlots);
  ASSERT_EQ(seen_frames.size(), static_cast<size_t>(kSlots));
  int checked = 0;
  for (int64_t f = 0; f < kSlots; ++f) {
    if ((f >= 20 && f <= kAt + 1) || f >= kLateAt) continue;
    const auto [seen, lit, dark] = NodeZeroSignatures(stage, hs2, *seen_frames[f], f);
    if (Distance(lit, dark) < 0.05) continue;  // node 0 adds little to this pattern here
    EXPECT_LT(Distance(seen, f < kAt ? lit : dark), 0.02) << "frame " << f;
    ++checked;
  }
  EXPECT_GT(checked, 20);

  // Node 1 switches 300 us late after its injection: just past its usual switch in slot 70, its units still show
  // slot 69's pattern.
  const int64_t edge = world.EdgeNs(70) + scene.SwitchDelayNs(1);
  auto levels = world.Exposure(edge + 20'000, edge + 200'000);
  ASSERT_TRUE(levels.ok()) << levels.status();
  const EmitterLevels before = scene.PatternLevels(69 % 38), after = scene.PatternLevels(70 % 38);
  int node1_units = 0, like_before = 0;
  for (size_t u = 0; u < scene.dome().units.size(); ++u) {
    if (scene.dome().units[u].node != 1) continue;
    ++node1_units;
    const auto e = static_cast<Eigen::Index>(u);
    auto check = [&](const Eigen::VectorXf& seen, const Eigen::VectorXf& was, const Eigen::VectorXf& next) {
      if (std::abs(seen[e] - was[e]) < 1e-6f && std::abs(was[e] - next[e]) > 1e-3f) ++like_before;
    };
    check(levels->cross, before.cross, after.cross);
    check(levels->parallel, before.parallel, after.parallel);
  }
  EXPECT_GT(node1_units, 0);
  EXPECT_GT(like_before, 0);
  for (auto& c : stage.cameras) ASSERT_TRUE(c->Stop().ok());

  // The scene vets a fault's fields as the rig file's are vetted.
  v1::SimFault bad;
  bad.set_target("hs-1");
  bad.set_delay_us(5);
  EXPECT_THAT(scene.CheckFault(bad).message(), ::testing::HasSubstr("fault.delay_us: applies to an LED unit"));
  bad.set_target("led-999");
  EXPECT_THAT(scene.CheckFault(bad).message(), ::testing::HasSubstr("fault.target: \"led-999\""));
}

// Takes as runs of the bus: nothing is exposed before the first run; a high-speed camera fires in every slot of each
// run, a machine-vision camera in slot 19 of each run counted from the run's first slot (its trigger line restarts at
// each T0), and the second run, asked to start on a cycle boundary, leaves the slots between silent.
TEST(SimStageWorldTest, TakesAreRunsOfTheBusAndDividedTriggersCountFromEachRun) {
  Stage stage;
  ASSERT_NO_FATAL_FAILURE(BuildStage(&stage, nullptr, /*takes=*/true));
  const SimScene& scene = *stage.scene;
  stage.world->Start();
  const int hs1 = scene.CameraIndex("hs-1"), mv1 = scene.CameraIndex("mv-01");
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  EXPECT_EQ(stage.cameras[hs1]->world_stats().triggers, 0u);  // no run: a silent bus
  auto first = stage.world->Run(40);
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_EQ(stage.sinks[hs1]->WaitFor(40).size(), 40u);
  auto second = stage.world->Run(38, 0, 38);
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_EQ(second->first, 76);
  auto hs = stage.sinks[hs1]->WaitFor(78);
  ASSERT_EQ(hs.size(), 78u);
  auto mv = stage.sinks[mv1]->WaitFor(2);
  ASSERT_EQ(mv.size(), 2u);
  const int64_t mv_trigger = scene.base().TicksToNs(scene.schedule().cameras(mv1).trigger_ticks());
  EXPECT_EQ(mv[0]->device_timestamp_ns, scene.base().SlotStartNs(19) + mv_trigger);
  EXPECT_EQ(mv[1]->device_timestamp_ns, scene.base().SlotStartNs(76 + 19) + mv_trigger);
  const int64_t hs_trigger = scene.base().TicksToNs(scene.schedule().cameras(hs1).trigger_ticks());
  EXPECT_EQ(hs[39]->device_timestamp_ns, scene.base().SlotStartNs(39) + hs_trigger);
  EXPECT_EQ(hs[40]->device_timestamp_ns, scene.base().SlotStartNs(76) + hs_trigger);  // 40..75 were silent
  EXPECT_EQ(stage.cameras[hs1]->world_stats().missed_triggers, 0u);
  for (auto& c : stage.cameras) ASSERT_TRUE(c->Stop().ok());
  stage.world->Stop();
}

TEST(SimStageWorldTest, FaultsNameWhatTheyHitAndOnlyWhatTheyCanHit) {
  auto loaded = LoadRig(kBuiltinRigName);
  ASSERT_TRUE(loaded.ok());
  v1::RigConfig rig = loaded->rig;
  auto* f = rig.mutable_sim()->add_faults();
  f->set_target("led-999");
  auto* g = rig.mutable_sim()->add_faults();
  g->set_target("hs-1");
  g->set_dead(true);
  auto* h = rig.mutable_sim()->add_faults();
  h->set_target("mv-01");
  h->set_drop_frames(1.5);
  auto* u = rig.mutable_sim()->add_faults();
  u->set_target(rig.light_nodes(0).id());
  u->add_drop_slots(3);
  std::vector<std::string> errors;
  for (const RigError& e : ValidateRig(rig, loaded->base_dir)) errors.push_back(e.path + ": " + e.message);
  EXPECT_THAT(errors, ::testing::Contains(::testing::HasSubstr("sim.faults[0].target: \"led-999\" is no LED unit")));
  EXPECT_THAT(errors, ::testing::Contains(::testing::HasSubstr("sim.faults[1].dead: only an LED unit can be dead")));
  EXPECT_THAT(errors, ::testing::Contains(::testing::HasSubstr("sim.faults[2].drop_frames: 1.5 is not in [0, 1]")));
  EXPECT_THAT(errors, ::testing::Contains(::testing::HasSubstr("sim.faults[3].drop_slots: applies to a camera")));
}

}  // namespace
}  // namespace stage::sim
