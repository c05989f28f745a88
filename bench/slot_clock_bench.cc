// Lateness of the slot-clock generator's real-time mode at 912 Hz next to its baseline in the same run: a bare loop
// of absolute clock_nanosleep calls to the same edges. The variants run interleaved in rounds so that they share the
// machine's noise. Goal (issue #3): the generator's p99 within 1.2x of the bare loop's.
// Run: build/bin/slot_clock_bench [--slots 10000] [--rounds 5]
#include <sys/prctl.h>
#include <time.h>

#include <algorithm>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "CLI/CLI.hpp"
#include "stage/timing/slot_clock.h"
#include "stage/timing/time_base.h"

namespace {

using stage::timing::HostClockNs;

struct Run {
  std::vector<int64_t> late_ns;
  uint64_t missed = 0;
};

// The baseline: one thread sleeping to each edge with clock_nanosleep(TIMER_ABSTIME), nothing else.
void BareLoop(const stage::timing::TimeBase& base, int64_t first, int64_t count, unsigned long slack_ns, Run* run) {
  std::thread t([&] {
    prctl(PR_SET_TIMERSLACK, slack_ns);
    const int64_t t0 = HostClockNs(false) + 2'000'000;
    const int64_t period = 1'000'000'000 / base.slot_rate_hz();
    for (int64_t k = 0; k < count; ++k) {
      const int64_t due = t0 + base.SlotStartNs(first + k) - base.SlotStartNs(first);
      timespec ts{due / 1'000'000'000, due % 1'000'000'000};
      while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) != 0) {
      }
      const int64_t late = HostClockNs(false) - due;
      if (late >= period) ++run->missed;
      run->late_ns.push_back(late);
    }
  });
  t.join();
}

void Generator(int64_t first, int64_t count, int64_t slack_ns, int64_t spin_ns, Run* run) {
  auto gen = stage::timing::SlotClock::Create({.slot_rate_hz = 912,
                                               .t0_ns = HostClockNs(false) + 2'000'000,
                                               .first_slot = 0,
                                               .slot_count = count,
                                               .timer_slack_ns = slack_ns,
                                               .spin_ns = spin_ns});
  if (!gen.ok()) {
    std::fprintf(stderr, "slot_clock_bench: %s\n", std::string(gen.status().message()).c_str());
    std::exit(1);
  }
  run->late_ns.reserve(run->late_ns.size() + count);
  (*gen)->AddListener([run](const stage::timing::SlotEdge& e) { run->late_ns.push_back(e.actual_ns - e.scheduled_ns); });
  if (auto s = (*gen)->Start(); !s.ok()) {
    std::fprintf(stderr, "slot_clock_bench: %s\n", std::string(s.message()).c_str());
    std::exit(1);
  }
  (*gen)->Wait();
  run->missed += (*gen)->stats().missed;
}

int64_t Percentile(std::vector<int64_t> v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  size_t i = static_cast<size_t>(p / 100.0 * static_cast<double>(v.size() - 1) + 0.5);
  return v[std::min(i, v.size() - 1)];
}

void Print(const char* name, const Run& run) {
  std::printf("%-44s %9.1f %9.1f %9.1f %9.1f %7llu %7zu\n", name, Percentile(run.late_ns, 50) / 1e3,
              Percentile(run.late_ns, 99) / 1e3, Percentile(run.late_ns, 99.9) / 1e3,
              Percentile(run.late_ns, 100) / 1e3, static_cast<unsigned long long>(run.missed), run.late_ns.size());
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Slot-clock lateness at 912 Hz: the generator's real-time mode next to a bare clock_nanosleep loop, "
               "interleaved in rounds. Figures in microseconds.",
               "slot_clock_bench"};
  int64_t slots = 10000;
  int rounds = 5;
  app.add_option("--slots", slots, "Slots per variant in all")->capture_default_str()->check(CLI::Range(100, 10000000));
  app.add_option("--rounds", rounds, "Rounds the slots are split into")->capture_default_str()->check(CLI::Range(1, 1000));
  CLI11_PARSE(app, argc, argv);

  auto base = stage::timing::TimeBase::Create(912);
  Run bare_default, bare_tight, gen, gen_spin;
  const int64_t per_round = slots / rounds;
  for (int r = 0; r < rounds; ++r) {
    BareLoop(*base, 0, per_round, 50'000, &bare_default);
    BareLoop(*base, 0, per_round, 1, &bare_tight);
    Generator(0, per_round, 1, 0, &gen);
    Generator(0, per_round, 1, 20'000, &gen_spin);
    std::fprintf(stderr, "round %d of %d done\n", r + 1, rounds);
  }
  std::printf("slot clock at 912 Hz (%.3f us per slot), %lld slots per variant in %d interleaved rounds\n",
              1e6 / 912, static_cast<long long>(per_round * rounds), rounds);
  std::printf("%-44s %9s %9s %9s %9s %7s %7s\n", "lateness, us", "p50", "p99", "p99.9", "max", "missed", "edges");
  Print("baseline: bare clock_nanosleep, slack 50 us", bare_default);
  Print("baseline: bare clock_nanosleep, slack 1 ns", bare_tight);
  Print("SlotClock real time (slack 1 ns)", gen);
  Print("SlotClock real time, 20 us spin", gen_spin);
  const double ratio = static_cast<double>(Percentile(gen.late_ns, 99)) /
                       std::max<int64_t>(1, Percentile(bare_tight.late_ns, 99));
  const double ratio_default = static_cast<double>(Percentile(gen.late_ns, 99)) /
                               std::max<int64_t>(1, Percentile(bare_default.late_ns, 99));
  std::printf("generator p99 / bare loop p99: %.2fx (same timer slack), %.2fx (default slack); goal <= 1.2x\n", ratio,
              ratio_default);
  return 0;
}
