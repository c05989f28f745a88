// The simulated image sensor: light to electrons to digital numbers. Per pixel, the expected signal in electrons is
// the radiance of the pixel's Bayer colour (or the luminance, for mono formats) times the exposure time times the
// sensor's sensitivity; photon shot noise (Poisson), read noise (Gaussian, electrons), full-well clipping, gain
// (electrons per digital number), black level, and quantization to 8 or 12 bits follow. Deterministic: the noise of
// a frame depends only on the seed, the camera and the frame counter.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace stage::sim {

struct SensorParams {
  // Electrons per unit of radiance per second of exposure.
  double electrons_per_radiance_s = 1.0;
  // Full-well capacity and read noise, electrons.
  double full_well_e = 10000;
  double read_noise_e = 5;
  // Digital numbers: bits (8 or 12), black level (DN), and gain = full_well / (2^bits - 1 - black) unless set.
  int bits = 8;
  double black_level_dn = 0;
  double electrons_per_dn = 0;
  // "RG" (RGGB Bayer), "GR", "GB", "BG", or "mono".
  std::string mosaic = "RG";

  double Gain() const;  // electrons per DN in use
};

// The frame a sensor reads out: width x height values, row-major, one per pixel (its Bayer colour).
struct RawImage {
  int width = 0;
  int height = 0;
  int bits = 8;
  std::vector<uint16_t> data;
};

// `rgb`: linear radiance, width x height x 3, row-major. `seed`, `stream` (e.g. a hash of the camera id) and
// `frame` select the noise.
RawImage ExposeSensor(const std::vector<float>& rgb, int width, int height, double exposure_s,
                      const SensorParams& params, uint64_t seed, uint64_t stream, uint64_t frame);

// Which colour (0 R, 1 G, 2 B) pixel (x, y) sees under `mosaic`; -1 for mono.
int MosaicColor(const std::string& mosaic, int x, int y);

}  // namespace stage::sim
