// A sync generator light node of the simulated stage: its clock line is the world's bus. The runs the controller asks
// the node for are runs of the bus, started in the node's name, so every camera and board sees the node's edges there
// as copper would carry them, and the bus goes quiet when the node's process dies (the world ends a run whose driver
// leaves it).
#pragma once

#include <memory>
#include <string>

#include "stage/light/slot_clock.h"

namespace stage::sim {

std::unique_ptr<light::SlotClockGenerator> NewWorldSlotClock(const std::string& world_address,
                                                             const std::string& node_id);

}  // namespace stage::sim
