// Eq. 11's data terms of one rendered view, forward and backward in one pass each:
//   L = lambda / (3 h w) sum |a V C + b - I / 255|_1 + (1 - lambda) / (h w) sum w |D^r - D|_1
// with the keyframe's exposure (a = exp(log a), b), the vignetting V = max(0.1, 1 + v1 r^2 +
// v2 r^4) (1 without it) and the depth-loss weights w (the validity mask or the proxy
// depth's weights). ``optimise.view_loss`` is the torch reference (the same expressions,
// float32, in the same order); sums are kept per row in double and added in row order
// (deterministic whatever the threads). The target image, depth and weights may be strided
// (a pixel lattice of the keyframe: every n-th row and column).
#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

namespace splat_loss {

struct Strided {            // element (y, x) at ptr[y * row + x * col]
  const void* ptr;
  int64_t row, col;
};

struct ViewLossArgs {
  int64_t h, w;
  const float* rgb;         // (h, w, 3) contiguous render
  const float* depth;       // (h, w) contiguous render
  Strided image;            // uint8 (h, w, 3): channel stride 1
  Strided target_depth;     // float
  Strided weight;           // float, or uint8 (bool mask) when weight_is_mask
  bool weight_is_mask;
  const float* r2;          // (h, w) contiguous r^2 map, or nullptr: no vignetting
  float v1, v2;             // vignetting
  float a, b;               // exposure: a = exp(log a)
  float lam;                // rgb weight lambda
};

inline float sgn(float x) { return float((x > 0.f) - (x < 0.f)); }

inline float weight_at(const ViewLossArgs& p, int64_t y, int64_t x) {
  const int64_t o = y * p.weight.row + x * p.weight.col;
  return p.weight_is_mask ? float(static_cast<const uint8_t*>(p.weight.ptr)[o] != 0)
                          : static_cast<const float*>(p.weight.ptr)[o];
}

constexpr float kVignetteMin = 0.1f;   // camera_model.CameraModel.vignetting's clamp

// 1 + v1 r^2 + v2 r^4 at pixel i before the clamp (1 without vignetting)
inline float vignette_raw(const ViewLossArgs& p, int64_t i) {
  if (p.r2 == nullptr) return 1.f;
  const float r2 = p.r2[i];
  return 1.0f + p.v1 * r2 + p.v2 * r2 * r2;
}

inline float clamp_vignette(float v) { return v < kVignetteMin ? kVignetteMin : v; }

// The loss (double; the caller rounds it to float32).
inline double view_loss_forward(const ViewLossArgs& p) {
  std::vector<double> row_rgb(p.h), row_d(p.h);
#pragma omp parallel for schedule(static)
  for (int64_t y = 0; y < p.h; ++y) {
    const uint8_t* img = static_cast<const uint8_t*>(p.image.ptr) + y * p.image.row;
    const float* td = static_cast<const float*>(p.target_depth.ptr) + y * p.target_depth.row;
    double s_rgb = 0.0, s_d = 0.0;
    for (int64_t x = 0; x < p.w; ++x) {
      const int64_t i = y * p.w + x;
      const float V = clamp_vignette(vignette_raw(p, i));
      for (int c = 0; c < 3; ++c) {
        const float e = (p.rgb[3 * i + c] * V) * p.a + p.b -
                        float(img[x * p.image.col + c]) / 255.0f;
        s_rgb += std::fabs(e);
      }
      s_d += std::fabs(p.depth[i] - td[x * p.target_depth.col]) * weight_at(p, y, x);
    }
    row_rgb[y] = s_rgb;
    row_d[y] = s_d;
  }
  double s_rgb = 0.0, s_d = 0.0;
  for (int64_t y = 0; y < p.h; ++y) {
    s_rgb += row_rgb[y];
    s_d += row_d[y];
  }
  const double n = double(p.h) * double(p.w);
  return double(p.lam) * s_rgb / (3.0 * n) + (1.0 - double(p.lam)) * s_d / n;
}

struct ViewLossParamGrad {
  double log_a, b, v1, v2;
};

// Gradients of g * L: g_rgb (h, w, 3) and g_depth (h, w) written, the exposure's and the
// vignetting's returned.
inline ViewLossParamGrad view_loss_backward(const ViewLossArgs& p, float g, float* g_rgb,
                                            float* g_depth) {
  const float c_rgb = float(double(g) * double(p.lam) / (3.0 * double(p.h) * double(p.w)));
  const float c_d = float(double(g) * (1.0 - double(p.lam)) / (double(p.h) * double(p.w)));
  std::vector<double> rows(4 * p.h);
#pragma omp parallel for schedule(static)
  for (int64_t y = 0; y < p.h; ++y) {
    const uint8_t* img = static_cast<const uint8_t*>(p.image.ptr) + y * p.image.row;
    const float* td = static_cast<const float*>(p.target_depth.ptr) + y * p.target_depth.row;
    double d_a = 0.0, d_b = 0.0, d_v1 = 0.0, d_v2 = 0.0;
    for (int64_t x = 0; x < p.w; ++x) {
      const int64_t i = y * p.w + x;
      const float raw = vignette_raw(p, i), V = clamp_vignette(raw);
      float d_V = 0.f;
      for (int c = 0; c < 3; ++c) {
        const float rv = p.rgb[3 * i + c] * V;
        const float s = c_rgb * sgn(rv * p.a + p.b - float(img[x * p.image.col + c]) / 255.0f);
        g_rgb[3 * i + c] = s * p.a * V;
        d_b += s;
        d_a += double(s) * double(rv);
        d_V += s * p.a * p.rgb[3 * i + c];
      }
      if (p.r2 != nullptr && raw >= kVignetteMin) {   // not clamped
        const float r2 = p.r2[i];
        d_v1 += double(d_V) * r2;
        d_v2 += double(d_V) * r2 * r2;
      }
      g_depth[i] = c_d * sgn(p.depth[i] - td[x * p.target_depth.col]) * weight_at(p, y, x);
    }
    rows[4 * y] = d_a;
    rows[4 * y + 1] = d_b;
    rows[4 * y + 2] = d_v1;
    rows[4 * y + 3] = d_v2;
  }
  ViewLossParamGrad out{0.0, 0.0, 0.0, 0.0};
  for (int64_t y = 0; y < p.h; ++y) {
    out.log_a += rows[4 * y];
    out.b += rows[4 * y + 1];
    out.v1 += rows[4 * y + 2];
    out.v2 += rows[4 * y + 3];
  }
  out.log_a *= double(p.a);   // d/d(log a) = a d/da
  return out;
}

}  // namespace splat_loss
