// A light node that drives the slot clock (the rig's timing.sync_generator: a gpiod node with drives_slot_clock) as
// the controller's sync generator: the controller plans each run with the node, tells every camera its T0, and asks
// the node for exactly that run (LightNode.RunSlotClock, EndSlotClock, GetSlotClock); the node writes the edges on its
// clock line and says how far it has got.
#pragma once

#include <memory>

#include "stage/v1/rig.pb.h"
#include "sync_generator.h"

namespace stage::controller {

std::unique_ptr<SyncGenerator> NewLightSyncGenerator(const v1::LightNodeConfig& node);

}  // namespace stage::controller
