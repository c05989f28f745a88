// Prometheus metrics of a FaStage process: counters, gauges and histograms updated where things happen, collectors
// that read a component's own statistics when the metrics are scraped, and the text exposition format (0.0.4) that
// Prometheus and promtool read. One registry per process (Registry::Default()); MetricsServer (metrics_server.h)
// serves it over HTTP.
//
// Names follow Prometheus' conventions (promtool's lint): base units (seconds, bytes, ratios), counters end in
// `_total`, every family has help text. A name or label that breaks the exposition format is a programming error: the
// registry logs it and aborts, as a failed CHECK would, so a test finds it before an operator's scraper does.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/string_view.h"

namespace stage::metrics {

// Label names and values of one series, in the order given.
using Labels = std::vector<std::pair<std::string, std::string>>;

enum class Type { kCounter, kGauge, kHistogram };

// A count that only goes up (frames received, calls handled).
class Counter {
 public:
  // `by` must be >= 0 (a negative step is ignored and logged: a counter never goes down).
  void Increment(double by = 1);
  double value() const { return value_.load(std::memory_order_relaxed); }

 private:
  std::atomic<double> value_{0};
};

// A value that goes up and down (a temperature, a queue's depth).
class Gauge {
 public:
  void Set(double v) { value_.store(v, std::memory_order_relaxed); }
  void Add(double by) { value_.fetch_add(by, std::memory_order_relaxed); }
  double value() const { return value_.load(std::memory_order_relaxed); }

 private:
  std::atomic<double> value_{0};
};

// Observations counted into buckets by upper bound (a latency's distribution). Lock-free.
class Histogram {
 public:
  // `bounds`: the buckets' upper bounds, strictly increasing, finite (+Inf is implied).
  explicit Histogram(std::vector<double> bounds);
  void Observe(double v);

  struct Snapshot {
    std::vector<double> bounds;
    std::vector<uint64_t> cumulative;  // one per bound, then +Inf (== count)
    double sum = 0;
    uint64_t count = 0;
  };
  Snapshot Read() const;

 private:
  std::vector<double> bounds_;
  std::unique_ptr<std::atomic<uint64_t>[]> counts_;  // bounds_.size() + 1 (the last: above every bound)
  std::atomic<double> sum_{0};
};

// `count` bounds from `start`, each `factor` times the one before (Prometheus' ExponentialBuckets).
std::vector<double> ExponentialBounds(double start, double factor, int count);

// What a collector writes at scrape time: samples of families it reads from elsewhere. Samples of one name are merged
// into one family, with the registry's own if it has one of that name and type.
class Writer {
 public:
  void Counter(absl::string_view name, absl::string_view help, const Labels& labels, double value);
  void Gauge(absl::string_view name, absl::string_view help, const Labels& labels, double value);

 private:
  friend class Registry;
  struct Sample {
    std::string labels;  // rendered: {a="b",c="d"} or ""
    double value;
  };
  struct Family {
    Type type;
    std::string help;
    std::vector<Sample> samples;
  };
  void Add(Type type, absl::string_view name, absl::string_view help, const Labels& labels, double value);
  std::map<std::string, Family> families_;
};

class Registry;

// Keeps a collector registered; removes it when destroyed (the component it reads from is going away).
class Registration {
 public:
  Registration() = default;
  Registration(Registration&& other) noexcept { *this = std::move(other); }
  Registration& operator=(Registration&& other) noexcept;
  ~Registration();

 private:
  friend class Registry;
  Registration(Registry* registry, uint64_t id) : registry_(registry), id_(id) {}
  Registry* registry_ = nullptr;
  uint64_t id_ = 0;
};

class Registry {
 public:
  Registry() = default;
  Registry(const Registry&) = delete;
  Registry& operator=(const Registry&) = delete;

  // The process's registry, what MetricsServer serves. Never destroyed: metrics outlive every thread that updates
  // them.
  static Registry& Default();

  // The series `name`{labels}, made on first use; the same name and labels give the same object, valid as long as
  // the registry. The help text is the family's (the first one given counts). Aborts when the name is taken by a
  // family of another type or a name or label is not valid.
  Counter* GetCounter(absl::string_view name, absl::string_view help, const Labels& labels = {});
  Gauge* GetGauge(absl::string_view name, absl::string_view help, const Labels& labels = {});
  // The bounds are the family's: every series of one histogram family has the first series' bounds.
  Histogram* GetHistogram(absl::string_view name, absl::string_view help, const std::vector<double>& bounds,
                          const Labels& labels = {});

  // Calls `collect` at every scrape, until the returned registration is destroyed. It runs on the scraping thread:
  // it must be thread-safe and quick (read counters, not compute).
  [[nodiscard]] Registration AddCollector(std::function<void(Writer&)> collect);

  // Every family in the text exposition format, version 0.0.4 (sorted by name; series in creation order).
  std::string Render() const;

 private:
  friend class Registration;
  struct Series {
    std::string labels;  // rendered
    std::unique_ptr<metrics::Counter> counter;
    std::unique_ptr<metrics::Gauge> gauge;
    std::unique_ptr<metrics::Histogram> histogram;
  };
  struct Family {
    Type type;
    std::string help;
    std::vector<double> bounds;
    std::vector<std::unique_ptr<Series>> series;
  };
  Series* Get(Type type, absl::string_view name, absl::string_view help, const Labels& labels,
              const std::vector<double>* bounds);
  void Remove(uint64_t id);

  mutable std::mutex mutex_;
  std::map<std::string, Family, std::less<>> families_;  // guarded by mutex_
  // Held while collectors run (a scrape) and while one is removed, so a removed collector is never running; never
  // held with mutex_ (a collector may ask for a series).
  mutable std::mutex collect_mutex_;
  std::map<uint64_t, std::function<void(Writer&)>> collectors_;  // guarded by collect_mutex_
  uint64_t next_collector_ = 1;                                  // guarded by collect_mutex_
};

// The standard process_* families (CPU seconds, resident memory, open descriptors, start time, from /proc/self) and
// stage_build_info{program,version}, collected into `registry` while the registration is kept.
[[nodiscard]] Registration RegisterProcessCollector(Registry& registry, absl::string_view program);

// The content type of Render()'s output, for the HTTP response.
inline constexpr char kContentType[] = "text/plain; version=0.0.4; charset=utf-8";

}  // namespace stage::metrics
