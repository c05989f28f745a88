// stagectl's table and JSON.
#include "status_format.h"

#include <nlohmann/json.hpp>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/proto_json.h"

namespace stage::stagectl {
namespace {

using ::testing::HasSubstr;

v1::StageStatus Example() {
  v1::StageStatus s;
  s.set_stage_id("fastage");
  s.set_stage_name("FaStage");
  s.set_session_state(v1::SESSION_STATE_IDLE);
  s.set_nodes_total(2);
  s.set_nodes_up(1);
  auto* a = s.add_nodes();
  a->set_id("mv-01");
  a->set_kind(v1::NODE_KIND_CAMERA);
  a->set_camera_role(v1::CAMERA_ROLE_MACHINE_VISION);
  a->set_address("127.0.0.1:5000");
  a->set_state(v1::NODE_STATE_UP);
  a->set_version("0.1.0");
  a->set_backend("sim");
  a->set_rtt_ns(250000);
  a->set_last_seen_unix_ns(1'000'000'000);
  auto* clock = a->mutable_clock();
  clock->set_measured(true);
  clock->set_offset_ns(-3'001'234);
  clock->set_uncertainty_ns(42'500);
  clock->set_drift_known(true);
  clock->set_drift_ppm(12.5);
  clock->set_limit_ns(10'000);
  clock->set_limit_reason("scheduled software triggers");
  clock->set_flagged(true);
  clock->mutable_ptp()->set_source("linuxptp");
  clock->mutable_ptp()->set_port_state("SLAVE");
  clock->mutable_ptp()->set_master_offset_ns(-1933);
  auto* b = s.add_nodes();
  b->set_id("lights-1");
  b->set_kind(v1::NODE_KIND_LIGHT);
  b->set_address("127.0.0.1:5001");
  b->set_state(v1::NODE_STATE_DOWN);
  b->set_reason("Connection refused");
  return s;
}

TEST(StatusFormatTest, TableShowsEveryNodeAndTheSummary) {
  std::string table = FormatStatusTable(Example(), 1'500'000'000, /*color=*/false);
  EXPECT_THAT(table, HasSubstr("Stage fastage (FaStage): 1 of 2 nodes up"));
  EXPECT_THAT(table, HasSubstr("mv-01"));
  EXPECT_THAT(table, HasSubstr("camera MV"));
  EXPECT_THAT(table, HasSubstr("0.25 ms"));
  EXPECT_THAT(table, HasSubstr("500 ms ago"));
  EXPECT_THAT(table, HasSubstr("Connection refused"));
  EXPECT_THAT(table, HasSubstr("1 node is not up."));
  // Clock offset with its uncertainty, flagged beyond the limit, and the PTP state beside it.
  EXPECT_THAT(table, HasSubstr("-3.001 ms ±42.5 us !"));
  EXPECT_THAT(table, HasSubstr("SLAVE -1.9 us"));
  EXPECT_THAT(table, HasSubstr("clock uncertainty 42.5 us > 10.0 us (scheduled software triggers)"));
  EXPECT_THAT(table, HasSubstr("1 node is flagged (!)"));
  EXPECT_EQ(table.find("\033["), std::string::npos);
  EXPECT_THAT(FormatStatusTable(Example(), 0, /*color=*/true), HasSubstr("\033[31mdown\033[0m"));
}

// `stagectl status --json` is the message in the project's JSON convention: enums by name, int64 as strings, every
// field present; any protobuf library reads it back.
TEST(StatusFormatTest, JsonIsTheMessageInTheContractsConvention) {
  const std::string text = ToContractJson(Example());
  auto j = nlohmann::json::parse(text);
  EXPECT_EQ(j["stage_id"], "fastage");
  EXPECT_EQ(j["session_state"], "SESSION_STATE_IDLE");
  EXPECT_EQ(j["current_take_id"], "");
  EXPECT_EQ(j["nodes_up"], 1);
  ASSERT_EQ(j["nodes"].size(), 2u);
  EXPECT_EQ(j["nodes"][0]["state"], "NODE_STATE_UP");
  EXPECT_EQ(j["nodes"][0]["kind"], "NODE_KIND_CAMERA");
  EXPECT_EQ(j["nodes"][0]["camera_role"], "CAMERA_ROLE_MACHINE_VISION");
  EXPECT_EQ(j["nodes"][0]["rtt_ns"], "250000");
  EXPECT_EQ(j["nodes"][1]["state"], "NODE_STATE_DOWN");
  EXPECT_EQ(j["nodes"][1]["reason"], "Connection refused");
  EXPECT_EQ(j["nodes"][0]["clock"]["offset_ns"], "-3001234");
  EXPECT_EQ(j["nodes"][0]["clock"]["flagged"], true);
  EXPECT_EQ(j["nodes"][0]["clock"]["drift_ppm"], 12.5);
  EXPECT_EQ(j["nodes"][0]["clock"]["ptp"]["port_state"], "SLAVE");
  EXPECT_FALSE(j["nodes"][1]["clock"].contains("ptp"));  // a message not set is left out
  v1::StageStatus back;
  ASSERT_TRUE(FromContractJson(text, &back).ok());
  EXPECT_EQ(back.SerializeAsString(), Example().SerializeAsString());
}

TEST(StatusFormatTest, AnUnmeasuredClockThatIsNeededIsFlagged) {
  v1::StageStatus s = Example();
  s.mutable_nodes(0)->mutable_clock()->set_measured(false);  // still flagged: it needs one
  std::string table = FormatStatusTable(s, 1'500'000'000, /*color=*/false);
  EXPECT_THAT(table, HasSubstr("- !"));
  EXPECT_THAT(table, HasSubstr("clock not measured; its scheduled software triggers need it"));
}

}  // namespace
}  // namespace stage::stagectl
