// stage-console in front of a simulated stage: an operator and an observer drive it in Debian's headless Chromium
// (tests/console/e2e.mjs, playwright-core), and its API is held to its login, roles and event stream by a plain HTTP
// client.
#include <httplib.h>
#include <signal.h>

#include <filesystem>
#include <iostream>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "simulated_stage.h"
#include "test_support.h"

namespace stage::testing {
namespace {

using ::testing::HasSubstr;

class ConsoleTest : public SimulatedStageTest {
 protected:
  void SetUp() override {
    users_ = console_dir_.path() + "/users";
    for (const auto& [name, role, password] :
         {std::tuple{"ana", "operator", "ana-secret"}, std::tuple{"bo", "observer", "bo-secret"}}) {
      CommandResult add =
          RunCommand({"/bin/sh", "-c",
                      absl::StrCat("printf '%s\\n' '", password, "' | ", BinDir(), "/stage-console users add ", name,
                                   " --role ", role, " --users ", users_)},
                     std::chrono::seconds(30));
      ASSERT_EQ(add.exit.exit_code, 0) << add.err;
    }
  }

  void TearDown() override {
    if (console_ && !console_->exited()) console_->Terminate(std::chrono::seconds(10));
    SimulatedStageTest::TearDown();
  }

  void StartConsole() {
    const std::string port_file = console_dir_.path() + "/port";
    std::filesystem::remove(port_file);
    metrics_file_ = console_dir_.path() + "/metrics";
    auto p = Subprocess::Spawn(
        {.argv = {BinDir() + "/stage-console", "--endpoints", Endpoints(), "--users", users_, "--listen", "127.0.0.1:0",
                  "--port-file", port_file, "--tail-log", run_dir_.path() + "/logs", "--metrics-listen", "127.0.0.1:0",
                  "--metrics-port-file", metrics_file_},
         .stderr_path = console_dir_.path() + "/console.log"});
    ASSERT_TRUE(p.ok()) << p.status();
    console_ = std::move(*p);
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
    while (!std::filesystem::exists(port_file)) {
      ASSERT_FALSE(console_->Poll().has_value()) << ReadFile(console_dir_.path() + "/console.log");
      ASSERT_LT(std::chrono::steady_clock::now(), deadline) << ReadFile(console_dir_.path() + "/console.log");
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    const std::string address = std::string(absl::StripAsciiWhitespace(ReadFile(port_file)));
    host_ = address.substr(0, address.rfind(':'));
    port_ = std::stoi(address.substr(address.rfind(':') + 1));
  }

  httplib::Client Client() {
    httplib::Client c(host_, port_);
    c.set_read_timeout(30, 0);
    return c;
  }

  // Logs in; the session cookie ("fastage_session=...").
  std::string Login(const std::string& user, const std::string& password) {
    auto r =
        Client().Post("/api/login", nlohmann::json{{"user", user}, {"password", password}}.dump(), "application/json");
    EXPECT_TRUE(r) << "no answer";
    if (!r) return "";
    EXPECT_EQ(r->status, 200) << r->body;
    const std::string set = r->get_header_value("Set-Cookie");
    EXPECT_THAT(set, HasSubstr("HttpOnly"));
    EXPECT_THAT(set, HasSubstr("SameSite=Strict"));
    return set.substr(0, set.find(';'));
  }

  TempDir console_dir_;
  std::string users_;
  std::string metrics_file_;
  std::unique_ptr<Subprocess> console_;
  std::string host_;
  int port_ = 0;
};

TEST_F(ConsoleTest, AnOperatorAndAnObserverDriveTheStageInChromium) {
  TempDir root;
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene({"--take-root", root.path()})));
  ASSERT_NO_FATAL_FAILURE(StartConsole());
  std::string victim_id;
  pid_t victim_pid = 0;
  int lights = 0;
  for (const auto& p : endpoints_.processes()) {
    if (p.kind() == v1::NODE_KIND_CAMERA && victim_id.empty()) {
      victim_id = p.id();
      victim_pid = p.pid();
    }
    if (p.kind() == v1::NODE_KIND_LIGHT) ++lights;
  }
  ASSERT_GT(victim_pid, 0);
  // FASTAGE_CONSOLE_SCREENSHOTS=docs/console refreshes the documentation's screenshots.
  const char* docs = std::getenv("FASTAGE_CONSOLE_SCREENSHOTS");
  const std::string shots = docs != nullptr && *docs != '\0' ? docs : console_dir_.path() + "/screenshots";
  CommandResult e2e = RunCommand(
      {"/usr/bin/node", std::string(FASTAGE_SOURCE_DIR) + "/tests/console/e2e.mjs"}, std::chrono::seconds(900),
      {absl::StrCat("CONSOLE_URL=http://", host_, ":", port_, "/"), "OPERATOR=ana:ana-secret", "OBSERVER=bo:bo-secret",
       "VICTIM_ID=" + victim_id, absl::StrCat("VICTIM_PID=", victim_pid), "SCREENSHOTS=" + shots, "TAKE_SECONDS=1"});
  ASSERT_FALSE(e2e.timed_out) << e2e.err;
  ASSERT_EQ(e2e.exit.exit_code, 0) << e2e.out << e2e.err << ReadFile(console_dir_.path() + "/console.log");
  const nlohmann::json measured = nlohmann::json::parse(e2e.out.substr(e2e.out.rfind('{')));
  std::cout << "measured in Chromium: " << measured.dump() << "\n";
  EXPECT_EQ(measured["outcome"], "COMPLETE");
  EXPECT_LT(measured["red_after_ms"].get<int>(), 1000);
  EXPECT_EQ(measured["lights_dark"].get<int>(), lights);
  for (const char* page :
       {"login", "stage", "take", "previews", "timing", "takes", "estop", "node-down", "alarms", "log"}) {
    EXPECT_TRUE(std::filesystem::exists(shots + "/" + page + ".png")) << page;
  }
  // The stage agrees: the emergency stop latched and every light node's device dark.
  const nlohmann::json status = StatusJson();
  EXPECT_EQ(status["estop_latched"], true);
  int dark = 0;
  for (const auto& d : status["devices"]) {
    if (d.contains("light") && d["light"]["mode"] == "LIGHT_MODE_BLACKOUT") ++dark;
  }
  EXPECT_EQ(dark, lights);
  // The operator's commands are in the console's log, by name.
  EXPECT_THAT(ReadFile(console_dir_.path() + "/console.log"), HasSubstr("ana (operator) /api/capture: ok"));
  EXPECT_THAT(ReadFile(console_dir_.path() + "/console.log"), HasSubstr("bo (observer) /api/estop: ok"));

  // A restarted console keeps the alarm and its acknowledgement.
  console_->Terminate(std::chrono::seconds(10));
  ASSERT_NO_FATAL_FAILURE(StartConsole());
  const std::string cookie = Login("bo", "bo-secret");
  auto alarms = Client().Get("/api/alarms", {{"Cookie", cookie}});
  ASSERT_TRUE(alarms);
  ASSERT_EQ(alarms->status, 200) << alarms->body;
  bool acked = false;
  const nlohmann::json listed = nlohmann::json::parse(alarms->body);
  for (const auto& a : listed["active"]) {
    if (a["key"] == "node-down:" + victim_id) acked = a["acked_by"] == "ana";
  }
  EXPECT_TRUE(acked) << alarms->body;
}

TEST_F(ConsoleTest, TheApiNeedsALoginTheRightRoleAndOurHeaderAndTheStreamResumesAfterItsLastEventId) {
  ASSERT_NO_FATAL_FAILURE(StartStage(ControlPlaneScene()));
  ASSERT_NO_FATAL_FAILURE(StartConsole());
  auto c = Client();
  EXPECT_EQ(c.Get("/api/status")->status, 401);
  EXPECT_EQ(c.Get("/api/events")->status, 401);
  EXPECT_EQ(c.Get("/")->status, 200);  // the login page itself
  auto wrong = c.Post("/api/login", R"({"user": "ana", "password": "guess"})", "application/json");
  EXPECT_EQ(wrong->status, 403);
  EXPECT_THAT(wrong->body, HasSubstr("unknown user or wrong password"));
  EXPECT_EQ(c.Post("/api/login", "not json", "application/json")->status, 400);
  const std::string observer = Login("bo", "bo-secret"), op = Login("ana", "ana-secret");
  // An observer may not command; nobody commands without X-FaStage (another site's page cannot send it).
  auto refused = c.Post("/api/arm", {{"Cookie", observer}, {"X-FaStage", "1"}}, "{}", "application/json");
  EXPECT_EQ(refused->status, 403);
  EXPECT_THAT(refused->body, HasSubstr("bo is an observer: /api/arm needs an operator"));
  EXPECT_EQ(c.Post("/api/pause", {{"Cookie", op}}, "{}", "application/json")->status, 403);
  // A command the stage refuses says why (nothing to pause), with the controller's code.
  auto pause = c.Post("/api/pause", {{"Cookie", op}, {"X-FaStage", "1"}}, "{}", "application/json");
  EXPECT_EQ(pause->status, 409) << pause->body;
  EXPECT_THAT(pause->body, HasSubstr("FAILED_PRECONDITION"));
  auto status = c.Get("/api/status", {{"Cookie", observer}});
  ASSERT_EQ(status->status, 200);
  EXPECT_THAT(status->body, HasSubstr("\"nodes_total\""));

  // The stream: events with ids; a reconnect with Last-Event-ID gets what came after it, first.
  struct Read {
    std::vector<uint64_t> ids;
    std::string text;  // everything read, for a failure's message
    std::string error;
  };
  auto read_events = [&](const httplib::Headers& headers, int wanted) {
    Read read;
    std::string buffer;
    auto client = Client();
    auto result = client.Get("/api/events", headers, [&](const char* data, size_t n) {
      buffer.append(data, n);
      read.text.append(data, n);
      size_t end;
      while ((end = buffer.find("\n\n")) != std::string::npos) {
        const std::string event = buffer.substr(0, end);
        buffer.erase(0, end + 2);
        if (absl::StartsWith(event, "id: ")) read.ids.push_back(std::stoull(event.substr(4, event.find('\n') - 4)));
      }
      return static_cast<int>(read.ids.size()) < wanted;
    });
    if (!result && result.error() != httplib::Error::Canceled) read.error = httplib::to_string(result.error());
    return read;
  };
  const Read first = read_events({{"Cookie", observer}}, 3);
  // (A chunk may bring more events than asked for: all of them are read.)
  ASSERT_GE(first.ids.size(), 3u) << first.error << "\n" << first.text.substr(0, 2000);
  EXPECT_LT(first.ids[1], first.ids[2]);
  const Read resumed = read_events({{"Cookie", observer}, {"Last-Event-ID", std::to_string(first.ids[1])}}, 1);
  ASSERT_GE(resumed.ids.size(), 1u) << resumed.error << "\n" << resumed.text.substr(0, 2000);
  EXPECT_EQ(resumed.ids[0], first.ids[1] + 1);
  // The console's own metrics, as promtool reads them: its logins and commands counted.
  const std::string metrics = std::string(absl::StripAsciiWhitespace(ReadFile(metrics_file_)));
  CommandResult lint = RunCommand({"/bin/sh", "-c",
                                   "curl -sf http://" + metrics + "/metrics > " + console_dir_.path() + "/m.txt && " +
                                       "/usr/bin/promtool check metrics < " + console_dir_.path() + "/m.txt"},
                                  std::chrono::seconds(30));
  EXPECT_EQ(lint.exit.exit_code, 0) << lint.out << lint.err;
  EXPECT_EQ(lint.out + lint.err, "");
  const std::string scraped = ReadFile(console_dir_.path() + "/m.txt");
  EXPECT_THAT(scraped, HasSubstr("stage_console_logins_total{outcome=\"refused\"} 1"));
  EXPECT_THAT(scraped, HasSubstr("stage_console_commands_total{path=\"/api/pause\",outcome=\"forbidden\"} 1"));
  EXPECT_THAT(scraped, HasSubstr("stage_console_commands_total{path=\"/api/pause\",outcome=\"failed\"} 1"));
  EXPECT_THAT(scraped, HasSubstr("stage_console_commands_total{path=\"/api/arm\",outcome=\"forbidden\"} 1"));
  EXPECT_THAT(scraped, HasSubstr("stage_console_controller_up 1"));
  // Logged out, the cookie opens nothing.
  c.Post("/api/logout", {{"Cookie", observer}}, "", "application/json");
  EXPECT_EQ(c.Get("/api/status", {{"Cookie", observer}})->status, 401);
}

}  // namespace
}  // namespace stage::testing
