// The simulator's node backends: see node_backends.h.
#include "stage/sim/node_backends.h"

#include "stage/common/logging.h"
#include "stage/common/status.h"
#include "stage/sim/sim_camera_device.h"
#include "stage/sim/sim_light_driver.h"
#include "stage/sim/world_devices.h"
#include "stage/sim/world_slot_clock.h"

namespace stage::sim {

void RegisterSimLightBackend(light::LightBackends* backends, std::function<void()> on_crash) {
  backends->Register(v1::LIGHT_BACKEND_SIM,
                     [on_crash](const v1::LightNodeConfig& config,
                                const light::LightBackendContext& context) -> absl::StatusOr<light::LightBackendParts> {
                       auto driver = std::make_unique<SimLightDriver>(config.id(), config.channel_count());
                       light::LightBackendParts parts;
                       if (!context.world_address.empty()) {
                         // In stage-sim's world: the node steps on the world's bus and lights the dome; the rig's sync
                         // generator node drives that bus (its clock line is the bus).
                         STAGE_ASSIGN_OR_RETURN(NodeWorld opened, OpenNodeWorld(*context.rig, context.world_address));
                         auto world = std::make_shared<NodeWorld>(std::move(opened));
                         STAGE_RETURN_IF_ERROR(JoinLightNode(driver.get(), *world->scene, config.id(),
                                                             world->client.get(), on_crash, context.self_arm));
                         if (context.rig->rig.timing().sync_generator() == config.id()) {
                           parts.slot_clock = NewWorldSlotClock(context.world_address, config.id());
                         }
                         parts.keep = world;
                       }
                       parts.driver = std::move(driver);
                       return parts;
                     });
}

void RegisterSimCameraBackend(camera::CameraBackends* backends, std::function<void()> on_crash) {
  backends->Register(
      v1::CAMERA_BACKEND_SIM,
      [on_crash](const v1::CameraConfig& config,
                 const camera::CameraBackendContext& context) -> absl::StatusOr<camera::CameraBackendParts> {
        auto device =
            std::make_unique<SimCameraDevice>(context.clock, config.device().empty() ? config.id() : config.device());
        camera::CameraBackendParts parts;
        if (!context.world_address.empty() && config.trigger().source() != v1::TRIGGER_SOURCE_HARDWARE_LINE) {
          // The world's cameras hang on its trigger bus; software triggers have no time in a lockstep world.
          Logger("camera-node")
              ->warn(
                  "camera {}: not in the simulated world (its trigger source is not hardware-line); it shows a test "
                  "pattern",
                  config.id());
        } else if (!context.world_address.empty()) {
          STAGE_ASSIGN_OR_RETURN(NodeWorld opened, OpenNodeWorld(*context.rig, context.world_address));
          auto world = std::make_shared<NodeWorld>(std::move(opened));
          STAGE_ASSIGN_OR_RETURN(SimCameraWorld plan, CameraWorld(world->scene, config.id(), world->client.get()));
          plan.on_crash = on_crash;
          STAGE_RETURN_IF_ERROR(device->AttachWorld(plan));
          parts.keep = world;
          parts.start_now = true;  // on the world's bus from the start
        }
        parts.device = std::move(device);
        return parts;
      });
}

}  // namespace stage::sim
