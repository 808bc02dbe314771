// Explicit float lane vectors for the CPU kernels (GCC/Clang vector extensions: 8 lanes in
// AVX registers on x86-64, 4 in SSE/NEON registers elsewhere) and the few operations they
// need. Loops written on them vectorise whatever the compiler's auto-vectoriser makes of
// masks and reductions; the build turns FP contraction off (-ffp-contract=off), so a
// multiply-add is fused exactly where vfma says and rounds the same wherever it is inlined.
// No torch dependency.
#pragma once

#include <cstdint>
#include <cstring>

namespace splat_lanes {

#if defined(__AVX__)
constexpr int kLanes = 8;  // 256-bit registers
#else
constexpr int kLanes = 4;  // SSE, NEON
#endif
typedef float vf __attribute__((vector_size(4 * kLanes)));
typedef int32_t vi __attribute__((vector_size(4 * kLanes)));

inline vf vload(const float* p) { vf v; std::memcpy(&v, p, sizeof(vf)); return v; }
inline void vstore(float* p, vf v) { std::memcpy(p, &v, sizeof(vf)); }
inline vf vsplat(float s) { return vf{} + s; }
// a * b + c, fused where the CPU has FMA (the build turns off the compiler's own
// contraction, so the forward and the backward's recomputation round alike)
inline vf vfma(vf a, vf b, vf c) {
#if defined(__AVX__) && defined(__FMA__)
  return __builtin_ia32_vfmaddps256(a, b, c);
#else
  return a * b + c;
#endif
}
inline vf vsel(vi m, vf a, vf b) { return m ? a : b; }   // lane-wise m != 0 ? a : b
inline vf vabs(vf v) { return vsel(v < 0.f, -v, v); }
inline vf vsign(vf v) {   // -1, 0 or 1
  return vsel(v > 0.f, vsplat(1.f), vsel(v < 0.f, vsplat(-1.f), vf{}));
}
inline bool vany(vi m) {
#if defined(__AVX__)
  return __builtin_ia32_movmskps256(reinterpret_cast<vf>(m)) != 0;
#elif defined(__SSE__)
  return __builtin_ia32_movmskps(reinterpret_cast<vf>(m)) != 0;
#else
  int r = 0;
  for (int l = 0; l < kLanes; ++l) r |= m[l];
  return r != 0;
#endif
}
// Sum of the lanes, in a fixed order (pairwise).
inline float hsum(vf v) {
#if defined(__AVX__)
  return ((v[0] + v[4]) + (v[1] + v[5])) + ((v[2] + v[6]) + (v[3] + v[7]));
#else
  return (v[0] + v[2]) + (v[1] + v[3]);
#endif
}
inline int vsum(vi m) {
  int r = 0;
  for (int l = 0; l < kLanes; ++l) r += m[l];
  return r;
}

}  // namespace splat_lanes
