// The take catalog and ledger on a real SQLite file: takes are created, updated, listed and numbered per day; the
// ledger counts per camera and pattern; what a process committed before it was killed is there after; the sqlite3
// shell reads the same file; a catalog from a newer program is refused.
#include "stage/storage/catalog.h"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::storage {
namespace {

using ::testing::HasSubstr;

std::string FreshRoot(const std::string& name) {
  const std::string root = ::testing::TempDir() + "/catalog-" + name;
  std::filesystem::remove_all(root);
  return root;
}

TakeRow Take(const std::string& id, int64_t created) {
  TakeRow t;
  t.id = id;
  t.state = v1::TAKE_STATE_CONFIGURING;
  t.created_unix_ns = created;
  t.slots = 912;
  t.dir = id;
  return t;
}

std::string Shell(const std::string& command) {
  std::string out;
  if (FILE* p = popen((command + " 2>&1").c_str(), "r")) {
    char buffer[4096];
    for (size_t got; (got = fread(buffer, 1, sizeof buffer, p)) > 0;) out.append(buffer, got);
    pclose(p);
  }
  return out;
}

TEST(CatalogTest, TakesAreCreatedUpdatedListedAndNumberedPerDay) {
  auto catalog = Catalog::Open(FreshRoot("takes"));
  ASSERT_TRUE(catalog.ok()) << catalog.status();
  Catalog& c = **catalog;
  // 2026-11-23 12:00 UTC; the id uses the local calendar, so stay clear of midnight in any zone.
  const int64_t noon = 1'795'435'200'000'000'000;
  auto first = c.NextTakeId("fastage", noon);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_THAT(*first, ::testing::MatchesRegex("fastage-202611(22|23|24)-0001"));
  ASSERT_TRUE(c.CreateTake(Take(*first, noon)).ok());
  auto suffix = [](const absl::StatusOr<std::string>& id) { return id.ok() ? id->substr(id->size() - 4) : ""; };
  auto second = c.NextTakeId("fastage", noon + 1);
  ASSERT_TRUE(second.ok());
  EXPECT_EQ(suffix(second), "0002");
  ASSERT_TRUE(c.CreateTake(Take(*second, noon + 1)).ok());
  EXPECT_TRUE(absl::IsAlreadyExists(c.CreateTake(Take(*first, noon))));
  // Another stage, or another day, starts again at 0001.
  EXPECT_EQ(suffix(c.NextTakeId("other", noon)), "0001");
  EXPECT_EQ(suffix(c.NextTakeId("fastage", noon + 3 * 86'400'000'000'000)), "0001");

  TakeRow done = Take(*first, noon);
  done.state = v1::TAKE_STATE_COMPLETE;
  done.outcome = v1::TAKE_OUTCOME_COMPLETE;
  done.frames_expected = 3312;
  done.frames_stored = 3312;
  done.size_bytes = 123456789;
  done.duration_s = 1.0;
  ASSERT_TRUE(c.UpdateTake(done).ok());
  auto got = c.GetTake(*first);
  ASSERT_TRUE(got.ok());
  EXPECT_EQ(got->outcome, v1::TAKE_OUTCOME_COMPLETE);
  EXPECT_EQ(got->state, v1::TAKE_STATE_COMPLETE);
  // The columns hold the enums' names as docs/storage.md shows them, for the sqlite3 shell.
  EXPECT_EQ(Shell("sqlite3 " + c.path() + " \"SELECT state, outcome FROM takes WHERE id='" + *first + "'\""),
            "complete|COMPLETE\n");
  EXPECT_EQ(got->size_bytes, 123456789);
  EXPECT_EQ(got->frames_stored, 3312);
  auto list = c.ListTakes();
  ASSERT_TRUE(list.ok());
  ASSERT_EQ(list->size(), 2u);
  EXPECT_EQ((*list)[0].id, *first);
  EXPECT_EQ((*list)[1].state, v1::TAKE_STATE_CONFIGURING);
  EXPECT_EQ((*list)[1].outcome, v1::TAKE_OUTCOME_UNSPECIFIED);
  auto missing = c.GetTake("fastage-19990101-0001");
  EXPECT_TRUE(absl::IsNotFound(missing.status()));
  EXPECT_THAT(missing.status().message(), HasSubstr("no take \"fastage-19990101-0001\""));
  EXPECT_TRUE(absl::IsNotFound(c.UpdateTake(Take("nope", 0))));
}

TEST(CatalogTest, TheLedgerCountsPerCameraAndPattern) {
  auto catalog = Catalog::Open(FreshRoot("ledger"));
  ASSERT_TRUE(catalog.ok()) << catalog.status();
  Catalog& c = **catalog;
  ASSERT_TRUE(c.CreateTake(Take("t1", 1)).ok());
  std::vector<LedgerEntry> entries;
  for (const std::string camera : {"hs-1", "hs-2", "mv-01"}) {
    const int64_t step = camera == "mv-01" ? 38 : 1;
    for (int64_t slot = camera == "mv-01" ? 19 : 0; slot < 76; slot += step) {
      LedgerEntry e{camera, slot, static_cast<int32_t>(slot % 38), LossReason::kNone, static_cast<uint64_t>(slot), ""};
      if (camera == "hs-1" && (slot == 3 || slot == 41))
        e = {camera, slot, static_cast<int32_t>(slot % 38), LossReason::kCameraDropped, std::nullopt, ""};
      if (camera == "hs-2" && slot == 10) e.reason = LossReason::kIncomplete;
      entries.push_back(e);
    }
  }
  ASSERT_TRUE(c.RecordLedger("t1", entries).ok());
  // A later report replaces an entry: hs-2's slot 75 failed to write after all.
  ASSERT_TRUE(c.RecordLedger("t1", {{"hs-2", 75, 75 % 38, LossReason::kWriteFailed, 75, "disk full"}}).ok());
  auto summary = c.Summarize("t1");
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->total.expected, 76 + 76 + 2);
  EXPECT_EQ(summary->total.stored, 154 - 4);
  EXPECT_EQ(summary->by_camera["hs-1"].lost[LossReason::kCameraDropped], 2);
  EXPECT_EQ(summary->by_camera["hs-2"].stored, 74);  // incomplete (data missing) and the write failure are lost
  EXPECT_EQ(summary->by_camera["hs-2"].lost[LossReason::kIncomplete], 1);
  EXPECT_EQ(summary->by_camera["hs-2"].lost[LossReason::kWriteFailed], 1);
  EXPECT_EQ(summary->by_camera["mv-01"].expected, 2);
  EXPECT_EQ(summary->by_pattern[3].expected, 2 + 2);  // slots 3 and 41 of hs-1 and hs-2
  EXPECT_EQ(summary->by_pattern[3].stored, 2);
  auto hs2 = c.Ledger("t1", "hs-2");
  ASSERT_TRUE(hs2.ok());
  ASSERT_EQ(hs2->size(), 76u);
  EXPECT_EQ(hs2->back().detail, "disk full");
  EXPECT_EQ(hs2->back().frame_id, 75u);
  // Pages: in camera then slot order, of the lost entries only, a few at a time, with the total each time.
  std::vector<std::pair<std::string, int64_t>> lost;
  for (int64_t offset = 0;; offset += 3) {
    auto page = c.ReadLedgerPage("t1", "", /*lost_only=*/true, offset, 3);
    ASSERT_TRUE(page.ok()) << page.status();
    EXPECT_EQ(page->total, 4);
    if (page->entries.empty()) break;
    for (const LedgerEntry& e : page->entries) lost.emplace_back(e.camera_id, e.slot);
  }
  EXPECT_EQ(lost,
            (std::vector<std::pair<std::string, int64_t>>{{"hs-1", 3}, {"hs-1", 41}, {"hs-2", 10}, {"hs-2", 75}}));
  auto mv = c.ReadLedgerPage("t1", "mv-01", false, 1, 10);
  ASSERT_TRUE(mv.ok());
  EXPECT_EQ(mv->total, 2);
  ASSERT_EQ(mv->entries.size(), 1u);
  EXPECT_EQ(mv->entries[0].slot, 57);
  EXPECT_EQ(std::string(LossReasonName(LossReason::kTriggerMissed)), "trigger missed");
  // The sqlite3 shell, an independent reader, sees the same file.
  EXPECT_EQ(Shell("sqlite3 " + c.path() + " \"SELECT count(*) FROM ledger WHERE take_id='t1' AND reason=0\""), "150\n");
}

TEST(CatalogTest, WhatWasCommittedSurvivesAKilledWriter) {
  const std::string root = FreshRoot("killed");
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    auto catalog = Catalog::Open(root);
    if (!catalog.ok() || !(*catalog)->CreateTake(Take("t1", 1)).ok()) _exit(3);
    std::vector<LedgerEntry> entries;
    for (int64_t slot = 0; slot < 912; ++slot) entries.push_back({"hs-1", slot, 0, LossReason::kNone, 0, ""});
    if (!(*catalog)->RecordLedger("t1", entries).ok()) _exit(4);
    kill(getpid(), SIGKILL);  // no close, no checkpoint
    _exit(5);
  }
  int status = 0;
  ASSERT_EQ(waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFSIGNALED(status)) << status;
  auto catalog = Catalog::Open(root);
  ASSERT_TRUE(catalog.ok()) << catalog.status();
  auto summary = (*catalog)->Summarize("t1");
  ASSERT_TRUE(summary.ok());
  EXPECT_EQ(summary->total.stored, 912);
}

TEST(CatalogTest, ACatalogFromANewerProgramIsRefused) {
  const std::string root = FreshRoot("newer");
  { ASSERT_TRUE(Catalog::Open(root).ok()); }
  ASSERT_EQ(Shell("sqlite3 " + root + "/catalog.sqlite 'PRAGMA user_version=7'"), "");
  auto catalog = Catalog::Open(root);
  ASSERT_FALSE(catalog.ok());
  EXPECT_THAT(catalog.status().message(), HasSubstr("catalog schema 7 is newer than this program's (1)"));
}

}  // namespace
}  // namespace stage::storage
