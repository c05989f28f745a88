// Prometheus metrics: the registry and the text exposition format.
#include "stage/common/metrics.h"

#include <dirent.h>
#include <sys/resource.h>
#include <unistd.h>

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "fmt/format.h"
#include "stage/common/logging.h"
#include "stage/common/version.h"

namespace stage::metrics {
namespace {

bool ValidName(absl::string_view name, bool label) {
  if (name.empty()) return false;
  for (size_t i = 0; i < name.size(); ++i) {
    const char c = name[i];
    const bool alpha = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || c == '_' || (!label && c == ':');
    if (!alpha && !(i > 0 && c >= '0' && c <= '9')) return false;
  }
  return !(label && name.substr(0, 2) == "__");
}

[[noreturn]] void Misuse(const std::string& what) {
  Logger("metrics")->critical("{}", what);
  std::fprintf(stderr, "metrics: %s\n", what.c_str());
  std::abort();
}

std::string Escape(absl::string_view text, bool quotes) {
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    if (c == '\\') {
      out += "\\\\";
    } else if (c == '\n') {
      out += "\\n";
    } else if (c == '"' && quotes) {
      out += "\\\"";
    } else {
      out += c;
    }
  }
  return out;
}

// {a="b",c="d"}, or "" without labels.
std::string RenderLabels(absl::string_view family, const Labels& labels) {
  if (labels.empty()) return "";
  std::string out = "{";
  for (const auto& [k, v] : labels) {
    if (!ValidName(k, /*label=*/true) || k == "le" || k == "quantile") {
      Misuse(absl::StrCat("metric ", family, ": \"", k, "\" is not a valid label name"));
    }
    if (out.size() > 1) out += ",";
    absl::StrAppend(&out, k, "=\"", Escape(v, /*quotes=*/true), "\"");
  }
  return out + "}";
}

// `labels` rendered ({...} or "") with one more label appended.
std::string WithLabel(const std::string& labels, const std::string& extra) {
  if (labels.empty()) return absl::StrCat("{", extra, "}");
  return absl::StrCat(labels.substr(0, labels.size() - 1), ",", extra, "}");
}

std::string FormatValue(double v) {
  if (std::isnan(v)) return "NaN";
  if (std::isinf(v)) return v > 0 ? "+Inf" : "-Inf";
  return fmt::format("{}", v);
}

const char* TypeName(Type t) {
  switch (t) {
    case Type::kCounter:
      return "counter";
    case Type::kGauge:
      return "gauge";
    case Type::kHistogram:
      return "histogram";
  }
  return "untyped";
}

void CheckFamilyName(Type type, absl::string_view name) {
  if (!ValidName(name, /*label=*/false)) Misuse(absl::StrCat("\"", name, "\" is not a valid metric name"));
  const bool total = name.size() > 6 && name.substr(name.size() - 6) == "_total";
  if ((type == Type::kCounter) != total) {
    Misuse(absl::StrCat("metric ", name, ": counters, and only counters, end in _total"));
  }
}

}  // namespace

void Counter::Increment(double by) {
  if (!(by >= 0)) {
    Logger("metrics")->error("a counter was asked to step by {}; ignored (counters never go down)", by);
    return;
  }
  value_.fetch_add(by, std::memory_order_relaxed);
}

Histogram::Histogram(std::vector<double> bounds)
    : bounds_(std::move(bounds)), counts_(new std::atomic<uint64_t>[bounds_.size() + 1]) {
  for (size_t i = 0; i < bounds_.size(); ++i) {
    if (!std::isfinite(bounds_[i]) || (i > 0 && bounds_[i] <= bounds_[i - 1])) {
      Misuse("histogram bounds must be finite and strictly increasing");
    }
  }
  for (size_t i = 0; i <= bounds_.size(); ++i) counts_[i].store(0, std::memory_order_relaxed);
}

void Histogram::Observe(double v) {
  size_t i = 0;
  while (i < bounds_.size() && v > bounds_[i]) ++i;
  counts_[i].fetch_add(1, std::memory_order_relaxed);
  sum_.fetch_add(v, std::memory_order_relaxed);
}

Histogram::Snapshot Histogram::Read() const {
  Snapshot s;
  s.bounds = bounds_;
  uint64_t running = 0;
  for (size_t i = 0; i <= bounds_.size(); ++i) {
    running += counts_[i].load(std::memory_order_relaxed);
    s.cumulative.push_back(running);
  }
  s.count = running;
  s.sum = sum_.load(std::memory_order_relaxed);
  return s;
}

std::vector<double> ExponentialBounds(double start, double factor, int count) {
  std::vector<double> bounds;
  double b = start;
  for (int i = 0; i < count; ++i, b *= factor) bounds.push_back(b);
  return bounds;
}

void Writer::Counter(absl::string_view name, absl::string_view help, const Labels& labels, double value) {
  Add(Type::kCounter, name, help, labels, value);
}

void Writer::Gauge(absl::string_view name, absl::string_view help, const Labels& labels, double value) {
  Add(Type::kGauge, name, help, labels, value);
}

void Writer::Add(Type type, absl::string_view name, absl::string_view help, const Labels& labels, double value) {
  CheckFamilyName(type, name);
  auto [it, fresh] = families_.try_emplace(std::string(name));
  Family& f = it->second;
  if (fresh) {
    f.type = type;
    f.help = std::string(help);
  } else if (f.type != type) {
    Misuse(absl::StrCat("metric ", name, " collected as a ", TypeName(type), " and as a ", TypeName(f.type)));
  }
  f.samples.push_back({RenderLabels(name, labels), value});
}

Registration& Registration::operator=(Registration&& other) noexcept {
  if (this != &other) {
    if (registry_ != nullptr) registry_->Remove(id_);
    registry_ = std::exchange(other.registry_, nullptr);
    id_ = other.id_;
  }
  return *this;
}

Registration::~Registration() {
  if (registry_ != nullptr) registry_->Remove(id_);
}

Registry& Registry::Default() {
  static Registry* registry = new Registry();
  return *registry;
}

Registry::Series* Registry::Get(Type type, absl::string_view name, absl::string_view help, const Labels& labels,
                                const std::vector<double>* bounds) {
  CheckFamilyName(type, name);
  if (help.empty()) Misuse(absl::StrCat("metric ", name, " has no help text"));
  std::string rendered = RenderLabels(name, labels);
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = families_.find(name);
  if (it == families_.end()) {
    it = families_
             .emplace(std::string(name), Family{type, std::string(help), bounds ? *bounds : std::vector<double>{}, {}})
             .first;
  } else if (it->second.type != type) {
    Misuse(absl::StrCat("metric ", name, " asked for as a ", TypeName(type), ", registered as a ",
                        TypeName(it->second.type)));
  }
  Family& f = it->second;
  for (auto& s : f.series) {
    if (s->labels == rendered) return s.get();
  }
  auto s = std::make_unique<Series>();
  s->labels = std::move(rendered);
  switch (type) {
    case Type::kCounter:
      s->counter = std::make_unique<metrics::Counter>();
      break;
    case Type::kGauge:
      s->gauge = std::make_unique<metrics::Gauge>();
      break;
    case Type::kHistogram:
      s->histogram = std::make_unique<metrics::Histogram>(f.bounds);
      break;
  }
  f.series.push_back(std::move(s));
  return f.series.back().get();
}

Counter* Registry::GetCounter(absl::string_view name, absl::string_view help, const Labels& labels) {
  return Get(Type::kCounter, name, help, labels, nullptr)->counter.get();
}

Gauge* Registry::GetGauge(absl::string_view name, absl::string_view help, const Labels& labels) {
  return Get(Type::kGauge, name, help, labels, nullptr)->gauge.get();
}

Histogram* Registry::GetHistogram(absl::string_view name, absl::string_view help, const std::vector<double>& bounds,
                                  const Labels& labels) {
  return Get(Type::kHistogram, name, help, labels, &bounds)->histogram.get();
}

Registration Registry::AddCollector(std::function<void(Writer&)> collect) {
  std::lock_guard<std::mutex> lock(collect_mutex_);
  const uint64_t id = next_collector_++;
  collectors_.emplace(id, std::move(collect));
  return Registration(this, id);
}

void Registry::Remove(uint64_t id) {
  // Waits for a scrape that is running the collector: once this returns it is never called again.
  std::lock_guard<std::mutex> lock(collect_mutex_);
  collectors_.erase(id);
}

std::string Registry::Render() const {
  Writer collected;
  {
    std::lock_guard<std::mutex> lock(collect_mutex_);
    for (const auto& [id, collect] : collectors_) collect(collected);
  }
  std::map<std::string, std::string> text;  // family name -> its lines (HELP and TYPE first)
  auto header = [](const std::string& name, const std::string& help, Type type) {
    return absl::StrCat("# HELP ", name, " ", Escape(help, /*quotes=*/false), "\n# TYPE ", name, " ", TypeName(type),
                        "\n");
  };
  std::map<std::string, Type> types;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& [name, f] : families_) {
      std::string& out = text[name];
      out = header(name, f.help, f.type);
      types[name] = f.type;
      for (const auto& s : f.series) {
        if (s->counter) absl::StrAppend(&out, name, s->labels, " ", FormatValue(s->counter->value()), "\n");
        if (s->gauge) absl::StrAppend(&out, name, s->labels, " ", FormatValue(s->gauge->value()), "\n");
        if (!s->histogram) continue;
        const Histogram::Snapshot h = s->histogram->Read();
        for (size_t i = 0; i <= h.bounds.size(); ++i) {
          const std::string le = i < h.bounds.size() ? FormatValue(h.bounds[i]) : "+Inf";
          absl::StrAppend(&out, name, "_bucket", WithLabel(s->labels, absl::StrCat("le=\"", le, "\"")), " ",
                          h.cumulative[i], "\n");
        }
        absl::StrAppend(&out, name, "_sum", s->labels, " ", FormatValue(h.sum), "\n");
        absl::StrAppend(&out, name, "_count", s->labels, " ", h.count, "\n");
      }
    }
  }
  for (const auto& [name, f] : collected.families_) {
    auto known = types.find(name);
    if (known != types.end() && known->second != f.type) {
      Misuse(absl::StrCat("metric ", name, " collected as a ", TypeName(f.type), ", registered as a ",
                          TypeName(known->second)));
    }
    std::string& out = text[name];
    if (out.empty()) out = header(name, f.help, f.type);
    for (const auto& s : f.samples) absl::StrAppend(&out, name, s.labels, " ", FormatValue(s.value), "\n");
  }
  std::string all;
  for (const auto& [name, lines] : text) all += lines;
  return all;
}

namespace {

// /proc/self/stat's fields after the command name: utime and stime (ticks) are the 12th and 13th, starttime (ticks
// since boot) the 20th.
bool ReadProcStat(double* cpu_seconds, double* start_ticks) {
  std::ifstream in("/proc/self/stat");
  std::string line;
  if (!std::getline(in, line)) return false;
  const size_t paren = line.rfind(')');
  if (paren == std::string::npos) return false;
  std::istringstream fields(line.substr(paren + 2));
  std::vector<std::string> f;
  std::string field;
  while (fields >> field) f.push_back(field);
  if (f.size() < 20) return false;
  const double tick = static_cast<double>(sysconf(_SC_CLK_TCK));
  *cpu_seconds = (std::stod(f[11]) + std::stod(f[12])) / tick;
  *start_ticks = std::stod(f[19]);
  return true;
}

double BootTimeSeconds() {
  std::ifstream in("/proc/stat");
  std::string key;
  double value;
  while (in >> key) {
    if (key == "btime" && in >> value) return value;
    in.ignore(1 << 20, '\n');
  }
  return 0;
}

int OpenDescriptors() {
  DIR* dir = opendir("/proc/self/fd");
  if (dir == nullptr) return -1;
  int n = 0;
  while (readdir(dir) != nullptr) ++n;
  closedir(dir);
  return n - 3;  // ".", ".." and the directory's own descriptor
}

}  // namespace

Registration RegisterProcessCollector(Registry& registry, absl::string_view program) {
  registry
      .GetGauge("stage_build_info", "FaStage's build: 1, labelled with the program and the version",
                {{"program", std::string(program)}, {"version", std::string(kVersion)}})
      ->Set(1);
  const double boot = BootTimeSeconds();
  const double tick = static_cast<double>(sysconf(_SC_CLK_TCK));
  const long page = sysconf(_SC_PAGESIZE);
  return registry.AddCollector([boot, tick, page](Writer& w) {
    double cpu = 0, start = 0;
    if (ReadProcStat(&cpu, &start)) {
      w.Counter("process_cpu_seconds_total", "Total user and system CPU time spent in seconds.", {}, cpu);
      if (boot > 0) {
        w.Gauge("process_start_time_seconds", "Start time of the process since unix epoch in seconds.", {},
                boot + start / tick);
      }
    }
    std::ifstream statm("/proc/self/statm");
    long size_pages = 0, resident_pages = 0;
    if (statm >> size_pages >> resident_pages) {
      w.Gauge("process_resident_memory_bytes", "Resident memory size in bytes.", {},
              static_cast<double>(resident_pages) * static_cast<double>(page));
      w.Gauge("process_virtual_memory_bytes", "Virtual memory size in bytes.", {},
              static_cast<double>(size_pages) * static_cast<double>(page));
    }
    const int fds = OpenDescriptors();
    if (fds >= 0) w.Gauge("process_open_fds", "Number of open file descriptors.", {}, fds);
    rlimit limit{};
    if (getrlimit(RLIMIT_NOFILE, &limit) == 0 && limit.rlim_cur != RLIM_INFINITY) {
      w.Gauge("process_max_fds", "Maximum number of open file descriptors.", {}, static_cast<double>(limit.rlim_cur));
    }
  });
}

}  // namespace stage::metrics
