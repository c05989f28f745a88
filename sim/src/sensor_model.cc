// Sensor noise and quantization.
#include "stage/sim/sensor_model.h"

#include <algorithm>
#include <cmath>
#include <random>

namespace stage::sim {

double SensorParams::Gain() const {
  if (electrons_per_dn > 0) return electrons_per_dn;
  const double levels = std::ldexp(1.0, bits) - 1 - black_level_dn;
  return full_well_e / std::max(1.0, levels);
}

int MosaicColor(const std::string& mosaic, int x, int y) {
  if (mosaic == "mono" || mosaic.size() != 2) return -1;
  // The 2x2 tile, top row then bottom row: RG -> R G / G B; GR -> G R / B G; GB -> G B / R G; BG -> B G / G R.
  static const char* kTiles[] = {"RGGB", "GRBG", "GBRG", "BGGR"};
  const char* tile = mosaic == "RG" ? kTiles[0] : mosaic == "GR" ? kTiles[1] : mosaic == "GB" ? kTiles[2] : kTiles[3];
  const char c = tile[(y & 1) * 2 + (x & 1)];
  return c == 'R' ? 0 : c == 'G' ? 1 : 2;
}

RawImage ExposeSensor(const std::vector<float>& rgb, int width, int height, double exposure_s,
                      const SensorParams& params, uint64_t seed, uint64_t stream, uint64_t frame) {
  RawImage out;
  out.width = width;
  out.height = height;
  out.bits = params.bits;
  out.data.resize(static_cast<size_t>(width) * height);
  std::seed_seq seq{static_cast<uint32_t>(seed),   static_cast<uint32_t>(seed >> 32),
                    static_cast<uint32_t>(stream), static_cast<uint32_t>(stream >> 32),
                    static_cast<uint32_t>(frame),  static_cast<uint32_t>(frame >> 32)};
  std::mt19937_64 rng(seq);
  std::normal_distribution<double> read(0.0, params.read_noise_e);
  const double gain = params.Gain();
  const double max_dn = std::ldexp(1.0, params.bits) - 1;
  const double scale = params.electrons_per_radiance_s * exposure_s;
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      const size_t i = static_cast<size_t>(y) * width + x;
      const int color = MosaicColor(params.mosaic, x, y);
      const double radiance = color < 0 ? 0.2126 * rgb[3 * i] + 0.7152 * rgb[3 * i + 1] + 0.0722 * rgb[3 * i + 2]
                                        : rgb[3 * i + static_cast<size_t>(color)];
      const double expected = std::max(0.0, radiance * scale);
      double electrons = 0;
      if (expected > 0) {
        // Poisson for small means; its normal approximation above (indistinguishable at these counts, and fast).
        if (expected < 50) {
          electrons = static_cast<double>(std::poisson_distribution<int64_t>(expected)(rng));
        } else {
          electrons = expected + std::sqrt(expected) * std::normal_distribution<double>(0.0, 1.0)(rng);
        }
      }
      electrons = std::min(electrons, params.full_well_e) + read(rng);
      const double dn = std::clamp(std::round(params.black_level_dn + electrons / gain), 0.0, max_dn);
      out.data[i] = static_cast<uint16_t>(dn);
    }
  }
  return out;
}

}  // namespace stage::sim
