// LED emission over time.
#include "stage/sim/emission.h"

#include <algorithm>
#include <cmath>

namespace stage::sim {

double ChannelWaveform::Ramp(const StepAt& s, int64_t x) const {
  const double dt = static_cast<double>(x - s.t);
  if (s.level >= s.start) {
    return rise_ns_ <= 0 ? s.level : std::min(s.level, s.start + dt / static_cast<double>(rise_ns_));
  }
  return fall_ns_ <= 0 ? s.level : std::max(s.level, s.start - dt / static_cast<double>(fall_ns_));
}

int64_t ChannelWaveform::Reach(const StepAt& s) const {
  const int64_t per_full_scale = s.level >= s.start ? rise_ns_ : fall_ns_;
  if (per_full_scale <= 0) return s.t;
  return s.t + static_cast<int64_t>(std::ceil(std::abs(s.level - s.start) * static_cast<double>(per_full_scale)));
}

double ChannelWaveform::RampIntegral(const StepAt& s, int64_t a, int64_t b) const {
  if (b <= a) return 0;
  const int64_t reach = Reach(s);
  double sum = 0;
  const int64_t linear_end = std::min(b, reach);
  if (linear_end > a) {
    // Linear between a and linear_end: the trapezoid is exact.
    sum += static_cast<double>(linear_end - a) * (Ramp(s, a) + Ramp(s, linear_end)) / 2;
  }
  const int64_t flat_start = std::max(a, reach);
  if (b > flat_start) sum += static_cast<double>(b - flat_start) * s.level;
  return sum;
}

void ChannelWaveform::Step(int64_t t_ns, double level) {
  level = std::clamp(level, 0.0, 1.0);
  if (!steps_.empty() && steps_.back().t == t_ns) {
    steps_.back().level = level;
    return;
  }
  steps_.push_back({t_ns, level, At(t_ns)});
}

double ChannelWaveform::At(int64_t t_ns) const {
  auto it = std::upper_bound(steps_.begin(), steps_.end(), t_ns, [](int64_t t, const StepAt& s) { return t < s.t; });
  if (it == steps_.begin()) return 0;
  return Ramp(*std::prev(it), t_ns);
}

double ChannelWaveform::Integral(int64_t t0_ns, int64_t t1_ns) const {
  if (t1_ns <= t0_ns) return 0;
  double sum = 0;
  // Before the first step the output is 0. Each step's ramp holds until the next step.
  for (size_t i = 0; i < steps_.size(); ++i) {
    const int64_t a = std::max(t0_ns, steps_[i].t);
    const int64_t b = std::min(t1_ns, i + 1 < steps_.size() ? steps_[i + 1].t : INT64_MAX);
    if (b > a) sum += RampIntegral(steps_[i], a, b);
    if (i + 1 < steps_.size() && steps_[i + 1].t >= t1_ns) break;
  }
  return sum;
}

void ChannelWaveform::Forget(int64_t t_ns) {
  auto it = std::upper_bound(steps_.begin(), steps_.end(), t_ns, [](int64_t t, const StepAt& s) { return t < s.t; });
  if (it == steps_.begin()) return;
  steps_.erase(steps_.begin(), std::prev(it));
}

EmissionState::EmissionState(const Dome& dome, std::vector<int64_t> rise_ns, std::vector<int64_t> fall_ns)
    : dome_(dome), rise_ns_(std::move(rise_ns)), fall_ns_(std::move(fall_ns)) {}

void EmissionState::SetLevels(int node, int64_t t_ns, const std::vector<double>& levels) {
  std::lock_guard<std::mutex> lock(mutex_);
  const int64_t rise = node < static_cast<int>(rise_ns_.size()) ? rise_ns_[static_cast<size_t>(node)] : 0;
  const int64_t fall = node < static_cast<int>(fall_ns_.size()) ? fall_ns_[static_cast<size_t>(node)] : 0;
  for (size_t c = 0; c < levels.size(); ++c) {
    auto [it, inserted] = channels_.try_emplace({node, static_cast<uint32_t>(c)}, rise, fall);
    it->second.Step(t_ns, levels[c]);
  }
}

void EmissionState::Dark(int node, int64_t t_ns) {
  std::lock_guard<std::mutex> lock(mutex_);
  for (auto& [key, wave] : channels_) {
    if (key.first == node) wave.Step(t_ns, 0);
  }
}

void EmissionState::SetUnitFault(size_t unit, UnitFault fault) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (unit >= dome_.units.size()) return;
  if (fault.dead || fault.delay_ns != 0) {
    unit_faults_[unit] = fault;
  } else {
    unit_faults_.erase(unit);
  }
}

void EmissionState::Forget(int64_t t_ns) {
  std::lock_guard<std::mutex> lock(mutex_);
  for (auto& [key, wave] : channels_) wave.Forget(t_ns);
}

EmitterLevels EmissionState::AverageLevels(int64_t t0_ns, int64_t t1_ns) const {
  const Eigen::Index n = static_cast<Eigen::Index>(dome_.units.size());
  EmitterLevels out{Eigen::VectorXf::Zero(n), Eigen::VectorXf::Zero(n)};
  if (t1_ns <= t0_ns) return out;
  const double span = static_cast<double>(t1_ns - t0_ns);
  std::lock_guard<std::mutex> lock(mutex_);
  auto average = [&](int node, uint32_t channel, int64_t delay) {
    auto it = channels_.find({node, channel});
    return it == channels_.end() ? 0.0f : static_cast<float>(it->second.Integral(t0_ns - delay, t1_ns - delay) / span);
  };
  for (Eigen::Index l = 0; l < n; ++l) {
    const LedUnitModel& u = dome_.units[static_cast<size_t>(l)];
    int64_t delay = 0;
    if (auto f = unit_faults_.find(static_cast<size_t>(l)); f != unit_faults_.end()) {
      if (f->second.dead) continue;
      delay = f->second.delay_ns;
    }
    out.cross[l] = average(u.node, u.cross_channel, delay);
    out.parallel[l] = average(u.node, u.parallel_channel, delay);
  }
  return out;
}

}  // namespace stage::sim
