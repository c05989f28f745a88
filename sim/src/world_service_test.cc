// The world over gRPC: devices in other processes (here: other clients) run lockstep through SimWorld, and a device
// whose connection goes away is let go.
#include "stage/sim/world_service.h"

#include <grpcpp/grpcpp.h>

#include <thread>

#include "gtest/gtest.h"
#include "stage/common/rpc_server.h"
#include "stage/sim/world_client.h"

namespace stage::sim {
namespace {

TEST(WorldServiceTest, LockstepThroughTheServiceAndADeviceThatDisconnectsIsLetGo) {
  Dome dome = Dome::FromDirections(FibonacciSphere(4), 1000);
  for (auto& u : dome.units) u.node = 0;
  World world(dome, {.slot_rate_hz = 912, .lockstep = true, .rise_ns = {0}, .fall_ns = {0}});
  v1::WorldInfo info;
  info.set_slot_rate_hz(912);
  info.set_lockstep(true);
  WorldService service(&world, info);
  auto server = RpcServer::Start({.listen = "127.0.0.1:0"}, {&service});
  ASSERT_TRUE(server.ok());

  auto lights = ConnectWorld((*server)->address());
  auto camera = ConnectWorld((*server)->address());
  ASSERT_TRUE(lights.ok() && camera.ok());
  auto light_device = (*lights)->Join("lights-a", 0);
  auto camera_device = (*camera)->Join("cam-a", -1);
  ASSERT_TRUE(light_device.ok() && camera_device.ok());
  EXPECT_EQ((*camera)->slot_rate_hz(), 912u);
  EXPECT_TRUE((*camera)->lockstep());
  world.Start();

  const int64_t slots = 20;
  std::thread light_thread([&] {
    for (int64_t k = 0; k < slots; ++k) {
      auto edge = (*lights)->WaitForEdge(*light_device, k);
      ASSERT_TRUE(edge.has_value());
      std::vector<double> levels(8, 0.0);
      levels[static_cast<size_t>(2 * (k % 4))] = 1.0;  // unit k mod 4's parallel emitter
      (*lights)->ReportLevels(0, edge->time_ns, levels, world.EdgeNs(k + 1));
    }
  });
  for (int64_t k = 0; k < slots; ++k) {
    auto edge = (*camera)->WaitForEdge(*camera_device, k);
    ASSERT_TRUE(edge.has_value());
    EXPECT_EQ(edge->time_ns, world.EdgeNs(k));
    auto levels = (*camera)->Exposure(edge->time_ns + 100'000, edge->time_ns + 900'000);
    ASSERT_TRUE(levels.ok()) << levels.status();
    for (int u = 0; u < 4; ++u) EXPECT_FLOAT_EQ(levels->parallel[u], u == k % 4 ? 1.0f : 0.0f) << k;
  }
  light_thread.join();

  // The light node's process goes away: its connection closes; the world lets it go and nobody waits for it.
  lights->reset();
  auto edge = (*camera)->WaitForEdge(*camera_device, slots + 5);
  ASSERT_TRUE(edge.has_value());
  auto levels = (*camera)->Exposure(edge->time_ns, edge->time_ns + 500'000);
  ASSERT_TRUE(levels.ok()) << levels.status();
  for (int u = 0; u < 4; ++u) EXPECT_FLOAT_EQ(levels->parallel[u], 0.0f);
  world.Stop();
  service.Shutdown();
}

}  // namespace
}  // namespace stage::sim
