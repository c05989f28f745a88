// Adding up ledger counts: one entry per loss reason, in the enum's order.
#include "stage/common/ledger_counts.h"

#include "gtest/gtest.h"

namespace stage {
namespace {

TEST(LedgerCountsTest, LossesStayOnePerReasonInTheEnumsOrder) {
  v1::LedgerCounts a;
  a.set_expected(10);
  a.set_stored(7);
  a.set_paused(2);
  AddLoss(&a, v1::LOSS_REASON_NODE_DOWN, 2);
  AddLoss(&a, v1::LOSS_REASON_CAMERA_DROPPED);
  v1::LedgerCounts b;
  b.set_expected(5);
  b.set_stored(4);
  AddLoss(&b, v1::LOSS_REASON_NODE_DOWN);
  v1::LedgerCounts sum;
  AddCounts(a, &sum);
  AddCounts(b, &sum);
  EXPECT_EQ(sum.expected(), 15);
  EXPECT_EQ(sum.stored(), 11);
  EXPECT_EQ(sum.paused(), 2);
  ASSERT_EQ(sum.lost_size(), 2);
  EXPECT_EQ(sum.lost(0).reason(), v1::LOSS_REASON_CAMERA_DROPPED);
  EXPECT_EQ(sum.lost(0).frames(), 1);
  EXPECT_EQ(sum.lost(1).reason(), v1::LOSS_REASON_NODE_DOWN);
  EXPECT_EQ(sum.lost(1).frames(), 3);
}

}  // namespace
}  // namespace stage
