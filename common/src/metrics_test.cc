#include "stage/common/metrics.h"

#include <httplib.h>
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "stage/common/metrics_server.h"

namespace stage::metrics {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;

TEST(MetricsTest, RendersTheTextFormatWithEscapedLabelsAndHelp) {
  Registry registry;
  registry.GetCounter("stage_frames_total", "Frames seen.\nOne line.", {{"camera", "mv-01"}})->Increment(3);
  registry.GetCounter("stage_frames_total", "ignored: the family has its help", {{"camera", "a\"b\\c\nd"}})
      ->Increment();
  registry.GetGauge("stage_temperature_celsius", "Board temperature.")->Set(41.5);
  EXPECT_EQ(registry.Render(),
            "# HELP stage_frames_total Frames seen.\\nOne line.\n"
            "# TYPE stage_frames_total counter\n"
            "stage_frames_total{camera=\"mv-01\"} 3\n"
            "stage_frames_total{camera=\"a\\\"b\\\\c\\nd\"} 1\n"
            "# HELP stage_temperature_celsius Board temperature.\n"
            "# TYPE stage_temperature_celsius gauge\n"
            "stage_temperature_celsius 41.5\n");
}

TEST(MetricsTest, TheSameNameAndLabelsAreTheSameSeries) {
  Registry registry;
  Counter* a = registry.GetCounter("x_total", "x", {{"k", "v"}});
  EXPECT_EQ(a, registry.GetCounter("x_total", "x", {{"k", "v"}}));
  EXPECT_NE(a, registry.GetCounter("x_total", "x", {{"k", "w"}}));
  a->Increment(2);
  a->Increment(-1);  // ignored: counters never go down
  EXPECT_EQ(a->value(), 2);
}

TEST(MetricsTest, HistogramBucketsAreCumulativeAndInclusive) {
  Registry registry;
  Histogram* h = registry.GetHistogram("lat_seconds", "Latency.", {0.001, 0.01, 0.1}, {{"method", "Arm"}});
  for (double v : {0.0005, 0.001, 0.002, 0.5}) h->Observe(v);
  const std::string text = registry.Render();
  EXPECT_THAT(text, HasSubstr("# TYPE lat_seconds histogram\n"));
  EXPECT_THAT(text, HasSubstr("lat_seconds_bucket{method=\"Arm\",le=\"0.001\"} 2\n"));
  EXPECT_THAT(text, HasSubstr("lat_seconds_bucket{method=\"Arm\",le=\"0.01\"} 3\n"));
  EXPECT_THAT(text, HasSubstr("lat_seconds_bucket{method=\"Arm\",le=\"0.1\"} 3\n"));
  EXPECT_THAT(text, HasSubstr("lat_seconds_bucket{method=\"Arm\",le=\"+Inf\"} 4\n"));
  EXPECT_THAT(text, HasSubstr("lat_seconds_count{method=\"Arm\"} 4\n"));
  EXPECT_THAT(text, HasSubstr("lat_seconds_sum{method=\"Arm\"} 0.5035\n"));
}

TEST(MetricsTest, CollectorsJoinTheRegistrysFamiliesUntilTheirRegistrationEnds) {
  Registry registry;
  registry.GetCounter("stage_calls_total", "Calls.", {{"node", "a"}})->Increment();
  double temperature = 40;
  {
    Registration r = registry.AddCollector([&](Writer& w) {
      w.Counter("stage_calls_total", "Calls.", {{"node", "b"}}, 7);
      w.Gauge("stage_temperature_celsius", "Temperature.", {}, temperature);
    });
    temperature = 42;
    const std::string text = registry.Render();
    // One family, its HELP and TYPE once, both series under it.
    EXPECT_THAT(text, HasSubstr("# TYPE stage_calls_total counter\nstage_calls_total{node=\"a\"} 1\n"
                                "stage_calls_total{node=\"b\"} 7\n"));
    EXPECT_THAT(text, HasSubstr("stage_temperature_celsius 42\n"));
    Registration moved = std::move(r);
    EXPECT_THAT(registry.Render(), HasSubstr("stage_temperature_celsius 42\n"));
  }
  EXPECT_THAT(registry.Render(), Not(HasSubstr("stage_temperature_celsius")));
  EXPECT_THAT(registry.Render(), Not(HasSubstr("node=\"b\"")));
}

TEST(MetricsDeathTest, MisnamedMetricsAbort) {
  Registry registry;
  EXPECT_DEATH(registry.GetCounter("frames", "a counter without _total"), "end in _total");
  EXPECT_DEATH(registry.GetGauge("frames_total", "a gauge with _total"), "end in _total");
  EXPECT_DEATH(registry.GetGauge("9lives", "x"), "not a valid metric name");
  EXPECT_DEATH(registry.GetGauge("ok", "x", {{"le", "1"}}), "not a valid label name");
  EXPECT_DEATH(registry.GetGauge("ok", ""), "no help text");
  registry.GetGauge("taken", "x");
  EXPECT_DEATH(registry.GetHistogram("taken", "x", {1}), "registered as a gauge");
}

// What promtool (Debian's prometheus package) says of `text`: its exit code and output.
std::pair<int, std::string> Promtool(const std::string& text) {
  const std::string dir = std::filesystem::temp_directory_path() / ("metrics_test." + std::to_string(getpid()));
  std::filesystem::create_directories(dir);
  { std::ofstream(dir + "/in.prom") << text; }
  const std::string command = "/usr/bin/promtool check metrics < " + dir + "/in.prom > " + dir + "/out.txt 2>&1";
  const int status = std::system(command.c_str());
  std::ifstream in(dir + "/out.txt");
  std::string out((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  std::filesystem::remove_all(dir);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

TEST(MetricsTest, PromtoolAcceptsTheRegistryAndTheProcessCollector) {
  Registry registry;
  Registration process = RegisterProcessCollector(registry, "metrics_test");
  registry.GetCounter("stage_frames_received_total", "Frames received.", {{"camera", "mv-01"}})->Increment(5);
  registry.GetGauge("stage_light_temperature_celsius", "LED board temperature.")->Set(35);
  registry.GetHistogram("stage_trigger_lateness_seconds", "How late triggers fired.", ExponentialBounds(1e-6, 4, 8))
      ->Observe(3e-6);
  const std::string text = registry.Render();
  EXPECT_THAT(text, HasSubstr("process_cpu_seconds_total "));
  EXPECT_THAT(text, HasSubstr("process_resident_memory_bytes "));
  EXPECT_THAT(text, HasSubstr("stage_build_info{program=\"metrics_test\",version=\""));
  auto [code, out] = Promtool(text);
  EXPECT_EQ(code, 0) << out << "\n" << text;
  EXPECT_EQ(out, "") << text;
  // The lint is real: a misnamed unit is reported.
  auto [bad_code, bad_out] = Promtool("# HELP x_milliseconds x\n# TYPE x_milliseconds gauge\nx_milliseconds 1\n");
  EXPECT_NE(bad_code, 0);
  EXPECT_THAT(bad_out, HasSubstr("x_milliseconds"));
}

TEST(MetricsServerTest, ServesTheRegistryOverHttpUntilDestroyed) {
  Registry registry;
  registry.GetCounter("stage_scrapes_seen_total", "x")->Increment(4);
  MetricsServerOptions options;
  auto server = MetricsServer::Start(options, &registry);
  ASSERT_TRUE(server.ok()) << server.status();
  const int port = (*server)->port();
  ASSERT_GT(port, 0);
  EXPECT_EQ((*server)->address(), "127.0.0.1:" + std::to_string(port));
  {
    httplib::Client client("127.0.0.1", port);
    auto response = client.Get("/metrics");
    ASSERT_TRUE(response) << httplib::to_string(response.error());
    EXPECT_EQ(response->status, 200);
    EXPECT_EQ(response->get_header_value("Content-Type"), kContentType);
    EXPECT_THAT(response->body, HasSubstr("stage_scrapes_seen_total 4\n"));
    EXPECT_EQ(client.Get("/nothing")->status, 404);
  }
  // A second server cannot take the same port: the error names the address.
  options.listen = "127.0.0.1:" + std::to_string(port);
  auto second = MetricsServer::Start(options, &registry);
  ASSERT_FALSE(second.ok());
  EXPECT_THAT(second.status().message(), HasSubstr(options.listen));
  server->reset();
  httplib::Client client("127.0.0.1", port);
  client.set_connection_timeout(1, 0);
  EXPECT_FALSE(client.Get("/metrics"));
}

TEST(MetricsServerTest, RejectsABadAddress) {
  Registry registry;
  MetricsServerOptions options;
  options.listen = "nowhere";
  auto server = MetricsServer::Start(options, &registry);
  ASSERT_FALSE(server.ok());
  EXPECT_THAT(server.status().message(), HasSubstr("metrics listen"));
}

}  // namespace
}  // namespace stage::metrics
