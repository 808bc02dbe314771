// EWA projection of 3D Gaussians (paper §3.2, "Rendering": Sigma' = J W Sigma W^T J^T) with
// a hand-written backward. The same expressions as projection.py (project_gaussians), which
// is the ground truth for tests. Written once for a value type V: float32 runs kLanes
// Gaussians at a time on lane vectors (lanes.h; masks instead of branches), float64 one
// Gaussian per loop iteration. No torch dependency (raster.cpp binds it).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>

#include "lanes.h"

namespace splat_raster {
using namespace splat_lanes;

constexpr double kSigmaExtent = 3.0;  // projection.SIGMA_EXTENT
constexpr double kFovClamp = 0.3;     // projection.FOV_CLAMP
constexpr double kQuatEps = 1e-8;     // geometry._EPS (quaternion normalisation)

template <typename T>
struct Camera {
  T R[9], t[3];               // world-to-camera rotation (row-major) and translation
  T fx, fy, cx, cy, near;
  T low_pass;                 // added to the 2D covariance diagonal, px^2 (projection.LOW_PASS)
  T lox, hix, loy, hiy;       // clamp range of x/z, y/z (frustum widened by kFovClamp)
  int64_t width, height;
};

template <typename T>
Camera<T> make_camera(const T* viewmat, double fx, double fy, double cx, double cy,
                      int64_t width, int64_t height, double near, double low_pass) {
  Camera<T> c;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) c.R[3 * i + j] = viewmat[4 * i + j];
    c.t[i] = viewmat[4 * i + 3];
  }
  c.fx = T(fx), c.fy = T(fy), c.cx = T(cx), c.cy = T(cy), c.near = T(near);
  c.low_pass = T(low_pass);
  const double tan_x = 0.5 * double(width) / fx, tan_y = 0.5 * double(height) / fy;
  c.lox = T(-(cx / fx + kFovClamp * tan_x));
  c.hix = T((double(width) - cx) / fx + kFovClamp * tan_x);
  c.loy = T(-(cy / fy + kFovClamp * tan_y));
  c.hiy = T((double(height) - cy) / fy + kFovClamp * tan_y);
  c.width = width, c.height = height;
  return c;
}

// ---------------------------------------------------------- scalar / lane-vector helpers
// The same code runs on V = float or double (one Gaussian, bool masks) and on V = vf (kLanes
// Gaussians, vi masks). max_ / min_ are std::max / std::min, NaN behaviour included.
template <typename V>
using MaskOf = decltype(V{} < V{});
template <typename V>
constexpr int kLanesOf = std::is_same_v<V, vf> ? kLanes : 1;   // Gaussians per value
template <typename V>
inline V lit(double c) {
  if constexpr (std::is_same_v<V, vf>) return vsplat(float(c));
  else return V(c);
}
inline float sel_(bool m, float a, float b) { return m ? a : b; }
inline double sel_(bool m, double a, double b) { return m ? a : b; }
inline vf sel_(vi m, vf a, vf b) { return vsel(m, a, b); }
inline bool and_(bool a, bool b) { return a && b; }
inline vi and_(vi a, vi b) { return a & b; }
template <typename V>
inline V max_(V a, V b) { return sel_(a < b, b, a); }
template <typename V>
inline V min_(V a, V b) { return sel_(b < a, b, a); }
inline float sqrt_(float x) { return std::sqrt(x); }
inline double sqrt_(double x) { return std::sqrt(x); }
inline float ceil_(float x) { return std::ceil(x); }
inline double ceil_(double x) { return std::ceil(x); }
inline float floor_(float x) { return std::floor(x); }
inline double floor_(double x) { return std::floor(x); }
inline vf sqrt_(vf x) {
#if defined(__AVX__)
  return __builtin_ia32_sqrtps256(x);
#else
  for (int l = 0; l < kLanes; ++l) x[l] = std::sqrt(x[l]);
  return x;
#endif
}
// ceil (Mode 0x0a: toward +inf) or floor (0x09: toward -inf), lane-wise, no exceptions
template <int Mode>
inline vf round_(vf x) {
#if defined(__AVX__)
  return __builtin_ia32_roundps256(x, Mode);
#else
  for (int l = 0; l < kLanes; ++l) x[l] = Mode == 0x0a ? std::ceil(x[l]) : std::floor(x[l]);
  return x;
#endif
}
inline vf ceil_(vf x) { return round_<0x0a>(x); }
inline vf floor_(vf x) { return round_<0x09>(x); }
inline int32_t to_int(float x) { return int32_t(x); }
inline int32_t to_int(double x) { return int32_t(x); }
inline vi to_int(vf x) { return __builtin_convertvector(x, vi); }

// Everything the forward computes for one Gaussian (or a lane vector of them); the backward
// recomputes it.
template <typename V>
struct Proj {
  using M = MaskOf<V>;
  V p[3];          // camera-frame centre
  M in_front;
  V inv_z;         // 1 / z, or 1 when culled by near (safe value, as in projection.py)
  V qn[4], qnorm;  // normalised quaternion (x, y, z, w) and the clamped norm
  V Rq[9];         // rotation of the quaternion (row-major)
  V M_[9];         // W R_q S (row-major)
  V xz, yz;        // x/z, y/z (not clamped)
  V tx, ty;        // clamped
  M tx_in, ty_in;  // inside the clamp range (gradient passes)
  V A0[3], A1[3];  // rows of J W R_q S
  V a, b, c, det;
};

// m: centre (3), q: quaternion (x, y, z, w), s: scales (3).
template <typename T, typename V>
inline void project_one(const Camera<T>& cam, const V* m, const V* q, const V* s, Proj<V>& o) {
  const V one = lit<V>(1), two = lit<V>(2);
  for (int i = 0; i < 3; ++i)
    o.p[i] = m[0] * cam.R[3 * i] + m[1] * cam.R[3 * i + 1] + m[2] * cam.R[3 * i + 2] + cam.t[i];
  o.in_front = o.p[2] > cam.near;
  o.inv_z = one / sel_(o.in_front, o.p[2], one);
  const V nrm = sqrt_(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  o.qnorm = max_(nrm, lit<V>(kQuatEps));
  for (int i = 0; i < 4; ++i) o.qn[i] = q[i] / o.qnorm;
  const V x = o.qn[0], y = o.qn[1], z = o.qn[2], w = o.qn[3];
  V* Rq = o.Rq;
  Rq[0] = one - two * (y * y + z * z), Rq[1] = two * (x * y - z * w);
  Rq[2] = two * (x * z + y * w), Rq[3] = two * (x * y + z * w);
  Rq[4] = one - two * (x * x + z * z), Rq[5] = two * (y * z - x * w);
  Rq[6] = two * (x * z - y * w), Rq[7] = two * (y * z + x * w);
  Rq[8] = one - two * (x * x + y * y);
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k)
      o.M_[3 * i + k] = (cam.R[3 * i] * Rq[k] + cam.R[3 * i + 1] * Rq[3 + k] +
                         cam.R[3 * i + 2] * Rq[6 + k]) * s[k];
  o.xz = o.p[0] * o.inv_z;
  o.yz = o.p[1] * o.inv_z;
  o.tx = min_(max_(o.xz, lit<V>(cam.lox)), lit<V>(cam.hix));
  o.ty = min_(max_(o.yz, lit<V>(cam.loy)), lit<V>(cam.hiy));
  o.tx_in = and_(o.xz >= cam.lox, o.xz <= cam.hix);
  o.ty_in = and_(o.yz >= cam.loy, o.yz <= cam.hiy);
  const V kx = cam.fx * o.inv_z, ky = cam.fy * o.inv_z;
  for (int k = 0; k < 3; ++k) {
    o.A0[k] = kx * (o.M_[k] - o.tx * o.M_[6 + k]);
    o.A1[k] = ky * (o.M_[3 + k] - o.ty * o.M_[6 + k]);
  }
  o.a = o.A0[0] * o.A0[0] + o.A0[1] * o.A0[1] + o.A0[2] * o.A0[2] + cam.low_pass;
  o.b = o.A0[0] * o.A1[0] + o.A0[1] * o.A1[1] + o.A0[2] * o.A1[2];
  o.c = o.A1[0] * o.A1[0] + o.A1[1] * o.A1[1] + o.A1[2] * o.A1[2] + cam.low_pass;
  o.det = o.a * o.c - o.b * o.b;
}

template <typename V>
inline V clampv(V v, V lo, V hi) { return min_(max_(v, lo), hi); }

// The forward's outputs of one Gaussian (or lane vector): means2d, conics, depth, the
// footprint (inclusive pixel ranges; 1, 0, 1, 0 when not valid), the radius and valid.
template <typename V>
struct ProjOut {
  V mx, my, con[3], depth;
  decltype(to_int(V{})) r[4], radius;
  MaskOf<V> ok;
};

template <typename T, typename V>
inline ProjOut<V> project_outputs(const Camera<T>& cam, const Proj<V>& o) {
  ProjOut<V> out;
  const V mx = cam.fx * o.p[0] * o.inv_z + cam.cx, my = cam.fy * o.p[1] * o.inv_z + cam.cy;
  out.mx = mx, out.my = my;
  out.con[0] = o.c / o.det, out.con[1] = -o.b / o.det, out.con[2] = o.a / o.det;
  out.depth = o.p[2];
  const V W = lit<V>(double(cam.width)), H = lit<V>(double(cam.height));
  const V zero = lit<V>(0), one = lit<V>(1), m1 = lit<V>(-1), ext = lit<V>(kSigmaExtent);
  const V Wm = W - one, Hm = H - one;
  const V ex = ext * sqrt_(o.a), ey = ext * sqrt_(o.c);
  const V x_lo = clampv(ceil_(mx - ex), m1, W), x_hi = clampv(floor_(mx + ex), m1, W);
  const V y_lo = clampv(ceil_(my - ey), m1, H), y_hi = clampv(floor_(my + ey), m1, H);
  out.ok = and_(and_(and_(o.in_front, o.det > zero), and_(x_lo <= x_hi, y_lo <= y_hi)),
                and_(and_(x_hi >= zero, x_lo <= Wm), and_(y_hi >= zero, y_lo <= Hm)));
  // not valid: the empty footprint (1, 0, 1, 0) and radius 0
  out.r[0] = to_int(sel_(out.ok, clampv(x_lo, zero, Wm), one));
  out.r[1] = to_int(sel_(out.ok, clampv(x_hi, zero, Wm), zero));
  out.r[2] = to_int(sel_(out.ok, clampv(y_lo, zero, Hm), one));
  out.r[3] = to_int(sel_(out.ok, clampv(y_hi, zero, Hm), zero));
  const V mid = lit<V>(0.5) * (o.a + o.c);
  const V lam = mid + sqrt_(max_(mid * mid - o.det, lit<V>(0.1)));
  out.radius = to_int(sel_(out.ok, min_(ceil_(ext * sqrt_(lam)), lit<V>(double(1 << 30))), zero));
  return out;
}

// Lane l of a vector, or the scalar itself; set_lane writes it.
template <typename X>
inline auto lane(const X& x, int l) {
  if constexpr (std::is_arithmetic_v<X>) return x;
  else return x[l];
}
template <typename X, typename S>
inline void set_lane(X& x, int l, S v) {
  if constexpr (std::is_arithmetic_v<X>) x = v;
  else x[l] = v;
}

// Gaussians g0 .. g0 + cnt - 1 into lane vectors (the last one repeated in the spare lanes)
// or, for a scalar V, Gaussian g0: centres m (3), quaternions q (4), scales s (3).
template <typename T, typename V>
inline void gather_gaussians(const T* means, const T* quats, const T* scales, int64_t g0,
                             int cnt, V* m, V* q, V* s) {
  constexpr int L = kLanesOf<V>;
  for (int l = 0; l < L; ++l) {
    const int64_t g = g0 + std::min(l, cnt - 1);
    for (int k = 0; k < 3; ++k) set_lane(m[k], l, means[3 * g + k]);
    for (int k = 0; k < 4; ++k) set_lane(q[k], l, quats[4 * g + k]);
    for (int k = 0; k < 3; ++k) set_lane(s[k], l, scales[3 * g + k]);
  }
}

// Gradients w.r.t. the centre (3), quaternion (4) and scales (3) of one Gaussian (or lane
// vector) from those w.r.t. means2d (gm, 2), conics (gc, 3) and depth (gd).
template <typename T, typename V>
inline void project_grads(const Camera<T>& cam, const V* m, const V* q, const V* s,
                          const V* gm, const V* gc, V gd, V* dm, V* dq, V* ds) {
  const V zero = lit<V>(0), two = lit<V>(2);
  Proj<V> o;
  project_one(cam, m, q, s, o);
  // conics = (c, -b, a) / det, det = a c - b^2
  const V idet = lit<V>(1) / o.det;
  const V ddet = -(gc[0] * o.c - gc[1] * o.b + gc[2] * o.a) * idet * idet;
  const V ga = gc[2] * idet + ddet * o.c;
  const V gb = -gc[1] * idet - two * o.b * ddet;
  const V gcc = gc[0] * idet + ddet * o.a;
  // a = |A0|^2 + lp, b = A0 . A1, c = |A1|^2 + lp
  V dA0[3], dA1[3];
  for (int k = 0; k < 3; ++k) {
    dA0[k] = two * ga * o.A0[k] + gb * o.A1[k];
    dA1[k] = two * gcc * o.A1[k] + gb * o.A0[k];
  }
  // A0 = fx iz (M0 - tx M2), A1 = fy iz (M1 - ty M2)
  const V kx = cam.fx * o.inv_z, ky = cam.fy * o.inv_z;
  V dM[9];
  V dtx = zero, dty = zero, diz = zero;
  for (int k = 0; k < 3; ++k) {
    dM[k] = kx * dA0[k];
    dM[3 + k] = ky * dA1[k];
    dM[6 + k] = -kx * o.tx * dA0[k] - ky * o.ty * dA1[k];
    dtx -= kx * dA0[k] * o.M_[6 + k];
    dty -= ky * dA1[k] * o.M_[6 + k];
    diz += cam.fx * dA0[k] * (o.M_[k] - o.tx * o.M_[6 + k]) +
           cam.fy * dA1[k] * (o.M_[3 + k] - o.ty * o.M_[6 + k]);
  }
  // means2d = (fx x iz + cx, fy y iz + cy); tx = clamp(x iz), ty = clamp(y iz)
  V dp[3] = {gm[0] * cam.fx * o.inv_z, gm[1] * cam.fy * o.inv_z, gd};
  diz += gm[0] * cam.fx * o.p[0] + gm[1] * cam.fy * o.p[1];
  dp[0] += sel_(o.tx_in, dtx * o.inv_z, zero);
  diz += sel_(o.tx_in, dtx * o.p[0], zero);
  dp[1] += sel_(o.ty_in, dty * o.inv_z, zero);
  diz += sel_(o.ty_in, dty * o.p[1], zero);
  dp[2] += sel_(o.in_front, -diz * o.inv_z * o.inv_z, zero);  // iz = 1 / z
  // p = R m + t
  for (int j = 0; j < 3; ++j)
    dm[j] = cam.R[j] * dp[0] + cam.R[3 + j] * dp[1] + cam.R[6 + j] * dp[2];
  // M = R (R_q S): d(R_q S) = R^T dM
  V dN[9];
  for (int j = 0; j < 3; ++j)
    for (int k = 0; k < 3; ++k)
      dN[3 * j + k] = cam.R[j] * dM[k] + cam.R[3 + j] * dM[3 + k] + cam.R[6 + j] * dM[6 + k];
  V dR[9];
  for (int k = 0; k < 3; ++k) {
    ds[k] = dN[k] * o.Rq[k] + dN[3 + k] * o.Rq[3 + k] + dN[6 + k] * o.Rq[6 + k];
    for (int j = 0; j < 3; ++j) dR[3 * j + k] = dN[3 * j + k] * s[k];
  }
  // R_q(x, y, z, w) of the normalised quaternion
  const V x = o.qn[0], y = o.qn[1], z = o.qn[2], w = o.qn[3];
  V dqn[4];
  dqn[0] = two * (y * (dR[1] + dR[3]) + z * (dR[2] + dR[6]) + w * (dR[7] - dR[5]) -
                  two * x * (dR[4] + dR[8]));
  dqn[1] = two * (x * (dR[1] + dR[3]) + w * (dR[2] - dR[6]) + z * (dR[5] + dR[7]) -
                  two * y * (dR[0] + dR[8]));
  dqn[2] = two * (w * (dR[3] - dR[1]) + x * (dR[2] + dR[6]) + y * (dR[5] + dR[7]) -
                  two * z * (dR[0] + dR[4]));
  dqn[3] = two * (z * (dR[3] - dR[1]) + y * (dR[2] - dR[6]) + x * (dR[7] - dR[5]));
  // qn = q / max(|q|, eps): the normalisation's gradient above eps, a plain scale below
  const auto normed = o.qnorm > lit<V>(kQuatEps);
  const V dot = dqn[0] * x + dqn[1] * y + dqn[2] * z + dqn[3] * w;
  for (int i = 0; i < 4; ++i)
    dq[i] = sel_(normed, (dqn[i] - o.qn[i] * dot) / o.qnorm, dqn[i] / o.qnorm);
}

// Outputs per Gaussian: means2d (2), conics (3), depth, ranges (4, int32), radius, valid.
template <typename T>
void project_forward(int64_t n, const Camera<T>& cam, const T* means, const T* quats,
                     const T* scales, T* means2d, T* conics, T* depths, int32_t* ranges,
                     int32_t* radii, uint8_t* valid) {
  // float32: kLanes Gaussians at a time (gather_gaussians)
  using V = std::conditional_t<std::is_same_v<T, float>, vf, T>;
  constexpr int L = kLanesOf<V>;
  const int64_t blocks = (n + L - 1) / L;
#pragma omp parallel for schedule(static)
  for (int64_t b = 0; b < blocks; ++b) {
    const int64_t g0 = b * L;
    const int cnt = int(std::min<int64_t>(L, n - g0));
    V m[3], q[4], s[3];
    gather_gaussians(means, quats, scales, g0, cnt, m, q, s);
    Proj<V> o;
    project_one(cam, m, q, s, o);
    const ProjOut<V> out = project_outputs(cam, o);
    for (int l = 0; l < cnt; ++l) {
      const int64_t g = g0 + l;
      means2d[2 * g] = lane(out.mx, l), means2d[2 * g + 1] = lane(out.my, l);
      for (int k = 0; k < 3; ++k) conics[3 * g + k] = lane(out.con[k], l);
      depths[g] = lane(out.depth, l);
      for (int k = 0; k < 4; ++k) ranges[4 * g + k] = lane(out.r[k], l);
      radii[g] = lane(out.radius, l);
      valid[g] = lane(out.ok, l) != 0;
    }
  }
}

// Gradients w.r.t. means (3), quats (4), scales (3) from those w.r.t. means2d (2), conics (3)
// and depths (1). A Gaussian whose upstream gradients are all zero gets exact zeros (a block
// of them is not computed at all).
template <typename T>
void project_backward(int64_t n, const Camera<T>& cam, const T* means, const T* quats,
                      const T* scales, const T* g_m2d, const T* g_con, const T* g_dep,
                      T* d_means, T* d_quats, T* d_scales) {
  using V = std::conditional_t<std::is_same_v<T, float>, vf, T>;
  constexpr int L = kLanesOf<V>;
  const int64_t blocks = (n + L - 1) / L;
#pragma omp parallel for schedule(static)
  for (int64_t b = 0; b < blocks; ++b) {
    const int64_t g0 = b * L;
    const int cnt = int(std::min<int64_t>(L, n - g0));
    bool zero[L], any = false;
    for (int l = 0; l < cnt; ++l) {
      const int64_t g = g0 + l;
      const T* gm = g_m2d + 2 * g;
      const T* gc = g_con + 3 * g;
      zero[l] = gm[0] == 0 && gm[1] == 0 && gc[0] == 0 && gc[1] == 0 && gc[2] == 0 &&
                g_dep[g] == 0;
      if (zero[l]) {
        for (int k = 0; k < 3; ++k) d_means[3 * g + k] = 0, d_scales[3 * g + k] = 0;
        for (int k = 0; k < 4; ++k) d_quats[4 * g + k] = 0;
      }
      any |= !zero[l];
    }
    if (!any) continue;
    V m[3], q[4], s[3], gm[2], gc[3], gd;
    gather_gaussians(means, quats, scales, g0, cnt, m, q, s);
    for (int l = 0; l < L; ++l) {
      const int64_t g = g0 + std::min(l, cnt - 1);
      for (int k = 0; k < 2; ++k) set_lane(gm[k], l, g_m2d[2 * g + k]);
      for (int k = 0; k < 3; ++k) set_lane(gc[k], l, g_con[3 * g + k]);
      set_lane(gd, l, g_dep[g]);
    }
    V dm[3], dq[4], ds[3];
    project_grads(cam, m, q, s, gm, gc, gd, dm, dq, ds);
    for (int l = 0; l < cnt; ++l) {
      const int64_t g = g0 + l;
      if (zero[l]) continue;   // zeros written above
      for (int k = 0; k < 3; ++k) d_means[3 * g + k] = lane(dm[k], l);
      for (int k = 0; k < 4; ++k) d_quats[4 * g + k] = lane(dq[k], l);
      for (int k = 0; k < 3; ++k) d_scales[3 * g + k] = lane(ds[k], l);
    }
  }
}

}  // namespace splat_raster
