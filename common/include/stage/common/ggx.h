// The GGX microfacet lobe the stage's specular reflection is modelled with, shared by the simulator's renderer and
// photometric stereo's solvers so that both use the same one: the normal distribution D and Smith's masking G1.
#pragma once

#include <cmath>

namespace stage {

// D(h) for n . h and roughness alpha (GGX / Trowbridge-Reitz): alpha^2 / (pi (n.h^2 (alpha^2 - 1) + 1)^2).
inline float GgxDistribution(float n_dot_h, float alpha) {
  if (n_dot_h <= 0) return 0;
  const float a2 = alpha * alpha;
  const float d = n_dot_h * n_dot_h * (a2 - 1) + 1;
  return a2 / (3.14159265358979323846f * d * d);
}

// Smith's masking for one direction x: 2 n.x / (n.x + sqrt(alpha^2 + (1 - alpha^2) n.x^2)).
inline float SmithG1(float n_dot_x, float alpha) {
  if (n_dot_x <= 0) return 0;
  const float a2 = alpha * alpha;
  return 2 * n_dot_x / (n_dot_x + std::sqrt(a2 + (1 - a2) * n_dot_x * n_dot_x));
}

}  // namespace stage
