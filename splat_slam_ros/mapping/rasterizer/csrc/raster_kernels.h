// Tile-based CPU rasterizer kernels for 3D Gaussian splatting (paper §3.2, "Rendering"):
// forward compositing of colour, depth and alpha, the covisibility flag of the
// supplementary, and a hand-written backward. No torch dependency (raster.cpp binds it);
// projection (EWA) happens in torch.
//
// Rules (identical to reference.py, which is the ground truth):
//  * Gaussian g touches pixel (x, y) only inside its footprint ranges[g] (inclusive);
//  * per tile, Gaussians are composited front to back by float32 depth, ties by index;
//  * alpha = min(0.99, o * exp(max(-12, power))), ignored below 1/255;
//  * a pixel stops at the first Gaussian that would take T below 1e-4 (not composited);
//  * visible[g]: g composited at some pixel while T was still >= 0.5.
//
// Performance notes. The pixel loops must auto-vectorise; check with -fopt-info-vec (GCC):
//  * build with -fno-trapping-math, else GCC will not if-convert the loop bodies;
//  * no compound conditions, no early exits, float masks instead of branches; the
//    footprint test is computed inline (a precomputed mask array broke vectorisation);
//  * forward: one flat loop over the tile rows the footprint reaches (only integer
//    reductions); backward: rows x TS lanes, float sums kept per lane and reduced once
//    per Gaussian (float reductions do not vectorise without -ffast-math, which we avoid);
//  * the loops are bound by latency, not by arithmetic: a long loop body leaves few
//    iterations in the CPU's out-of-order window. So each Gaussian's pixels go through two
//    passes, the alphas (the exponential: long but independent chains) into a tile-sized
//    buffer, then the compositing (forward: -20-30 %, backward: -10 %), and exp_neg's
//    polynomial is evaluated by Estrin's scheme (3 dependent steps instead of 7: -10 %);
//  * exp() is exp_neg() (plain arithmetic) on the exponent clamped to >= -12;
//  * only the Gaussians with a footprint (a view sees a small part of a large map) are
//    binned and packed, one per cache line, once per view (the backward reuses the
//    forward's packing); backward gradients are written per (tile, Gaussian) pair in list
//    order and reduced per Gaussian afterwards (deterministic, no atomics).
// The backward recomputes the forward front to back with the same expressions (exact
// transmittance, no division chain, same decisions); the "everything behind" sums come
// from the forward outputs minus a running prefix, folded into one scalar per pixel (R).
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace splat_raster {

constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr float kTMin = 1e-4f;
constexpr float kPowerMin = -12.0f;
constexpr float kVisibleT = 0.5f;

// exp(x) for x in [-12, ~0]: Cody-Waite range reduction + degree-7 Taylor polynomial
// (relative error ~1e-7). Written without calls or branches so GCC vectorises it.
inline float exp_neg(float x) {
  const float t = x * 1.44269504088896341f;
  const float nf = (t + 12582912.0f) - 12582912.0f;  // round to nearest integer
  const float r = (x - nf * 0.693359375f) + nf * 2.12194440e-4f;
  // Estrin's scheme: the same degree-7 polynomial with a dependency chain of 3 steps
  // instead of Horner's 7 (the compositing loops are latency-bound)
  const float r2 = r * r, r4 = r2 * r2;
  const float a = 1.0f + r, b = 0.5f + r * (1.0f / 6.0f);
  const float c = 1.0f / 24.0f + r * (1.0f / 120.0f);
  const float d = 1.0f / 720.0f + r * (1.0f / 5040.0f);
  const float p = (a + r2 * b) + r4 * (c + r2 * d);
  const int32_t bits = (static_cast<int32_t>(nf) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(float));
  return p * scale;
}

struct GaussianTiles {
  int32_t tx0, tx1, ty0, ty1;
};

inline GaussianTiles tiles_of(const int32_t* r, int ts) {
  return {r[0] / ts, r[1] / ts, r[2] / ts, r[3] / ts};
}

inline bool has_footprint(const int32_t* r) { return r[0] <= r[1] && r[2] <= r[3]; }

// The Gaussians with a footprint, in index order. A view sees a small part of a large map:
// binning, packing and the gradient reduction touch only these ("slots"); keys hold the
// slot, which orders ties exactly as the Gaussian index would.
inline std::vector<int32_t> with_footprint(const int32_t* ranges, int64_t n) {
  std::vector<int32_t> ids;
  for (int64_t g = 0; g < n; ++g)
    if (has_footprint(ranges + 4 * g)) ids.push_back(int32_t(g));
  return ids;
}

// Slot-major pair offsets (nc + 1): a slot's (tile, Gaussian) pairs.
inline std::vector<int64_t> pair_offsets(const int32_t* ranges, const int32_t* ids, int64_t nc,
                                         int ts) {
  std::vector<int64_t> off(nc + 1, 0);
  for (int64_t s = 0; s < nc; ++s) {
    const GaussianTiles t = tiles_of(ranges + 4 * int64_t(ids[s]), ts);
    off[s + 1] = off[s] + int64_t(t.tx1 - t.tx0 + 1) * (t.ty1 - t.ty0 + 1);
  }
  return off;
}

inline int thread_id() {
#ifdef _OPENMP
  return omp_get_thread_num();
#else
  return 0;
#endif
}
inline int thread_count() {
#ifdef _OPENMP
  return omp_get_num_threads();
#else
  return 1;
#endif
}
inline int max_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}

// Per-tile lists of keys (float32 depth bits << 32 | slot), each sorted: the Gaussians of
// a tile front to back, ties by index. Parallel counting sort by tile (stable), then a
// sort inside each tile. pair_off: slot-major pair offsets (nc + 1).
inline void bin_gaussians(const int32_t* ranges, const float* depths, const int32_t* ids,
                          int64_t nc, int ts, int64_t tiles_x, int64_t tiles_y,
                          const int64_t* pair_off, int64_t* tile_off, int64_t* keys) {
  const int64_t n_tiles = tiles_x * tiles_y, m = pair_off[nc];
  std::vector<int32_t> pair_tile(m);
  std::vector<int64_t> pair_key(m);
#pragma omp parallel for schedule(static)
  for (int64_t s = 0; s < nc; ++s) {
    const int64_t g = ids[s];
    uint32_t dbits;
    std::memcpy(&dbits, depths + g, sizeof(float));  // depth > near > 0: bits are monotonic
    const int64_t key = (int64_t(dbits) << 32) | s;
    const GaussianTiles t = tiles_of(ranges + 4 * g, ts);
    int64_t p = pair_off[s];
    for (int32_t ty = t.ty0; ty <= t.ty1; ++ty)
      for (int32_t tx = t.tx0; tx <= t.tx1; ++tx, ++p) {
        pair_tile[p] = int32_t(ty * tiles_x + tx);
        pair_key[p] = key;
      }
  }
  const int max_t = max_threads();
  std::vector<int64_t> hist(size_t(max_t) * n_tiles, 0);  // [thread][tile]
#pragma omp parallel
  {
    const int t = thread_id(), nt = thread_count();
    const int64_t p0 = m * t / nt, p1 = m * (t + 1) / nt;
    int64_t* h = hist.data() + size_t(t) * n_tiles;
    for (int64_t p = p0; p < p1; ++p) ++h[pair_tile[p]];
#pragma omp barrier
#pragma omp single
    {
      int64_t off = 0;
      for (int64_t tile = 0; tile < n_tiles; ++tile) {
        tile_off[tile] = off;
        for (int u = 0; u < nt; ++u) {
          const int64_t c = hist[size_t(u) * n_tiles + tile];
          hist[size_t(u) * n_tiles + tile] = off;
          off += c;
        }
      }
      tile_off[n_tiles] = off;
    }
    for (int64_t p = p0; p < p1; ++p) keys[h[pair_tile[p]]++] = pair_key[p];
  }
#pragma omp parallel for schedule(dynamic, 8)
  for (int64_t i = 0; i < n_tiles; ++i) std::sort(keys + tile_off[i], keys + tile_off[i + 1]);
}

// One cache line per Gaussian: the per-tile lists visit Gaussians in depth order.
struct alignas(64) Packed {
  float mx, my, ca, cb, cc, op, c0, c1, c2, d;
  int32_t x0, x1, y0, y1;  // footprint (inclusive)
  int32_t pad[2];
};

// One Packed per slot (``out``: nc of them); the backward reuses the forward's.
inline void pack(const int32_t* ids, int64_t nc, const float* means2d, const float* conics,
                 const float* colors, const float* opac, const float* depths,
                 const int32_t* ranges, Packed* out) {
#pragma omp parallel for schedule(static)
  for (int64_t s = 0; s < nc; ++s) {
    const int64_t g = ids[s];
    Packed& p = out[s];
    p.mx = means2d[2 * g];
    p.my = means2d[2 * g + 1];
    p.ca = conics[3 * g];
    p.cb = conics[3 * g + 1];
    p.cc = conics[3 * g + 2];
    p.op = opac[g];
    p.c0 = colors[3 * g];
    p.c1 = colors[3 * g + 1];
    p.c2 = colors[3 * g + 2];
    p.d = depths[g];
    p.x0 = ranges[4 * g];
    p.x1 = ranges[4 * g + 1];
    p.y0 = ranges[4 * g + 2];
    p.y1 = ranges[4 * g + 3];
    p.pad[0] = p.pad[1] = 0;
  }
}

inline int64_t key_slot(int64_t key) { return key & 0xffffffffLL; }

// ------------------------------------------------------------------ forward
template <int TS>
void forward_tiles(int64_t width, int64_t height, int64_t tiles_x, int64_t n_tiles,
                   const int64_t* tile_off, const int64_t* keys, const Packed* gs,
                   const int32_t* ids, const float* bg, float* out_rgb, float* out_depth,
                   float* out_alpha, float* out_T, uint8_t* visible) {
  constexpr int P = TS * TS;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t tile = 0; tile < n_tiles; ++tile) {
    const int64_t tx0 = (tile % tiles_x) * TS, ty0 = (tile / tiles_x) * TS;
    const int tw = int(std::min<int64_t>(TS, width - tx0));
    const int th = int(std::min<int64_t>(TS, height - ty0));
    alignas(64) float T[P], C0[P], C1[P], C2[P], D[P], act[P];
    alignas(64) float PX[P], PY[P];
    for (int i = 0; i < P; ++i) {
      PX[i] = float(tx0 + i % TS);
      PY[i] = float(ty0 + i / TS);
      T[i] = 1.f;
      C0[i] = C1[i] = C2[i] = D[i] = 0.f;
      act[i] = ((i % TS) < tw && (i / TS) < th) ? 1.f : 0.f;
    }
    int n_active = tw * th;
    const int64_t k_end = tile_off[tile + 1];
    for (int64_t k = tile_off[tile]; k < k_end && n_active > 0; ++k) {
      const int64_t s = key_slot(keys[k]);
      if (k + 1 < k_end) __builtin_prefetch(gs + key_slot(keys[k + 1]));
      const Packed q = gs[s];
      const int ya = int(std::max<int64_t>(q.y0, ty0) - ty0);
      const int yb = int(std::min<int64_t>(q.y1, ty0 + TS - 1) - ty0);
      // one flat loop over the rows the footprint reaches (rows are contiguous)
      const float fx0 = float(q.x0), fx1 = float(q.x1);
      int n_stop = 0, vis = 0;
      // two passes over the rows: the alphas (the exponential: long dependency chains, but
      // independent pixels), then the compositing (short chains); split, more pixels are in
      // flight in the CPU's out-of-order window than in one long loop body
      alignas(64) float AL[P];
      for (int i = ya * TS; i < (yb + 1) * TS; ++i) {
        const float dx = PX[i] - q.mx, dy = PY[i] - q.my;
        float pw = -0.5f * (q.ca * dx * dx + q.cc * dy * dy) - (q.cb * dy) * dx;  // as in backward
        pw = pw < kPowerMin ? kPowerMin : pw;
        float al = q.op * exp_neg(pw);
        al = al > kAlphaMax ? kAlphaMax : al;
        const float inx = (PX[i] >= fx0) & (PX[i] <= fx1) ? 1.f : 0.f;
        AL[i] = (al >= kAlphaMin ? al : 0.f) * inx;
      }
      for (int i = ya * TS; i < (yb + 1) * TS; ++i) {
        const float al = AL[i] * act[i];
        const float Tb = T[i];
        const float Tn = Tb * (1.f - al);
        const int32_t stop = Tn < kTMin;
        const float keep = stop ? 0.f : 1.f;
        const float w = al * keep * Tb;
        T[i] = stop ? Tb : Tn;
        act[i] *= keep;
        C0[i] += w * q.c0;
        C1[i] += w * q.c1;
        C2[i] += w * q.c2;
        D[i] += w * q.d;
        n_stop += stop;
        vis |= (w > 0.f) & (Tb >= kVisibleT);
      }
      if (vis) __atomic_store_n(visible + ids[s], uint8_t(1), __ATOMIC_RELAXED);
      n_active -= n_stop;
    }
    for (int y = 0; y < th; ++y)
      for (int x = 0; x < tw; ++x) {
        const int i = y * TS + x;
        const int64_t o = (ty0 + y) * width + tx0 + x;
        out_rgb[3 * o] = C0[i] + T[i] * bg[0];
        out_rgb[3 * o + 1] = C1[i] + T[i] * bg[1];
        out_rgb[3 * o + 2] = C2[i] + T[i] * bg[2];
        out_depth[o] = D[i];
        out_alpha[o] = 1.f - T[i];
        out_T[o] = T[i];
      }
  }
}

// ------------------------------------------------------------------ backward
constexpr int kNumGrad = 10;  // mx, my, conic a, b, c, opacity, colour 0..2, depth

// d alpha_j:  dC/dalpha_j = T_j c_j - S_j / (1 - alpha_j), S_j = sum_{i>j} c_i w_i + T_N bg
//             dA/dalpha_j = T_N / (1 - alpha_j)           (A = 1 - T_N)
// With g = dL/d(rgb, depth, alpha) at the pixel and gc_j = g_rgb . c_j + g_D d_j:
//   dL/dalpha_j = T_j gc_j - R_j / (1 - alpha_j),
//   R_j = g_rgb . S_j + g_D S^D_j - g_A T_N = R_{j-1} - w_j gc_j,  R_{-1} = g . outputs - g_A T_N.
template <int TS>
void backward_tiles(int64_t width, int64_t height, int64_t tiles_x, int64_t n_tiles,
                    const int64_t* tile_off, const int64_t* keys, const Packed* gs, const float* out_rgb, const float* out_depth,
                    const float* out_T, const float* g_rgb, const float* g_depth,
                    const float* g_alpha, float* pair_grad) {
  constexpr int P = TS * TS;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t tile = 0; tile < n_tiles; ++tile) {
    const int64_t tile_tx = tile % tiles_x, tile_ty = tile / tiles_x;
    const int64_t tx0 = tile_tx * TS, ty0 = tile_ty * TS;
    const int tw = int(std::min<int64_t>(TS, width - tx0));
    const int th = int(std::min<int64_t>(TS, height - ty0));
    // T is set to 0 once a pixel stops (and for pixels outside the image): it then
    // takes no further part, which replaces the forward's "active" mask.
    alignas(64) float T[P], R[P], G0[P], G1[P], G2[P], GD[P], PX[P], PY[P];
    alignas(64) float acc[kNumGrad][TS];
    alignas(64) int32_t stop_l[TS];
    alignas(64) float AL[P], GE[P], LV[P];
    for (int i = 0; i < P; ++i) {
      const int x = i % TS, y = i / TS;
      PX[i] = float(tx0 + x);
      PY[i] = float(ty0 + y);
      if (x < tw && y < th) {
        const int64_t o = (ty0 + y) * width + tx0 + x;
        T[i] = 1.f;
        G0[i] = g_rgb[3 * o];
        G1[i] = g_rgb[3 * o + 1];
        G2[i] = g_rgb[3 * o + 2];
        GD[i] = g_depth[o];
        R[i] = G0[i] * out_rgb[3 * o] + G1[i] * out_rgb[3 * o + 1] +
               G2[i] * out_rgb[3 * o + 2] + GD[i] * out_depth[o] - g_alpha[o] * out_T[o];
      } else {
        T[i] = R[i] = G0[i] = G1[i] = G2[i] = GD[i] = 0.f;
      }
    }
    int n_active = tw * th;
    const int64_t k_end = tile_off[tile + 1];
    int64_t k = tile_off[tile];
    for (; k < k_end && n_active > 0; ++k) {
      const int64_t s = key_slot(keys[k]);
      if (k + 1 < k_end) __builtin_prefetch(gs + key_slot(keys[k + 1]));
      const Packed q = gs[s];
      const int ya = int(std::max<int64_t>(q.y0, ty0) - ty0);
      const int yb = int(std::min<int64_t>(q.y1, ty0 + TS - 1) - ty0);
      for (int j = 0; j < kNumGrad; ++j)
        for (int x = 0; x < TS; ++x) acc[j][x] = 0.f;
      for (int x = 0; x < TS; ++x) stop_l[x] = 0;
      const float fx0 = float(q.x0), fx1 = float(q.x1);
      // forward recomputation (same expressions as forward_tiles: identical alpha, identical
      // decisions), in its own pass like the forward's; m_live: d alpha / d raw before the
      // stop test (0 where not composited or clamped at kAlphaMax)
      for (int i = ya * TS; i < (yb + 1) * TS; ++i) {
        const float dx = PX[i] - q.mx, dy = PY[i] - q.my;
        float pw = -0.5f * (q.ca * dx * dx + q.cc * dy * dy) - (q.cb * dy) * dx;
        pw = pw < kPowerMin ? kPowerMin : pw;
        const float G = exp_neg(pw);
        const float raw = q.op * G;
        float al = raw > kAlphaMax ? kAlphaMax : raw;
        const float inx = (PX[i] >= fx0) & (PX[i] <= fx1) ? 1.f : 0.f;
        const float m = (al >= kAlphaMin ? 1.f : 0.f) * inx;
        AL[i] = al * m;
        GE[i] = G;
        LV[i] = m * (raw <= kAlphaMax ? 1.f : 0.f);
      }
      for (int y = ya; y <= yb; ++y) {
        const float* PXr = PX + y * TS;
        const float* PYr = PY + y * TS;
        float* Tr = T + y * TS;
        float* Rr = R + y * TS;
        const float* H0 = G0 + y * TS;
        const float* H1 = G1 + y * TS;
        const float* H2 = G2 + y * TS;
        const float* HD = GD + y * TS;
        const float* ALr = AL + y * TS;
        const float* GEr = GE + y * TS;
        const float* LVr = LV + y * TS;
        for (int x = 0; x < TS; ++x) {
          const float dx = PXr[x] - q.mx, dy = PYr[x] - q.my;
          const float al = ALr[x], G = GEr[x];
          const float Tb = Tr[x];
          const float Tn = Tb * (1.f - al);
          const int32_t stop = Tn < kTMin;
          const float keep = stop ? 0.f : 1.f;
          const float a = al * keep;  // composited alpha, 0 if not composited
          const float w = a * Tb;
          Tr[x] = stop ? 0.f : Tn;
          stop_l[x] += stop & (Tb > 0.f);
          // gradients
          const float gc = H0[x] * q.c0 + H1[x] * q.c1 + H2[x] * q.c2 + HD[x] * q.d;
          const float Rn = Rr[x] - w * gc;
          Rr[x] = Rn;
          const float live = LVr[x] * keep;  // d alpha / d raw
          const float dal = (Tb * gc - Rn / (1.f - a)) * live;
          const float gp = dal * q.op * G;  // dL/dpower
          const float gx = gp * dx, gy = gp * dy;
          acc[0][x] += gx;
          acc[1][x] += gy;
          acc[2][x] += gx * dx;
          acc[3][x] += gx * dy;
          acc[4][x] += gy * dy;
          acc[5][x] += dal * G;
          acc[6][x] += w * H0[x];
          acc[7][x] += w * H1[x];
          acc[8][x] += w * H2[x];
          acc[9][x] += w * HD[x];
        }
      }
      int n_stop = 0;
      for (int x = 0; x < TS; ++x) n_stop += stop_l[x];
      n_active -= n_stop;
      float sum[kNumGrad];
      for (int j = 0; j < kNumGrad; ++j) {
        float s = 0.f;
        for (int x = 0; x < TS; ++x) s += acc[j][x];
        sum[j] = s;
      }
      // sums of gp dx, gp dy, gp dx^2, gp dx dy, gp dy^2 -> d/d(mean, conic); power =
      // -0.5 (a dx^2 + c dy^2) - b dx dy, d power / d mean = (a dx + b dy, b dx + c dy)
      float* dst = pair_grad + kNumGrad * k;  // written in list order: sequential
      dst[0] = q.ca * sum[0] + q.cb * sum[1];
      dst[1] = q.cb * sum[0] + q.cc * sum[1];
      dst[2] = -0.5f * sum[2];
      dst[3] = -sum[3];
      dst[4] = -0.5f * sum[4];
      for (int j = 5; j < kNumGrad; ++j) dst[j] = sum[j];
    }
    // Gaussians behind the point where all pixels stopped
    for (int64_t j = kNumGrad * k; j < kNumGrad * k_end; ++j) pair_grad[j] = 0.f;
  }
}

// Deterministic reduction of the per-(tile, Gaussian) gradients into per-Gaussian ones
// (grads: n x kNumGrad, zero for Gaussians without a footprint): every thread owns a range
// of slots and scans the whole (tile-major) list, adding in list order.
inline void reduce_pairs(int64_t n, const int32_t* ids, int64_t nc, int64_t m,
                         const int64_t* keys, const float* pair_grad, float* grads) {
  std::vector<float> acc(size_t(nc) * kNumGrad, 0.f);
#pragma omp parallel
  {
    const int t = thread_id(), nt = thread_count();
    const int64_t s0 = nc * t / nt, s1 = nc * (t + 1) / nt;
    for (int64_t k = 0; k < m; ++k) {
      const int64_t s = key_slot(keys[k]);
      if (s < s0 || s >= s1) continue;
      for (int j = 0; j < kNumGrad; ++j) acc[kNumGrad * s + j] += pair_grad[kNumGrad * k + j];
    }
  }
  std::memset(grads, 0, sizeof(float) * size_t(n) * kNumGrad);
  for (int64_t s = 0; s < nc; ++s)
    std::memcpy(grads + kNumGrad * int64_t(ids[s]), acc.data() + kNumGrad * s,
                sizeof(float) * kNumGrad);
}

}  // namespace splat_raster
