// Eq. 11's data terms of one rendered view, forward and backward in one pass each:
//   L = lambda / (3 h w) sum |a V C + b - I / 255|_1 + (1 - lambda) / (h w) sum w |D^r - D|_1
// with the keyframe's exposure (a = exp(log a), b), the vignetting V = max(0.1, 1 + v1 r^2 +
// v2 r^4) (1 without it) and the depth-loss weights w (the validity mask or the proxy
// depth's weights). ``optimise.view_loss`` is the torch reference (the same expressions,
// float32). Each row is gathered into contiguous buffers and computed on lane vectors
// (lanes.h); its sums are kept per lane, added across the lanes once, and the rows' sums are
// added in double in row order (deterministic whatever the threads). The target image,
// depth and weights may be strided (a pixel lattice of the keyframe: every n-th row and
// column).
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "lanes.h"

namespace splat_loss {
using namespace splat_lanes;

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

constexpr float kVignetteMin = 0.1f;   // camera_model.CameraModel.vignetting's clamp

// One row of the inputs, gathered into contiguous float buffers (the targets may be
// strided) padded to whole lane vectors (the padding: zero weights, live 0; r2 stays 0
// without vignetting).
struct Row {
  int64_t w, wpad;
  std::vector<float> c0, c1, c2, i0, i1, i2, d, td, wt, r2, live;
  explicit Row(int64_t width)
      : w(width), wpad((width + kLanes - 1) / kLanes * kLanes), c0(wpad), c1(wpad), c2(wpad),
        i0(wpad), i1(wpad), i2(wpad), d(wpad), td(wpad), wt(wpad), r2(wpad), live(wpad, 0.f) {
    for (int64_t x = 0; x < w; ++x) live[x] = 1.f;
  }
  void load(const ViewLossArgs& p, int64_t y) {
    const uint8_t* img = static_cast<const uint8_t*>(p.image.ptr) + y * p.image.row;
    const float* tdr = static_cast<const float*>(p.target_depth.ptr) + y * p.target_depth.row;
    const int64_t ic = p.image.col, tc = p.target_depth.col, wc = p.weight.col;
    const float* rgb = p.rgb + 3 * y * w;
    for (int64_t x = 0; x < w; ++x) {
      c0[x] = rgb[3 * x], c1[x] = rgb[3 * x + 1], c2[x] = rgb[3 * x + 2];
      // the 8-bit values; divided by 255 lane-wise (image())
      i0[x] = float(img[x * ic]), i1[x] = float(img[x * ic + 1]), i2[x] = float(img[x * ic + 2]);
      td[x] = tdr[x * tc];
    }
    std::memcpy(d.data(), p.depth + y * w, sizeof(float) * w);
    if (p.weight_is_mask) {
      const uint8_t* m = static_cast<const uint8_t*>(p.weight.ptr) + y * p.weight.row;
      for (int64_t x = 0; x < w; ++x) wt[x] = float(m[x * wc] != 0);
    } else {
      const float* f = static_cast<const float*>(p.weight.ptr) + y * p.weight.row;
      for (int64_t x = 0; x < w; ++x) wt[x] = f[x * wc];
    }
    if (p.r2 != nullptr) std::memcpy(r2.data(), p.r2 + y * w, sizeof(float) * w);
    for (int64_t x = w; x < wpad; ++x)
      c0[x] = c1[x] = c2[x] = i0[x] = i1[x] = i2[x] = d[x] = td[x] = wt[x] = r2[x] = 0.f;
  }
  // the target colour of channel c at lanes x..: the 8-bit value / 255
  vf image(int c, int64_t x) const {
    const float* I = c == 0 ? &i0[x] : c == 1 ? &i1[x] : &i2[x];
    return vload(I) / 255.0f;
  }
};

// 1 + v1 r^2 + v2 r^4 before the clamp (1 without vignetting), lane-wise
inline vf vignette_raw(const ViewLossArgs& p, vf r2) {
  if (p.r2 == nullptr) return vsplat(1.f);
  return (1.0f + p.v1 * r2) + (p.v2 * r2) * r2;
}

inline vf clamp_vignette(vf v) { return vsel(v < kVignetteMin, vsplat(kVignetteMin), v); }

// The loss (double; the caller rounds it to float32).
inline double view_loss_forward(const ViewLossArgs& p) {
  std::vector<double> row_rgb(p.h), row_d(p.h);
#pragma omp parallel
  {
    Row r(p.w);
#pragma omp for schedule(static)
    for (int64_t y = 0; y < p.h; ++y) {
      r.load(p, y);
      vf s_rgb = {}, s_d = {};
      for (int64_t x = 0; x < r.wpad; x += kLanes) {
        const vf V = clamp_vignette(vignette_raw(p, vload(&r.r2[x]))), live = vload(&r.live[x]);
        const float* C[3] = {&r.c0[x], &r.c1[x], &r.c2[x]};
        for (int c = 0; c < 3; ++c) {
          const vf e = (vload(C[c]) * V) * p.a + p.b - r.image(c, x);
          s_rgb += vabs(e) * live;
        }
        s_d += vabs(vload(&r.d[x]) - vload(&r.td[x])) * vload(&r.wt[x]);
      }
      row_rgb[y] = hsum(s_rgb);
      row_d[y] = hsum(s_d);
    }
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
#pragma omp parallel
  {
    Row r(p.w);
    std::vector<float> g0(r.wpad), g1(r.wpad), g2(r.wpad), gd(r.wpad);
#pragma omp for schedule(static)
    for (int64_t y = 0; y < p.h; ++y) {
      r.load(p, y);
      vf d_a = {}, d_b = {}, d_v1 = {}, d_v2 = {};
      for (int64_t x = 0; x < r.wpad; x += kLanes) {
        const vf raw = vignette_raw(p, vload(&r.r2[x])), V = clamp_vignette(raw);
        const vf live = vload(&r.live[x]);
        const float* C[3] = {&r.c0[x], &r.c1[x], &r.c2[x]};
        float* G[3] = {&g0[x], &g1[x], &g2[x]};
        vf d_V = {};
        for (int c = 0; c < 3; ++c) {
          const vf col = vload(C[c]), rv = col * V;
          const vf s = c_rgb * vsign(rv * p.a + p.b - r.image(c, x)) * live;
          vstore(G[c], s * p.a * V);
          d_b += s;
          d_a += s * rv;
          d_V += s * p.a * col;
        }
        if (p.r2 != nullptr) {   // not clamped: the vignetting's gradient
          const vf r2 = vload(&r.r2[x]), dv = vsel(raw >= kVignetteMin, d_V, vf{});
          d_v1 += dv * r2;
          d_v2 += dv * r2 * r2;
        }
        vstore(&gd[x], c_d * vsign(vload(&r.d[x]) - vload(&r.td[x])) * vload(&r.wt[x]));
      }
      for (int64_t x = 0; x < p.w; ++x) {
        const int64_t i = y * p.w + x;
        g_rgb[3 * i] = g0[x], g_rgb[3 * i + 1] = g1[x], g_rgb[3 * i + 2] = g2[x];
        g_depth[i] = gd[x];
      }
      rows[4 * y] = hsum(d_a);
      rows[4 * y + 1] = hsum(d_b);
      rows[4 * y + 2] = hsum(d_v1);
      rows[4 * y + 3] = hsum(d_v2);
    }
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
