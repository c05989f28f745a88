// Adding up a take's ledger counts (stage.v1.LedgerCounts): the controller's per-camera and total counts, stagectl's
// counts by role. Losses stay one entry per reason, in the enum's order.
#pragma once

#include <cstdint>

#include "stage/v1/controller.pb.h"

namespace stage {

// Adds `n` frames lost for `reason` to `counts`.
void AddLoss(v1::LedgerCounts* counts, v1::LossReason reason, int64_t n = 1);
// Adds every count of `from` (expected, stored, paused, each loss) to `to`.
void AddCounts(const v1::LedgerCounts& from, v1::LedgerCounts* to);

}  // namespace stage
