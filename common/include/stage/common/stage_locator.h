// How a client program finds the stage's controller and the transport security to reach it with (stagectl,
// stage-console): from flags, the environment, a rig file, or stage-sim's endpoint file.
#pragma once

#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/v1/sim.pb.h"

namespace stage {

struct StageLocator {
  // The controller, host:port (--controller).
  std::string controller;
  // stage-sim's endpoint file (--endpoints).
  std::string endpoints;
  // The rig file (--config): the controller at its controller.listen.
  std::string rig_path;
  // Who the client is to a stage on mutual TLS ("operator/ana", "console") (--as).
  std::string identity;
};

// stage-sim's endpoint file: --endpoints, $FASTAGE_ENDPOINTS, or the default run directory's. NotFound says
// `wanted` could not be found.
absl::StatusOr<v1::SimEndpoints> ReadSimEndpoints(const StageLocator& where, const std::string& wanted);

// Where the controller is: --controller, the rig's controller.listen (--config), $FASTAGE_CONTROLLER, the endpoint
// file (--endpoints, $FASTAGE_ENDPOINTS, or stage-sim's default run directory), in that order.
absl::StatusOr<std::string> ResolveController(const StageLocator& where);

// The stage's transport security, from its rig (--config, or the effective rig of the stage-sim endpoint file): on
// mutual TLS, the client presents the certificate of `where->identity` (or $FASTAGE_IDENTITY, or `default_identity`,
// which it is set to). Without a rig to read, plain text; an identity then is refused (InvalidArgument).
absl::Status UseStageSecurity(StageLocator* where, const std::string& default_identity);

}  // namespace stage
