// Adding up ledger counts: see ledger_counts.h.
#include "stage/common/ledger_counts.h"

#include <algorithm>

namespace stage {

void AddLoss(v1::LedgerCounts* counts, v1::LossReason reason, int64_t n) {
  for (v1::LossCount& l : *counts->mutable_lost()) {
    if (l.reason() == reason) {
      l.set_frames(l.frames() + n);
      return;
    }
  }
  v1::LossCount* l = counts->add_lost();
  l->set_reason(reason);
  l->set_frames(n);
  std::sort(counts->mutable_lost()->begin(), counts->mutable_lost()->end(),
            [](const v1::LossCount& a, const v1::LossCount& b) { return a.reason() < b.reason(); });
}

void AddCounts(const v1::LedgerCounts& from, v1::LedgerCounts* to) {
  to->set_expected(to->expected() + from.expected());
  to->set_stored(to->stored() + from.stored());
  to->set_paused(to->paused() + from.paused());
  for (const v1::LossCount& l : from.lost()) AddLoss(to, l.reason(), l.frames());
}

}  // namespace stage
