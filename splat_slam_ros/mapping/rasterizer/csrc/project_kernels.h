// EWA projection of 3D Gaussians (paper §3.2, "Rendering": Sigma' = J W Sigma W^T J^T) with
// a hand-written backward, one Gaussian per loop iteration (OpenMP). The same expressions, in
// the same order, as projection.py (project_gaussians), which is the ground truth for tests;
// templated on float / double. No torch dependency (raster.cpp binds it).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

namespace splat_raster {

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

// Everything the forward computes for one Gaussian (the backward recomputes it).
template <typename T>
struct Proj {
  T p[3];          // camera-frame centre
  bool in_front;
  T inv_z;         // 1 / z, or 1 when culled by near (safe value, as in projection.py)
  T qn[4], qnorm;  // normalised quaternion (x, y, z, w) and the clamped norm
  T Rq[9];         // rotation of the quaternion (row-major)
  T M[9];          // W R_q S (row-major)
  T xz, yz;        // x/z, y/z (not clamped)
  T tx, ty;        // clamped
  bool tx_in, ty_in;  // inside the clamp range (gradient passes)
  T A0[3], A1[3];  // rows of J W R_q S
  T a, b, c, det;
};

template <typename T>
inline void project_one(const Camera<T>& cam, const T* m, const T* q, const T* s, Proj<T>& o) {
  for (int i = 0; i < 3; ++i)
    o.p[i] = m[0] * cam.R[3 * i] + m[1] * cam.R[3 * i + 1] + m[2] * cam.R[3 * i + 2] + cam.t[i];
  o.in_front = o.p[2] > cam.near;
  o.inv_z = T(1) / (o.in_front ? o.p[2] : T(1));
  const T nrm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  o.qnorm = std::max(nrm, T(kQuatEps));
  for (int i = 0; i < 4; ++i) o.qn[i] = q[i] / o.qnorm;
  const T x = o.qn[0], y = o.qn[1], z = o.qn[2], w = o.qn[3];
  T* Rq = o.Rq;
  Rq[0] = 1 - 2 * (y * y + z * z), Rq[1] = 2 * (x * y - z * w), Rq[2] = 2 * (x * z + y * w);
  Rq[3] = 2 * (x * y + z * w), Rq[4] = 1 - 2 * (x * x + z * z), Rq[5] = 2 * (y * z - x * w);
  Rq[6] = 2 * (x * z - y * w), Rq[7] = 2 * (y * z + x * w), Rq[8] = 1 - 2 * (x * x + y * y);
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k)
      o.M[3 * i + k] = (cam.R[3 * i] * Rq[k] + cam.R[3 * i + 1] * Rq[3 + k] +
                        cam.R[3 * i + 2] * Rq[6 + k]) * s[k];
  o.xz = o.p[0] * o.inv_z;
  o.yz = o.p[1] * o.inv_z;
  o.tx = std::min(std::max(o.xz, cam.lox), cam.hix);
  o.ty = std::min(std::max(o.yz, cam.loy), cam.hiy);
  o.tx_in = o.xz >= cam.lox && o.xz <= cam.hix;
  o.ty_in = o.yz >= cam.loy && o.yz <= cam.hiy;
  const T kx = cam.fx * o.inv_z, ky = cam.fy * o.inv_z;
  for (int k = 0; k < 3; ++k) {
    o.A0[k] = kx * (o.M[k] - o.tx * o.M[6 + k]);
    o.A1[k] = ky * (o.M[3 + k] - o.ty * o.M[6 + k]);
  }
  o.a = o.A0[0] * o.A0[0] + o.A0[1] * o.A0[1] + o.A0[2] * o.A0[2] + cam.low_pass;
  o.b = o.A0[0] * o.A1[0] + o.A0[1] * o.A1[1] + o.A0[2] * o.A1[2];
  o.c = o.A1[0] * o.A1[0] + o.A1[1] * o.A1[1] + o.A1[2] * o.A1[2] + cam.low_pass;
  o.det = o.a * o.c - o.b * o.b;
}

template <typename T>
inline T clampv(T v, T lo, T hi) { return std::min(std::max(v, lo), hi); }

// Outputs per Gaussian: means2d (2), conics (3), depth, ranges (4, int32), radius, valid.
template <typename T>
void project_forward(int64_t n, const Camera<T>& cam, const T* means, const T* quats,
                     const T* scales, T* means2d, T* conics, T* depths, int32_t* ranges,
                     int32_t* radii, uint8_t* valid) {
#pragma omp parallel for schedule(static)
  for (int64_t g = 0; g < n; ++g) {
    Proj<T> o;
    project_one(cam, means + 3 * g, quats + 4 * g, scales + 3 * g, o);
    const T mx = cam.fx * o.p[0] * o.inv_z + cam.cx, my = cam.fy * o.p[1] * o.inv_z + cam.cy;
    means2d[2 * g] = mx, means2d[2 * g + 1] = my;
    conics[3 * g] = o.c / o.det, conics[3 * g + 1] = -o.b / o.det;
    conics[3 * g + 2] = o.a / o.det;
    depths[g] = o.p[2];
    const T W = T(cam.width), H = T(cam.height);
    const T ex = T(kSigmaExtent) * std::sqrt(o.a), ey = T(kSigmaExtent) * std::sqrt(o.c);
    const T x_lo = clampv(std::ceil(mx - ex), T(-1), W), x_hi = clampv(std::floor(mx + ex), T(-1), W);
    const T y_lo = clampv(std::ceil(my - ey), T(-1), H), y_hi = clampv(std::floor(my + ey), T(-1), H);
    const bool ok = o.in_front && o.det > 0 && x_lo <= x_hi && y_lo <= y_hi && x_hi >= 0 &&
                    x_lo <= W - 1 && y_hi >= 0 && y_lo <= H - 1;
    valid[g] = ok;
    int32_t* r = ranges + 4 * g;
    if (ok) {
      r[0] = int32_t(clampv(x_lo, T(0), W - 1)), r[1] = int32_t(clampv(x_hi, T(0), W - 1));
      r[2] = int32_t(clampv(y_lo, T(0), H - 1)), r[3] = int32_t(clampv(y_hi, T(0), H - 1));
      const T mid = T(0.5) * (o.a + o.c);
      const T lam = mid + std::sqrt(std::max(mid * mid - o.det, T(0.1)));
      radii[g] = int32_t(std::min(std::ceil(T(kSigmaExtent) * std::sqrt(lam)), T(1 << 30)));
    } else {
      r[0] = 1, r[1] = 0, r[2] = 1, r[3] = 0;
      radii[g] = 0;
    }
  }
}

// Gradients w.r.t. means (3), quats (4), scales (3) from those w.r.t. means2d (2), conics (3)
// and depths (1). A Gaussian whose upstream gradients are all zero gets exact zeros.
template <typename T>
void project_backward(int64_t n, const Camera<T>& cam, const T* means, const T* quats,
                      const T* scales, const T* g_m2d, const T* g_con, const T* g_dep,
                      T* d_means, T* d_quats, T* d_scales) {
#pragma omp parallel for schedule(static)
  for (int64_t g = 0; g < n; ++g) {
    const T* gm = g_m2d + 2 * g;
    const T* gc = g_con + 3 * g;
    const T gd = g_dep[g];
    T* dm = d_means + 3 * g;
    T* dq = d_quats + 4 * g;
    T* ds = d_scales + 3 * g;
    if (gm[0] == 0 && gm[1] == 0 && gc[0] == 0 && gc[1] == 0 && gc[2] == 0 && gd == 0) {
      dm[0] = dm[1] = dm[2] = 0;
      dq[0] = dq[1] = dq[2] = dq[3] = 0;
      ds[0] = ds[1] = ds[2] = 0;
      continue;
    }
    const T* s = scales + 3 * g;
    Proj<T> o;
    project_one(cam, means + 3 * g, quats + 4 * g, s, o);
    // conics = (c, -b, a) / det, det = a c - b^2
    const T idet = T(1) / o.det;
    const T ddet = -(gc[0] * o.c - gc[1] * o.b + gc[2] * o.a) * idet * idet;
    const T ga = gc[2] * idet + ddet * o.c;
    const T gb = -gc[1] * idet - T(2) * o.b * ddet;
    const T gcc = gc[0] * idet + ddet * o.a;
    // a = |A0|^2 + lp, b = A0 . A1, c = |A1|^2 + lp
    T dA0[3], dA1[3];
    for (int k = 0; k < 3; ++k) {
      dA0[k] = T(2) * ga * o.A0[k] + gb * o.A1[k];
      dA1[k] = T(2) * gcc * o.A1[k] + gb * o.A0[k];
    }
    // A0 = fx iz (M0 - tx M2), A1 = fy iz (M1 - ty M2)
    const T kx = cam.fx * o.inv_z, ky = cam.fy * o.inv_z;
    T dM[9];
    T dtx = 0, dty = 0, diz = 0;
    for (int k = 0; k < 3; ++k) {
      dM[k] = kx * dA0[k];
      dM[3 + k] = ky * dA1[k];
      dM[6 + k] = -kx * o.tx * dA0[k] - ky * o.ty * dA1[k];
      dtx -= kx * dA0[k] * o.M[6 + k];
      dty -= ky * dA1[k] * o.M[6 + k];
      diz += cam.fx * dA0[k] * (o.M[k] - o.tx * o.M[6 + k]) +
             cam.fy * dA1[k] * (o.M[3 + k] - o.ty * o.M[6 + k]);
    }
    // means2d = (fx x iz + cx, fy y iz + cy); tx = clamp(x iz), ty = clamp(y iz)
    T dp[3] = {gm[0] * cam.fx * o.inv_z, gm[1] * cam.fy * o.inv_z, gd};
    diz += gm[0] * cam.fx * o.p[0] + gm[1] * cam.fy * o.p[1];
    if (o.tx_in) dp[0] += dtx * o.inv_z, diz += dtx * o.p[0];
    if (o.ty_in) dp[1] += dty * o.inv_z, diz += dty * o.p[1];
    if (o.in_front) dp[2] += -diz * o.inv_z * o.inv_z;  // iz = 1 / z
    // p = R m + t
    for (int j = 0; j < 3; ++j)
      dm[j] = cam.R[j] * dp[0] + cam.R[3 + j] * dp[1] + cam.R[6 + j] * dp[2];
    // M = R (R_q S): d(R_q S) = R^T dM
    T dN[9];
    for (int j = 0; j < 3; ++j)
      for (int k = 0; k < 3; ++k)
        dN[3 * j + k] = cam.R[j] * dM[k] + cam.R[3 + j] * dM[3 + k] + cam.R[6 + j] * dM[6 + k];
    T dR[9];
    for (int k = 0; k < 3; ++k) {
      ds[k] = dN[k] * o.Rq[k] + dN[3 + k] * o.Rq[3 + k] + dN[6 + k] * o.Rq[6 + k];
      for (int j = 0; j < 3; ++j) dR[3 * j + k] = dN[3 * j + k] * s[k];
    }
    // R_q(x, y, z, w) of the normalised quaternion
    const T x = o.qn[0], y = o.qn[1], z = o.qn[2], w = o.qn[3];
    T dqn[4];
    dqn[0] = T(2) * (y * (dR[1] + dR[3]) + z * (dR[2] + dR[6]) + w * (dR[7] - dR[5]) -
                     T(2) * x * (dR[4] + dR[8]));
    dqn[1] = T(2) * (x * (dR[1] + dR[3]) + w * (dR[2] - dR[6]) + z * (dR[5] + dR[7]) -
                     T(2) * y * (dR[0] + dR[8]));
    dqn[2] = T(2) * (w * (dR[3] - dR[1]) + x * (dR[2] + dR[6]) + y * (dR[5] + dR[7]) -
                     T(2) * z * (dR[0] + dR[4]));
    dqn[3] = T(2) * (z * (dR[3] - dR[1]) + y * (dR[2] - dR[6]) + x * (dR[7] - dR[5]));
    // qn = q / max(|q|, eps)
    if (o.qnorm > T(kQuatEps)) {
      const T dot = dqn[0] * x + dqn[1] * y + dqn[2] * z + dqn[3] * w;
      for (int i = 0; i < 4; ++i) dq[i] = (dqn[i] - o.qn[i] * dot) / o.qnorm;
    } else {
      for (int i = 0; i < 4; ++i) dq[i] = dqn[i] / o.qnorm;
    }
  }
}

}  // namespace splat_raster
