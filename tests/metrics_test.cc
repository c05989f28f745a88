// Every process of a simulated stage serves Prometheus metrics (stage-sim --metrics): each endpoint passes promtool's
// check, and what it counts follows a take: the controller sees every node up and counts the take and its frames, the
// cameras count the frames they received and wrote, the light nodes show the armed table's duty, every server counts
// its calls.
#include <httplib.h>
#include <sys/wait.h>

#include <cstdlib>
#include <fstream>
#include <map>
#include <regex>
#include <string>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

// GET http://ADDRESS/metrics; "" (with a failure) when it does not answer 200.
std::string Scrape(const std::string& address) {
  const size_t colon = address.rfind(':');
  httplib::Client client(address.substr(0, colon), std::stoi(address.substr(colon + 1)));
  client.set_read_timeout(30, 0);
  auto response = client.Get("/metrics");
  if (!response) {
    ADD_FAILURE() << address << ": " << httplib::to_string(response.error());
    return "";
  }
  EXPECT_EQ(response->status, 200) << address;
  EXPECT_EQ(response->get_header_value("Content-Type"), "text/plain; version=0.0.4; charset=utf-8");
  return response->body;
}

// The value of the sample `series` (name{labels} exactly as rendered); NaN when absent.
double Value(const std::string& text, const std::string& series) {
  const std::string line = series + " ";
  size_t at = 0;
  while ((at = text.find(line, at)) != std::string::npos) {
    if (at == 0 || text[at - 1] == '\n') return std::stod(text.substr(at + line.size()));
    at += line.size();
  }
  return std::nan("");
}

// promtool check metrics on `text`: "" when it has nothing to say, else its words (and the exit code).
std::string Promtool(const std::string& text, const std::string& dir, const std::string& name) {
  const std::string in = dir + "/" + name + ".prom", out = dir + "/" + name + ".promtool";
  std::ofstream(in) << text;
  const int status = std::system(("/usr/bin/promtool check metrics < " + in + " > " + out + " 2>&1").c_str());
  const int code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  const std::string said = ReadFile(out);
  return code == 0 && said.empty() ? "" : absl::StrCat("exit ", code, ": ", said);
}

class StageMetricsTest : public SimulatedStageTest {};

TEST_F(StageMetricsTest, EveryProcessServesMetricsThatPromtoolAcceptsAndThatFollowATake) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--metrics", "--take-root", root.path()})));
  ASSERT_FALSE(endpoints_.metrics().empty());
  std::map<std::string, std::string> address = {{"stage-sim", endpoints_.metrics()}};
  for (const auto& p : endpoints_.processes()) {
    ASSERT_FALSE(p.metrics().empty()) << p.id();
    address[p.id()] = p.metrics();
  }

  // Armed: every light node shows its table's load, within its limits.
  CommandResult arm = Stagectl({"arm", "--frames", "2", "--name", "metrics"});
  ASSERT_EQ(arm.exit.exit_code, 0) << arm.err;
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() != v1::NODE_KIND_LIGHT) continue;
    const std::string text = Scrape(p.metrics());
    const std::string node = "{node=\"" + p.id() + "\"}";
    EXPECT_EQ(Value(text, "stage_light_mode{node=\"" + p.id() + "\",mode=\"armed\"}"), 1) << text;
    EXPECT_GT(Value(text, "stage_light_duty_ratio" + node), 0) << text;
    EXPECT_LE(Value(text, "stage_light_duty_ratio" + node), 1) << text;
    EXPECT_GT(Value(text, "stage_light_thermal_load_ratio" + node), 0) << text;
    EXPECT_LE(Value(text, "stage_light_thermal_load_ratio" + node), 1) << text;
    EXPECT_THAT(text, HasSubstr("grpc_server_handled_total{grpc_type=\"unary\",grpc_service=\"stage.v1.LightNode\","
                                "grpc_method=\"Arm\",grpc_code=\"OK\"} 1\n"));
  }
  CommandResult capture = Stagectl({"capture", "--json"});
  ASSERT_EQ(capture.exit.exit_code, 0) << CaptureVerdict(capture) << capture.out;
  const nlohmann::json take = nlohmann::json::parse(capture.out);
  ASSERT_EQ(take["outcome"], "TAKE_OUTCOME_COMPLETE");
  const double expected = std::stod(take["total"]["expected"].get<std::string>());  // int64: a string in JSON

  std::map<std::string, std::string> text;
  for (const auto& [id, a] : address) {
    text[id] = Scrape(a);
    EXPECT_EQ(Promtool(text[id], run_dir_.path(), id), "") << id << ":\n" << text[id];
    EXPECT_GT(Value(text[id], "process_cpu_seconds_total"), 0) << id;
    EXPECT_GT(Value(text[id], "process_resident_memory_bytes"), 0) << id;
  }

  // The controller: every node up, the take counted with its frames, the Capture call handled.
  const std::string& controller = text.at("controller");
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() == v1::NODE_KIND_CONTROLLER) continue;
    const std::string kind = p.kind() == v1::NODE_KIND_CAMERA  ? "camera"
                             : p.kind() == v1::NODE_KIND_LIGHT ? "light"
                                                               : "processing-worker";
    EXPECT_EQ(Value(controller, "stage_node_state{node=\"" + p.id() + "\",kind=\"" + kind + "\",state=\"up\"}"), 1)
        << p.id() << "\n"
        << controller;
  }
  EXPECT_EQ(Value(controller, "stage_takes_total{state=\"complete\"}"), 1) << controller;
  EXPECT_EQ(Value(controller, "stage_take_frames_expected_total"), expected);
  EXPECT_EQ(Value(controller, "stage_take_frames_stored_total"), expected);
  EXPECT_EQ(Value(controller, "stage_session_state{state=\"idle\"}"), 1);
  EXPECT_EQ(Value(controller,
                  "grpc_server_handled_total{grpc_type=\"server_stream\",grpc_service=\"stage.v1."
                  "StageController\",grpc_method=\"Capture\",grpc_code=\"OK\"}"),
            1)
      << controller;

  // Every camera: the take's frames received and written, none dropped; its node's calls timed.
  double written = 0;
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() != v1::NODE_KIND_CAMERA) continue;
    const std::string& t = text.at(p.id());
    const std::string camera = "{camera=\"" + p.id() + "\"}";
    EXPECT_GT(Value(t, "stage_camera_frames_received_total" + camera), 0) << t;
    EXPECT_GT(Value(t, "stage_camera_frames_written_total" + camera), 0) << t;
    EXPECT_EQ(Value(t, "stage_camera_frames_dropped_total" + camera), 0) << t;
    EXPECT_EQ(Value(t, "stage_camera_link_up" + camera), 1) << t;
    written += Value(t, "stage_camera_frames_written_total" + camera);
    EXPECT_THAT(t, HasSubstr("grpc_server_handling_seconds_count{grpc_type=\"unary\",grpc_service=\"stage.v1."
                             "CameraNode\",grpc_method=\"Finish\"} 1\n"));
  }
  EXPECT_EQ(written, expected);
  // Disarmed after the take: no load.
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() != v1::NODE_KIND_LIGHT) continue;
    EXPECT_EQ(Value(text.at(p.id()), "stage_light_duty_ratio{node=\"" + p.id() + "\"}"), 0);
  }
  // The world ran the take's slots.
  EXPECT_GT(Value(text.at("stage-sim"), "stage_sim_world_slot"), 0) << text.at("stage-sim");
  EXPECT_THAT(text.at("stage-sim"), HasSubstr("stage_build_info{program=\"stage-sim\",version=\""));
}

}  // namespace
}  // namespace stage::testing
