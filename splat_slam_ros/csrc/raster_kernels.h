// Tile-based CPU rasterizer kernels for 3D Gaussian splatting (paper §3.2, "Rendering"):
// forward compositing of colour, depth and alpha, the covisibility flag of the
// supplementary, and a hand-written backward. No torch dependency (raster.cpp binds it);
// projection (EWA) is project_kernels.h.
//
// Rules (identical to reference.py, which is the ground truth):
//  * Gaussian g touches pixel (x, y) only inside its footprint ranges[g] (inclusive);
//  * per tile, Gaussians are composited front to back by float32 depth, ties by index;
//  * alpha = min(0.99, o * exp(max(-12, power))), ignored below 1/255;
//  * a pixel stops at the first Gaussian that would take T below 1e-4 (not composited);
//  * visible[g]: g composited at some pixel while T was still >= 0.5.
//
// Performance notes (measured on a 2-core x86-64 with AVX2: forward + backward of a
// 320x240 view of a 13k-Gaussian map, 19.6 ms before these rules, 12.9 ms with them):
//  * the pixel loops work on explicit lane vectors (lanes.h: 8 floats with AVX, else 4): a
//    tile row is TS / kLanes of them, and only the vectors a footprint reaches are visited;
//  * the build turns the compiler's FP contraction off (-ffp-contract=off) and the kernels
//    fuse multiply-adds explicitly (vfma): the backward's recomputation of the forward
//    then rounds exactly as the forward did, whatever the compiler inlines where;
//  * the loops are bound by latency, not by arithmetic: a long loop body leaves few
//    iterations in the CPU's out-of-order window. So each Gaussian's pixels go through two
//    passes, the alphas (the exponential: long but independent chains) into a tile-sized
//    buffer, then the compositing (forward -25 %, backward -25 %), and exp_neg's
//    polynomial is evaluated by Estrin's scheme (3 dependent steps instead of 7);
//  * the backward keeps its 10 per-Gaussian sums in lane vectors (registers) and adds the
//    lanes once per (tile, Gaussian) pair (-25 % against per-column sums in memory), and
//    skips lane vectors whose alphas are all below 1/255 (they change nothing);
//  * exp() is exp_neg() (plain arithmetic) on the exponent clamped to >= -12;
//  * only the Gaussians with a footprint (a view sees a small part of a large map) are
//    binned and packed, one per cache line, once per view (the backward reuses the
//    forward's packing); the binning radix-sorts them by depth once and counting-sorts
//    their pairs by tile, so no list needs sorting (-40 % against a sort per tile);
//    backward gradients are written per (tile, Gaussian) pair in list order and reduced
//    per Gaussian afterwards (deterministic, no atomics; written at slot-major positions
//    instead, the scattered writes cost the backward more than the reduction saved).
// Tried and not kept: each row's lane vectors bounded by the Gaussian's alpha >= 1/255
// ellipse instead of its footprint (6 % fewer vectors, slower: scalar work per row); the
// forward skipping all-zero vectors (88 % of the visited vectors have a live alpha).
// The backward recomputes the forward front to back with the same expressions (exact
// transmittance, no division chain, same decisions); the "everything behind" sums come
// from the forward outputs minus a running prefix, folded into one scalar per pixel (R).
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

#include "lanes.h"

#ifdef _OPENMP
#include <omp.h>
#endif

namespace splat_raster {

constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr float kTMin = 1e-4f;
constexpr float kPowerMin = -12.0f;
constexpr float kVisibleT = 0.5f;

inline int64_t key_slot(int64_t key) { return key & 0xffffffffLL; }

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

// The number of (tile, Gaussian) pairs of the nc slots: the binned lists' total length.
inline int64_t pair_count(const int32_t* ranges, const int32_t* ids, int64_t nc, int ts) {
  int64_t m = 0;
  for (int64_t s = 0; s < nc; ++s) {
    const GaussianTiles t = tiles_of(ranges + 4 * int64_t(ids[s]), ts);
    m += int64_t(t.tx1 - t.tx0 + 1) * (t.ty1 - t.ty0 + 1);
  }
  return m;
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

// The keys (float32 depth bits << 32 | slot) of the nc slots, sorted: front to back, ties
// by index (an LSD radix sort of the depth bits, stable over the slots' index order).
inline std::vector<int64_t> depth_order(const float* depths, const int32_t* ids, int64_t nc) {
  std::vector<int64_t> a(nc), b(nc);
  for (int64_t s = 0; s < nc; ++s) {
    uint32_t dbits;
    std::memcpy(&dbits, depths + ids[s], sizeof(float));  // depth > near > 0: bits monotonic
    a[s] = (int64_t(dbits) << 32) | s;
  }
  for (int shift = 32; shift < 64; shift += 8) {
    int64_t count[257] = {0};
    for (int64_t s = 0; s < nc; ++s) ++count[((a[s] >> shift) & 0xff) + 1];
    if (count[((a[0] >> shift) & 0xff) + 1] == nc) continue;  // one value: nothing to move
    for (int v = 0; v < 256; ++v) count[v + 1] += count[v];
    for (int64_t s = 0; s < nc; ++s) b[count[(a[s] >> shift) & 0xff]++] = a[s];
    a.swap(b);
  }
  return a;
}

// Per-tile lists of keys (float32 depth bits << 32 | slot), each sorted: the Gaussians of
// a tile front to back, ties by index. The slots in depth order (depth_order), then a
// stable counting sort of their (tile, Gaussian) pairs by tile: the lists come out sorted.
// m: pair_count, the lists' total length.
inline void bin_gaussians(const int32_t* ranges, const float* depths, const int32_t* ids,
                          int64_t nc, int ts, int64_t tiles_x, int64_t tiles_y,
                          int64_t m, int64_t* tile_off, int64_t* keys) {
  const int64_t n_tiles = tiles_x * tiles_y;
  tile_off[n_tiles] = m;
  if (nc == 0) {
    for (int64_t tile = 0; tile < n_tiles; ++tile) tile_off[tile] = 0;
    return;
  }
  const std::vector<int64_t> order = depth_order(depths, ids, nc);
  const int max_t = max_threads();
  std::vector<int64_t> hist(size_t(max_t) * n_tiles, 0);  // [thread][tile]
#pragma omp parallel
  {
    const int t = thread_id(), nt = thread_count();
    const int64_t j0 = nc * t / nt, j1 = nc * (t + 1) / nt;  // a stretch of the depth order
    int64_t* h = hist.data() + size_t(t) * n_tiles;
    for (int64_t j = j0; j < j1; ++j) {
      const GaussianTiles g = tiles_of(ranges + 4 * int64_t(ids[key_slot(order[j])]), ts);
      for (int32_t ty = g.ty0; ty <= g.ty1; ++ty)
        for (int32_t tx = g.tx0; tx <= g.tx1; ++tx) ++h[ty * tiles_x + tx];
    }
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
    }
    for (int64_t j = j0; j < j1; ++j) {
      const int64_t key = order[j];
      const GaussianTiles g = tiles_of(ranges + 4 * int64_t(ids[key_slot(key)]), ts);
      for (int32_t ty = g.ty0; ty <= g.ty1; ++ty)
        for (int32_t tx = g.tx0; tx <= g.tx1; ++tx) keys[h[ty * tiles_x + tx]++] = key;
    }
  }
}

// One cache line per Gaussian: the per-tile lists visit Gaussians in depth order.
struct alignas(64) Packed {
  float mx, my, ca, cb, cc, op, c0, c1, c2, d;
  int32_t x0, x1, y0, y1;  // footprint (inclusive)
  int32_t pad[2];
};

// One Packed per slot (``out``: nc of them); the backward reuses the forward's. ``colors``
// may be null (visible_tiles reads none).
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
    p.c0 = colors ? colors[3 * g] : 0.f;  // no colours: visible sets only
    p.c1 = colors ? colors[3 * g + 1] : 0.f;
    p.c2 = colors ? colors[3 * g + 2] : 0.f;
    p.d = depths[g];
    p.x0 = ranges[4 * g];
    p.x1 = ranges[4 * g + 1];
    p.y0 = ranges[4 * g + 2];
    p.y1 = ranges[4 * g + 3];
    p.pad[0] = p.pad[1] = 0;
  }
}


// ------------------------------------------------------------------ lane vectors
// The pixel loops work on lane vectors (lanes.h). A vector whose alphas are all 0 (below
// 1/255 or outside the footprint) changes nothing: the same expressions give back T, R and
// the sums unchanged.
using namespace splat_lanes;

// exp(x) for x in [-12, ~0], lane-wise: Cody-Waite range reduction + degree-7 Taylor
// polynomial (relative error ~1e-7), plain arithmetic.
inline vf exp_neg(vf x) {
  // nf: x / ln 2 rounded to the nearest integer; r = x - nf ln 2 in two parts (the first
  // product is exact)
  const vf nf = vfma(x, vsplat(1.44269504088896341f), vsplat(12582912.0f)) - 12582912.0f;
  const vf r = vfma(nf, vsplat(2.12194440e-4f), vfma(nf, vsplat(-0.693359375f), x));
  // Estrin's scheme: the same degree-7 polynomial with a dependency chain of 3 steps
  // instead of Horner's 7 (the compositing loops are latency-bound)
  const vf r2 = r * r, r4 = r2 * r2;
  const vf a = 1.0f + r, b = vfma(r, vsplat(1.0f / 6.0f), vsplat(0.5f));
  const vf c = vfma(r, vsplat(1.0f / 120.0f), vsplat(1.0f / 24.0f));
  const vf d = vfma(r, vsplat(1.0f / 5040.0f), vsplat(1.0f / 720.0f));
  const vf p = vfma(r4, vfma(r2, d, c), vfma(r2, b, a));
  const vi bits = (__builtin_convertvector(nf, vi) + 127) << 23;
  return p * reinterpret_cast<vf>(bits);
}

// The alphas of Gaussian q at the pixels (x, y) of one lane vector (x: the lanes' columns),
// before the stop test (0 outside the footprint or below 1/255); raw: opacity x the
// Gaussian; G: the Gaussian.
struct Alphas {
  vf al, raw, G;
};
inline Alphas alphas(const Packed& q, vf x, float y) {
  const float dy = y - q.my;
  const vf dx = x - q.mx;
  // power = -0.5 (a dx^2 + c dy^2) - b dx dy
  vf pw = vfma(vsplat(-q.cb * dy), dx, -0.5f * vfma(q.ca * dx, dx, vsplat(q.cc * dy * dy)));
  pw = vsel(pw < kPowerMin, vsplat(kPowerMin), pw);
  const vf G = exp_neg(pw);
  const vf raw = q.op * G;
  const vf al = vsel(raw > kAlphaMax, vsplat(kAlphaMax), raw);
  const vi inx = (x >= float(q.x0)) & (x <= float(q.x1)) & (al >= kAlphaMin);
  return {vsel(inx, al, vf{}), raw, G};
}

// Tile ``tile`` of a width x height image: its first pixel (tx0, ty0), its size inside the
// image (tw x th: the right and bottom tiles may be partial) and its lanes' pixel columns.
template <int TS>
struct TileSpan {
  int64_t tx0, ty0;
  int tw, th;
  vf X[TS / kLanes];
  TileSpan(int64_t tile, int64_t tiles_x, int64_t width, int64_t height)
      : tx0((tile % tiles_x) * TS), ty0((tile / tiles_x) * TS),
        tw(int(std::min<int64_t>(TS, width - tx0))), th(int(std::min<int64_t>(TS, height - ty0))) {
    for (int h = 0; h < TS / kLanes; ++h)
      for (int l = 0; l < kLanes; ++l) X[h][l] = float(tx0 + h * kLanes + l);
  }
  bool inside(int i) const { return (i % TS) < tw && (i / TS) < th; }
};

// The rows [ya, yb] and lane vectors [h0, h1] of a tile (first pixel tx0, ty0) that
// Gaussian q's footprint reaches.
struct Reach {
  int ya, yb, h0, h1;
};
template <int TS>
inline Reach reach(const Packed& q, int64_t tx0, int64_t ty0) {
  const int xa = int(std::max<int64_t>(q.x0, tx0) - tx0);
  const int xb = int(std::min<int64_t>(q.x1, tx0 + TS - 1) - tx0);
  return {int(std::max<int64_t>(q.y0, ty0) - ty0), int(std::min<int64_t>(q.y1, ty0 + TS - 1) - ty0),
          xa / kLanes, xb / kLanes};
}

// ------------------------------------------------------------------ forward
template <int TS>
void forward_tiles(int64_t width, int64_t height, int64_t tiles_x, int64_t n_tiles,
                   const int64_t* tile_off, const int64_t* keys, const Packed* gs,
                   const int32_t* ids, const float* bg, float* out_rgb, float* out_depth,
                   float* out_alpha, float* out_T, uint8_t* visible) {
  static_assert(TS % kLanes == 0, "tile rows are whole lane vectors");
  constexpr int P = TS * TS;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t tile = 0; tile < n_tiles; ++tile) {
    const TileSpan<TS> sp(tile, tiles_x, width, height);
    const int64_t tx0 = sp.tx0, ty0 = sp.ty0;
    const int tw = sp.tw, th = sp.th;
    const vf* X = sp.X;  // the lanes' pixel columns
    alignas(64) float T[P], C0[P], C1[P], C2[P], D[P], act[P];
    for (int i = 0; i < P; ++i) {
      T[i] = 1.f;
      C0[i] = C1[i] = C2[i] = D[i] = 0.f;
      act[i] = sp.inside(i) ? 1.f : 0.f;
    }
    int n_active = tw * th;
    const int64_t k_end = tile_off[tile + 1];
    for (int64_t k = tile_off[tile]; k < k_end && n_active > 0; ++k) {
      const int64_t s = key_slot(keys[k]);
      if (k + 1 < k_end) __builtin_prefetch(gs + key_slot(keys[k + 1]));
      const Packed q = gs[s];
      const auto [ya, yb, h0, h1] = reach<TS>(q, tx0, ty0);
      vi n_stop = {}, vis = {};
      // two passes: the alphas, then the compositing (see the performance notes)
      alignas(64) float AL[P];
      for (int y = ya; y <= yb; ++y) {
        const float py = float(ty0 + y);
        for (int h = h0; h <= h1; ++h) vstore(AL + y * TS + h * kLanes, alphas(q, X[h], py).al);
      }
      for (int y = ya; y <= yb; ++y) {
        for (int h = h0; h <= h1; ++h) {
          const int i = y * TS + h * kLanes;
          const vf al0 = vload(AL + i);
          const vf ac = vload(act + i);
          const vf al = al0 * ac;
          const vf Tb = vload(T + i);
          const vf Tn = Tb * (1.f - al);
          const vi stop = Tn < kTMin;
          const vf keep = vsel(stop, vf{}, vsplat(1.f));
          const vf w = al * keep * Tb;
          vstore(T + i, vsel(stop, Tb, Tn));
          vstore(act + i, ac * keep);
          vstore(C0 + i, vfma(w, vsplat(q.c0), vload(C0 + i)));
          vstore(C1 + i, vfma(w, vsplat(q.c1), vload(C1 + i)));
          vstore(C2 + i, vfma(w, vsplat(q.c2), vload(C2 + i)));
          vstore(D + i, vfma(w, vsplat(q.d), vload(D + i)));
          n_stop -= stop;  // stop lanes are -1
          vis |= (w > 0.f) & (Tb >= kVisibleT);
        }
      }
      if (vany(vis)) __atomic_store_n(visible + ids[s], uint8_t(1), __ATOMIC_RELAXED);
      n_active -= vsum(n_stop);
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

// ------------------------------------------------------------------ visible sets
// forward_tiles' ``visible`` alone: a pixel leaves once T < kVisibleT, where the forward
// has nothing more to flag (while T >= 0.5 no alpha <= 0.99 can take it below kTMin, so
// the forward composites every Gaussian there; T is updated by the same expression), so
// the flags are the forward's to the bit without compositing the pixels' back layers.
template <int TS>
void visible_tiles(int64_t width, int64_t height, int64_t tiles_x, int64_t n_tiles,
                   const int64_t* tile_off, const int64_t* keys, const Packed* gs,
                   const int32_t* ids, uint8_t* visible) {
  static_assert(TS % kLanes == 0, "tile rows are whole lane vectors");
  constexpr int P = TS * TS;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t tile = 0; tile < n_tiles; ++tile) {
    const TileSpan<TS> sp(tile, tiles_x, width, height);
    alignas(64) float T[P], act[P];
    for (int i = 0; i < P; ++i) {
      T[i] = 1.f;
      act[i] = sp.inside(i) ? 1.f : 0.f;
    }
    int n_active = sp.tw * sp.th;
    const int64_t k_end = tile_off[tile + 1];
    for (int64_t k = tile_off[tile]; k < k_end && n_active > 0; ++k) {
      const int64_t s = key_slot(keys[k]);
      if (k + 1 < k_end) __builtin_prefetch(gs + key_slot(keys[k + 1]));
      const Packed q = gs[s];
      const auto [ya, yb, h0, h1] = reach<TS>(q, sp.tx0, sp.ty0);
      vi n_left = {}, vis = {};
      // one pass (unlike the forward's two): most lane vectors here have left already,
      // and those skip the exponential
      for (int y = ya; y <= yb; ++y) {
        const float py = float(sp.ty0 + y);
        for (int h = h0; h <= h1; ++h) {
          const int i = y * TS + h * kLanes;
          const vf ac = vload(act + i);
          if (!vany(ac > 0.f)) continue;
          const vf al = alphas(q, sp.X[h], py).al * ac;
          const vf Tn = vload(T + i) * (1.f - al);
          const vi left = (ac > 0.f) & (Tn < kVisibleT);
          vis |= al > 0.f;
          vstore(T + i, Tn);
          vstore(act + i, vsel(left, vf{}, ac));
          n_left -= left;  // left lanes are -1
        }
      }
      if (vany(vis)) __atomic_store_n(visible + ids[s], uint8_t(1), __ATOMIC_RELAXED);
      n_active -= vsum(n_left);
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
  static_assert(TS % kLanes == 0, "tile rows are whole lane vectors");
  constexpr int P = TS * TS;
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t tile = 0; tile < n_tiles; ++tile) {
    const TileSpan<TS> sp(tile, tiles_x, width, height);
    const int64_t tx0 = sp.tx0, ty0 = sp.ty0;
    const int tw = sp.tw, th = sp.th;
    const vf* X = sp.X;
    // T is set to 0 once a pixel stops (and for pixels outside the image): it then
    // takes no further part, which replaces the forward's "active" mask.
    alignas(64) float T[P], R[P], G0[P], G1[P], G2[P], GD[P];
    alignas(64) float AL[P], GE[P], LV[P];
    for (int i = 0; i < P; ++i) {
      const int x = i % TS, y = i / TS;
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
      const auto [ya, yb, h0, h1] = reach<TS>(q, tx0, ty0);
      vi n_stop = {};
      // per-lane sums over the footprint's rows and lane vectors
      vf a0 = {}, a1 = {}, a2 = {}, a3 = {}, a4 = {}, a5 = {}, a6 = {}, a7 = {}, a8 = {},
         a9 = {};
      // forward recomputation (the forward's expressions: identical alpha, identical
      // decisions) in its own pass, as in the forward; LV: d alpha / d raw before the stop
      // test (0 where not composited or clamped)
      for (int h = h0; h <= h1; ++h)
        for (int y = ya; y <= yb; ++y) {
          const int i = y * TS + h * kLanes;
          const Alphas A = alphas(q, X[h], float(ty0 + y));
          vstore(AL + i, A.al);
          vstore(GE + i, A.G);
          vstore(LV + i, vsel((A.al > 0.f) & (A.raw <= kAlphaMax), vsplat(1.f), vf{}));
        }
      for (int h = h0; h <= h1; ++h) {
        const vf dx = X[h] - q.mx;
        for (int y = ya; y <= yb; ++y) {
          const int i = y * TS + h * kLanes;
          const vf al = vload(AL + i);
          if (!vany(al > 0.f)) continue;
          const vf G = vload(GE + i), lv = vload(LV + i);
          const vf Tb = vload(T + i);
          const vf Tn = Tb * (1.f - al);
          const vi stop = Tn < kTMin;
          const vf keep = vsel(stop, vf{}, vsplat(1.f));
          const vf a = al * keep;  // composited alpha, 0 if not composited
          const vf w = a * Tb;
          vstore(T + i, vsel(stop, vf{}, Tn));
          n_stop -= stop & (Tb > 0.f);
          // gradients
          const vf H0 = vload(G0 + i), H1 = vload(G1 + i), H2 = vload(G2 + i),
                   HD = vload(GD + i);
          const vf gc = vfma(HD, vsplat(q.d),
                             vfma(H2, vsplat(q.c2), vfma(H1, vsplat(q.c1), H0 * q.c0)));
          const vf Rn = vfma(-w, gc, vload(R + i));
          vstore(R + i, Rn);
          const vf live = lv * keep;  // d alpha / d raw
          const vf dal = vfma(Tb, gc, -(Rn / (1.f - a))) * live;
          const vf gp = dal * q.op * G;  // dL/dpower
          const float dy = float(ty0 + y) - q.my;
          const vf gx = gp * dx, gy = gp * dy;
          a0 += gx;
          a1 += gy;
          a2 = vfma(gx, dx, a2);
          a3 = vfma(gx, vsplat(dy), a3);
          a4 = vfma(gy, vsplat(dy), a4);
          a5 = vfma(dal, G, a5);
          a6 = vfma(w, H0, a6);
          a7 = vfma(w, H1, a7);
          a8 = vfma(w, H2, a8);
          a9 = vfma(w, HD, a9);
        }
      }
      n_active -= vsum(n_stop);
      float sum[kNumGrad] = {hsum(a0), hsum(a1), hsum(a2), hsum(a3), hsum(a4),
                             hsum(a5), hsum(a6), hsum(a7), hsum(a8), hsum(a9)};
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

// Deterministic reduction of the per-(tile, Gaussian) gradients into per-Gaussian ones, zero
// for Gaussians without a footprint: every thread owns a range of slots and scans the whole
// (tile-major) list, adding in list order. Written as the autograd outputs (contiguous, no
// copies later): d_m2d (n x 2), d_conic (n x 3), d_col (n x 3), d_op (n), d_depth (n).
struct PerGaussianGrads {
  float *m2d, *conic, *col, *op, *depth;
};
inline void reduce_pairs(int64_t n, const int32_t* ids, int64_t nc, int64_t m,
                         const int64_t* keys, const float* pair_grad, PerGaussianGrads out) {
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
  std::memset(out.m2d, 0, sizeof(float) * size_t(n) * 2);
  std::memset(out.conic, 0, sizeof(float) * size_t(n) * 3);
  std::memset(out.col, 0, sizeof(float) * size_t(n) * 3);
  std::memset(out.op, 0, sizeof(float) * size_t(n));
  std::memset(out.depth, 0, sizeof(float) * size_t(n));
  for (int64_t s = 0; s < nc; ++s) {   // the pair layout: mx, my, conic a b c, o, colour, depth
    const float* a = acc.data() + kNumGrad * s;
    const int64_t g = ids[s];
    std::memcpy(out.m2d + 2 * g, a, sizeof(float) * 2);
    std::memcpy(out.conic + 3 * g, a + 2, sizeof(float) * 3);
    out.op[g] = a[5];
    std::memcpy(out.col + 3 * g, a + 6, sizeof(float) * 3);
    out.depth[g] = a[9];
  }
}

}  // namespace splat_raster
