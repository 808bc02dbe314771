// Per-edge terms of the dense bundle adjustment (paper Eq. 1; tracking/dense_ba.py, whose
// torch _edge_terms/_edge_blocks are the reference): for each edge (i -> j) and BA pixel
// the residual r = target - pi(G_ji pi^-1(p, d_i)), its sqrt-weighted Jacobians w.r.t. the
// source pose (Jp, the target pose's is -Jp) and the source disparity (Jd), reduced at once
// to what the Schur-complement solve needs: H_e = Jp^T W Jp (6x6), v_e = Jp^T W r (6), and
// per pixel the coupling a = Jp^T W Jd (6), the disparity diagonal c = Jd^T W Jd and the
// right-hand side b = Jd^T W r. Jp and Jd are never stored.
//
// Pixels run in float lanes (lanes.h); the 6x6 and 6-vector sums are flushed from float
// lanes into double per image row. One OpenMP task per edge. No torch dependency.
#pragma once

#include <cmath>
#include <cstdint>

#include "lanes.h"

namespace splat_ba {
using namespace splat_lanes;

struct EdgeGeometry {   // float32, row-major
  float Rji[9], tji[3];  // camera i -> camera j
  float Ri[9], ti[3];    // camera i -> world (homogeneous world point: Ri q + ti d)
  float Rj[9];           // camera j -> world rotation (its columns)
};

// One edge over its h x w BA pixels. Inputs: d (P), target (P, 2), weight (P, 2); outputs:
// a (P, 6), c (P), b (P); H (36, row-major), v (6) and stats (cost, weight sum, valid pixels)
// in double.
inline void edge_blocks(const EdgeGeometry& g, const float intr[4], int h, int w, float huber,
                        const float* d, const float* target, const float* weight, float* a,
                        float* c, float* b, double* H, double* v, double* stats) {
  const float fx = intr[0], fy = intr[1], cx = intr[2], cy = intr[3];
  double Hd[21] = {0}, vd[6] = {0}, cost = 0, wsum = 0;
  int64_t n_valid = 0;
  constexpr int L = kLanes;
  for (int y = 0; y < h; ++y) {
    vf Hl[21], vl[6], cl = vf{}, wl = vf{};
    vi nl = vi{};
    for (auto& x : Hl) x = vf{};
    for (auto& x : vl) x = vf{};
    const float qy = (float(y) - cy) / fy;
    for (int x0 = 0; x0 < w; x0 += L) {
      const int n = w - x0 < L ? w - x0 : L;
      const int64_t p0 = int64_t(y) * w + x0;
      vf qx, dd, t0, t1, w0, w1;
      for (int l = 0; l < L; ++l) {   // lanes past the row's end: zero weight
        const bool in = l < n;
        qx[l] = (float(x0 + l) - cx) / fx;
        dd[l] = in ? d[p0 + l] : 1.f;
        t0[l] = in ? target[2 * (p0 + l)] : 0.f;
        t1[l] = in ? target[2 * (p0 + l) + 1] : 0.f;
        w0[l] = in ? weight[2 * (p0 + l)] : 0.f;
        w1[l] = in ? weight[2 * (p0 + l) + 1] : 0.f;
      }
      // X = Rji q + tji d (camera j), Xw = Ri q + ti d (world, homogeneous)
      vf X[3], Xw[3];
      for (int r = 0; r < 3; ++r) {
        X[r] = qx * g.Rji[3 * r] + (g.Rji[3 * r + 1] * qy + g.Rji[3 * r + 2]) + dd * g.tji[r];
        Xw[r] = qx * g.Ri[3 * r] + (g.Ri[3 * r + 1] * qy + g.Ri[3 * r + 2]) + dd * g.ti[r];
      }
      const vf z = X[2];
      const vf dmin = vsel(dd > 1e-6f, dd, vsplat(1e-6f));
      const vi valid = z > dmin * 1e-3f;
      const vf iz = 1.f / vsel(z > 1e-6f, z, vsplat(1e-6f));
      const vf xz = X[0] * iz, yz = X[1] * iz;
      vf r0 = t0 - (fx * xz + cx), r1 = t1 - (fy * yz + cy);
      w0 = vsel(valid, w0, vf{});
      w1 = vsel(valid, w1, vf{});
      if (huber > 0.f) {
        const vf rn2 = r0 * r0 + r1 * r1;
        vf rn;
        for (int l = 0; l < L; ++l) rn[l] = std::sqrt(rn2[l]);
        const vf s = vsel(rn > huber, huber / vsel(rn > 1e-12f, rn, vsplat(1e-12f)),
                          vsplat(1.f));
        w0 = w0 * s;
        w1 = w1 * s;
      }
      r0 = vsel(valid, r0, vf{});
      r1 = vsel(valid, r1, vf{});
      vf sw0, sw1;
      for (int l = 0; l < L; ++l) { sw0[l] = std::sqrt(w0[l]); sw1[l] = std::sqrt(w1[l]); }
      const vf rs0 = r0 * sw0, rs1 = r1 * sw1;
      const vf sa = fx * iz * sw0, sb = fy * iz * sw1;
      // rows of d(pixel)/d(Xw) = Jproj Rj^T: M0 = sa (c0 - xz c2), M1 = sb (c1 - yz c2)
      vf M0[3], M1[3];
      for (int k = 0; k < 3; ++k) {
        M0[k] = sa * (g.Rj[3 * k] - xz * g.Rj[3 * k + 2]);
        M1[k] = sb * (g.Rj[3 * k + 1] - yz * g.Rj[3 * k + 2]);
      }
      // pose Jacobian rows [d M, Xw x M] (left world-frame perturbation, xi = (t, w))
      vf J0[6], J1[6];
      for (int k = 0; k < 3; ++k) { J0[k] = M0[k] * dd; J1[k] = M1[k] * dd; }
      J0[3] = Xw[1] * M0[2] - Xw[2] * M0[1];
      J0[4] = Xw[2] * M0[0] - Xw[0] * M0[2];
      J0[5] = Xw[0] * M0[1] - Xw[1] * M0[0];
      J1[3] = Xw[1] * M1[2] - Xw[2] * M1[1];
      J1[4] = Xw[2] * M1[0] - Xw[0] * M1[2];
      J1[5] = Xw[0] * M1[1] - Xw[1] * M1[0];
      const vf Jd0 = sa * (g.tji[0] - xz * g.tji[2]);
      const vf Jd1 = sb * (g.tji[1] - yz * g.tji[2]);
      int u = 0;
      for (int r = 0; r < 6; ++r) {
        for (int s = r; s < 6; ++s) Hl[u++] += J0[r] * J0[s] + J1[r] * J1[s];
        vl[r] += J0[r] * rs0 + J1[r] * rs1;
      }
      cl += rs0 * rs0 + rs1 * rs1;
      wl += w0 + w1;
      nl += (w0 + w1 > 0.f) & 1;
      vf ak[6];
      for (int k = 0; k < 6; ++k) ak[k] = J0[k] * Jd0 + J1[k] * Jd1;
      const vf ck = Jd0 * Jd0 + Jd1 * Jd1, bk = Jd0 * rs0 + Jd1 * rs1;
      for (int l = 0; l < n; ++l) {
        float* ap = a + 6 * (p0 + l);
        for (int k = 0; k < 6; ++k) ap[k] = ak[k][l];
        c[p0 + l] = ck[l];
        b[p0 + l] = bk[l];
      }
    }
    for (int u = 0; u < 21; ++u) Hd[u] += hsum(Hl[u]);
    for (int r = 0; r < 6; ++r) vd[r] += hsum(vl[r]);
    cost += hsum(cl);
    wsum += hsum(wl);
    n_valid += vsum(nl);
  }
  int u = 0;
  for (int r = 0; r < 6; ++r)
    for (int s = r; s < 6; ++s, ++u) H[6 * r + s] = H[6 * s + r] = Hd[u];
  for (int r = 0; r < 6; ++r) v[r] = vd[r];
  stats[0] = cost;
  stats[1] = wsum;
  stats[2] = double(n_valid);
}

}  // namespace splat_ba
