// The console under load: a simulated stage records a take while N browsers' worth of event streams (curl processes)
// follow the console; the console's answers to API calls are timed meanwhile, beside a bare HTTP round trip to a
// trivial server in this process, in the same run. The take must come out with every frame stored.
#include <httplib.h>
#include <unistd.h>

#include <filesystem>
#include <nlohmann/json.hpp>
#include <thread>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"
#include "bench_util.h"
#include "stage/common/file_util.h"
#include "stage/common/subprocess.h"

namespace {

using stage::bench::Clock;
using stage::bench::Die;
using stage::bench::Ms;
constexpr const char* kProgram = "console_bench";

std::string BinDir() { return std::filesystem::read_symlink("/proc/self/exe").parent_path().string(); }

std::string WaitForFile(const std::string& path, stage::Subprocess& owner, const std::string& log) {
  const auto deadline = Clock::now() + std::chrono::seconds(120);
  while (!std::filesystem::exists(path)) {
    if (owner.Poll().has_value()) Die(kProgram, "exited: " + stage::ReadFileToString(log).value_or(""));
    if (Clock::now() > deadline) Die(kProgram, path + " did not appear");
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  return stage::ReadFileToString(path).value_or("");
}

struct Percentiles {
  double p50, p99, max;
};

Percentiles Of(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return {v[v.size() / 2], v[std::min(v.size() - 1, v.size() * 99 / 100)], v.back()};
}

// `n` timed GETs of `path` (with `headers`), `gap` apart.
std::vector<double> Time(httplib::Client& client, const std::string& path, const httplib::Headers& headers, int n,
                         std::chrono::milliseconds gap) {
  std::vector<double> ms;
  for (int i = 0; i < n; ++i) {
    const auto t0 = Clock::now();
    auto r = client.Get(path, headers);
    ms.push_back(Ms(Clock::now() - t0));
    if (!r || r->status != 200) Die(kProgram, path + " failed");
    std::this_thread::sleep_for(gap);
  }
  return ms;
}

// `n` timed POSTs of `body` to `path` (a command), `gap` apart; each must answer `status`.
std::vector<double> TimePost(httplib::Client& client, const std::string& path, const httplib::Headers& headers,
                             const std::string& body, int status, int n, std::chrono::milliseconds gap) {
  std::vector<double> ms;
  for (int i = 0; i < n; ++i) {
    const auto t0 = Clock::now();
    auto r = client.Post(path, headers, body, "application/json");
    ms.push_back(Ms(Clock::now() - t0));
    if (!r || r->status != status) Die(kProgram, path + " did not answer " + std::to_string(status));
    std::this_thread::sleep_for(gap);
  }
  return ms;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "The console's API latency with N event streams open while a take records, beside a bare HTTP round "
      "trip in the same run",
      kProgram};
  int streams = 20;
  int calls = 200;
  double seconds = 3;
  app.add_option("--streams", streams, "Event streams (curl processes) following the console")->capture_default_str();
  app.add_option("--calls", calls, "Timed calls of each kind")->capture_default_str();
  app.add_option("--seconds", seconds, "Length of the take")->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  const std::string dir = std::filesystem::temp_directory_path() / ("console_bench." + std::to_string(getpid()));
  std::filesystem::create_directories(dir);
  const std::string bin = BinDir();
  auto sim = stage::Subprocess::Spawn(
      {.argv = {bin + "/stage-sim", "--run-dir", dir + "/run", "--set", "sim.render_scale=0.02", "--set",
                "sim.subject.performance=still", "--take-root", dir + "/takes"},
       .stderr_path = dir + "/stage-sim.log"});
  if (!sim.ok()) Die(kProgram, std::string(sim.status().message()));
  WaitForFile(dir + "/run/endpoints.json", **sim, dir + "/stage-sim.log");
  const std::string users = dir + "/users";
  if (std::system(absl::StrCat("printf 'pw\\n' | ", bin, "/stage-console users add op --role operator --users ", users,
                               " > /dev/null")
                      .c_str()) != 0) {
    Die(kProgram, "stage-console users add failed");
  }
  auto console =
      stage::Subprocess::Spawn({.argv = {bin + "/stage-console", "--endpoints", dir + "/run/endpoints.json", "--users",
                                         users, "--listen", "127.0.0.1:0", "--port-file", dir + "/console.port"},
                                .stderr_path = dir + "/console.log"});
  if (!console.ok()) Die(kProgram, std::string(console.status().message()));
  const std::string address(
      absl::StripAsciiWhitespace(WaitForFile(dir + "/console.port", **console, dir + "/console.log")));
  const std::string host = address.substr(0, address.rfind(':'));
  const int port = std::stoi(address.substr(address.rfind(':') + 1));
  httplib::Client client(host, port);
  auto login = client.Post("/api/login", R"({"user": "op", "password": "pw"})", "application/json");
  if (!login || login->status != 200) Die(kProgram, "login failed");
  const std::string cookie =
      login->get_header_value("Set-Cookie").substr(0, login->get_header_value("Set-Cookie").find(';'));
  const httplib::Headers auth = {{"Cookie", cookie}};

  // The baseline: a trivial server in this process, the same client library, the same loopback.
  httplib::Server bare;
  bare.Get("/", [](const httplib::Request&, httplib::Response& res) { res.set_content("{}", "application/json"); });
  const int bare_port = bare.bind_to_any_port("127.0.0.1");
  std::thread bare_thread([&] { bare.listen_after_bind(); });
  httplib::Client bare_client("127.0.0.1", bare_port);

  std::vector<std::unique_ptr<stage::Subprocess>> curls;
  for (int i = 0; i < streams; ++i) {
    auto c = stage::Subprocess::Spawn(
        {.argv = {"/usr/bin/curl", "-sN", "-H", "Cookie: " + cookie, absl::StrCat("http://", address, "/api/events")},
         .stdout_path = absl::StrCat(dir, "/stream-", i, ".txt")});
    if (!c.ok()) Die(kProgram, std::string(c.status().message()));
    curls.push_back(std::move(*c));
  }
  std::this_thread::sleep_for(std::chrono::seconds(2));
  auto capture =
      client.Post("/api/capture", {{"Cookie", cookie}, {"X-FaStage", "1"}},
                  absl::StrCat(R"({"seconds": )", seconds, R"(, "name": "console bench"})"), "application/json");
  if (!capture || capture->status != 200)
    Die(kProgram, "capture: " + (capture ? capture->body : std::string("no answer")));
  const nlohmann::json first = nlohmann::json::parse(capture->body);
  const std::string take_id = first.value("take_id", "");
  // Timed while the take records (not while it arms).
  auto session = [&] {
    auto r = client.Get("/api/status", auth);
    return r && r->status == 200 ? nlohmann::json::parse(r->body).value("session_state", "") : std::string();
  };
  for (int i = 0; i < 1200 && session() != "SESSION_STATE_CAPTURING"; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  const std::string state_before = session();
  const auto gap = std::chrono::milliseconds(5);
  const Percentiles bare_ms = Of(Time(bare_client, "/", {}, calls, gap));
  const Percentiles me_ms = Of(Time(client, "/api/me", auth, calls, gap));
  const Percentiles status_ms = Of(Time(client, "/api/status", auth, calls, gap));
  const Percentiles takes_ms = Of(Time(client, "/api/takes", auth, calls / 4, gap));
  // A command through the whole gate (login, role, header) and the alarm database: acknowledging an alarm there is
  // none of (404), which leaves the take alone.
  const Percentiles ack_ms = Of(TimePost(client, "/api/alarms/ack", {{"Cookie", cookie}, {"X-FaStage", "1"}},
                                         R"({"id": 999999})", 404, calls, gap));
  const std::string state_after = session();
  // The take's end, and what it stored.
  nlohmann::json summary;
  for (int i = 0; i < 600; ++i) {
    auto t = client.Get("/api/take?id=" + take_id, auth);
    if (t && t->status == 200) {
      summary = nlohmann::json::parse(t->body);
      if (summary.value("outcome", "") != "TAKE_OUTCOME_UNSPECIFIED" && summary.contains("total")) break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
  }
  int64_t events = 0;
  for (int i = 0; i < streams; ++i) {
    const std::string text = stage::ReadFileToString(absl::StrCat(dir, "/stream-", i, ".txt")).value_or("");
    for (size_t at = 0; (at = text.find("\nid: ", at)) != std::string::npos; ++at) ++events;
  }
  for (auto& c : curls) c->Terminate(std::chrono::seconds(2));
  (*console)->Terminate(std::chrono::seconds(10));
  (*sim)->Terminate(std::chrono::seconds(20));
  bare.stop();
  bare_thread.join();

  std::printf(
      "console_bench: %d event streams (curl) open while take %s of %.1f s recorded; %d calls each, %d ms apart "
      "(the session %s when they began, %s when they ended)\n",
      streams, take_id.c_str(), seconds, calls, static_cast<int>(gap.count()), state_before.c_str(),
      state_after.c_str());
  std::printf("  %-34s p50 %7.2f ms   p99 %7.2f ms   max %7.2f ms\n", "bare HTTP round trip (baseline)", bare_ms.p50,
              bare_ms.p99, bare_ms.max);
  std::printf("  %-34s p50 %7.2f ms   p99 %7.2f ms   max %7.2f ms\n", "GET /api/me (login checked)", me_ms.p50,
              me_ms.p99, me_ms.max);
  std::printf("  %-34s p50 %7.2f ms   p99 %7.2f ms   max %7.2f ms\n", "GET /api/status (the stage)", status_ms.p50,
              status_ms.p99, status_ms.max);
  std::printf("  %-34s p50 %7.2f ms   p99 %7.2f ms   max %7.2f ms\n", "GET /api/takes (a controller call)",
              takes_ms.p50, takes_ms.p99, takes_ms.max);
  std::printf("  %-34s p50 %7.2f ms   p99 %7.2f ms   max %7.2f ms\n", "POST /api/alarms/ack (a command)", ack_ms.p50,
              ack_ms.p99, ack_ms.max);
  std::printf("  events delivered to the streams: %lld; the take: %s, %s of %s frames stored\n",
              static_cast<long long>(events), summary.value("outcome", "?").c_str(),
              summary.contains("total") ? summary["total"].value("stored", "?").c_str() : "?",
              summary.contains("total") ? summary["total"].value("expected", "?").c_str() : "?");
  std::filesystem::remove_all(dir);
  const bool ok = summary.value("outcome", "") == "TAKE_OUTCOME_COMPLETE";
  return ok ? 0 : 1;
}
