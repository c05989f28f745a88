// A simulated camera on the network: Aravis's fake GigE Vision camera (ArvGvFakeCamera), listening at an IPv4 address
// of this machine, whose images are the simulated stage. A camera node opens it with the real Aravis backend and
// talks GVCP/GVSP to it over loopback, exactly as to a camera on the stage's network (docs/cameras.md).
//
// The picture comes from a SimCameraDevice in the world (the camera's trigger plan, renderer and clock): each frame it
// renders at a trigger edge is, when the fake is acquiring with TriggerMode On and TriggerSource Line0, the hardware
// trigger of the fake, which sends it (scaled up to the fake's image size, if the sim renders smaller) stamped with
// the exposure start on the camera's clock. No Aravis header appears here (only gige_fake_camera.cc includes it).
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "stage/sim/scene.h"
#include "stage/sim/world_client.h"

namespace stage::sim {

struct GigEFakeOptions {
  // The rig's camera this fake is.
  std::string camera_id;
  // Where it listens (GVCP port 3956): an IPv4 address on an interface of this machine.
  std::string address;
  // GVSP packets lost on the way, fraction (Aravis's gvsp-lost-packet-ratio).
  double packet_loss = 0;
  // Leaves the network once the world passes this time (seconds from slot 0; < 0: never), for link_down_s of wall
  // time, and comes back power-cycled (settings at their defaults, frame counter from 0).
  double link_down_at_s = -1;
  double link_down_s = 0;
  // How often the fake looks at its trigger (Aravis polls it): frames wait up to one period to be sent (their
  // timestamps are the exposure's). Above the camera's frame rate.
  double trigger_poll_hz = 200;

  absl::Status Validate() const;
};

// Options for camera `camera_id` from the rig: its device address and its sim.faults.
absl::StatusOr<GigEFakeOptions> GigEFakeOptionsFromRig(const SimScene& scene, const std::string& camera_id);

struct GigEFakeStats {
  uint64_t rendered = 0;       // frames the world rendered for the camera
  uint64_t sent = 0;           // frames sent over GVSP
  uint64_t not_acquiring = 0;  // rendered while the fake was not acquiring on its trigger line (a camera ignores them)
  uint64_t link_down = 0;      // rendered while the fake was off the network
  uint64_t outages = 0;        // times it left the network
};

class GigEFakeCamera {
 public:
  // Starts the fake at options.address and joins `world` (not owned; outlives the fake) as the camera. Unavailable
  // when the address is on no interface (the error says how to add it).
  static absl::StatusOr<std::unique_ptr<GigEFakeCamera>> Create(std::shared_ptr<const SimScene> scene,
                                                                 WorldClient* world, GigEFakeOptions options);
  // Leaves the world and the network.
  ~GigEFakeCamera();

  GigEFakeStats stats() const;
  const GigEFakeOptions& options() const;

  struct Impl;

 private:
  explicit GigEFakeCamera(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace stage::sim
