// Torch bindings of the project's CPU kernels: the rasterizer in raster_kernels.h (see there
// for the compositing rules and the performance notes; forward and backward take the
// projected Gaussians, float32, contiguous, CPU, and the footprints, int32), the projection,
// the fused view loss and the dense-BA edge terms (ba_kernels.h).
#include <torch/extension.h>

#include "ba_kernels.h"
#include "loss_kernels.h"
#include "project_kernels.h"
#include "raster_kernels.h"

namespace {
using namespace splat_raster;

// ------------------------------------------------------------------ bindings
void check_float32(const torch::Tensor& t) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == torch::kFloat32 && t.is_contiguous(),
              "float32 contiguous CPU tensors expected");
}

void check_inputs(const torch::Tensor& means2d, const torch::Tensor& conics,
                  const torch::Tensor& opac, const torch::Tensor& depths,
                  const torch::Tensor& ranges) {
  const int64_t n = means2d.size(0);
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be (N, 2)");
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == n && conics.size(1) == 3, "conics (N, 3)");
  TORCH_CHECK(opac.dim() == 1 && opac.size(0) == n, "opacities (N,)");
  TORCH_CHECK(depths.dim() == 1 && depths.size(0) == n, "depths (N,)");
  TORCH_CHECK(ranges.dim() == 2 && ranges.size(0) == n && ranges.size(1) == 4, "ranges (N, 4)");
  TORCH_CHECK(n < (int64_t(1) << 31), "too many Gaussians");
  for (const auto* t : {&means2d, &conics, &opac, &depths}) check_float32(*t);
  TORCH_CHECK(ranges.device().is_cpu() && ranges.scalar_type() == torch::kInt32 &&
                  ranges.is_contiguous(),
              "ranges must be int32 contiguous CPU");
}

// The packed Gaussians live in a uint8 tensor (torch's CPU allocations are 64-byte aligned,
// which the cache-line Packed needs).
Packed* packed_ptr(const torch::Tensor& packed) {
  auto* p = packed.data_ptr<uint8_t>();
  TORCH_CHECK(reinterpret_cast<uintptr_t>(p) % alignof(Packed) == 0,
              "packed Gaussians are not aligned");
  return reinterpret_cast<Packed*>(p);
}

#define DISPATCH_TILE(ts, ...)                                      \
  switch (ts) {                                                     \
    case 8: { constexpr int TS = 8; __VA_ARGS__; break; }           \
    case 16: { constexpr int TS = 16; __VA_ARGS__; break; }         \
    case 32: { constexpr int TS = 32; __VA_ARGS__; break; }         \
    default: TORCH_CHECK(false, "tile_size must be 8, 16 or 32");   \
  }

// The Gaussians with a footprint, binned by tile and packed (what the forward, the
// visible sets and the backward share).
struct Binned {
  int64_t tiles_x, n_tiles;
  torch::Tensor ids, tile_off, keys, packed;
};

Binned bin_and_pack(const torch::Tensor& means2d, const torch::Tensor& conics,
                    const float* colors, const torch::Tensor& opac,
                    const torch::Tensor& depths, const torch::Tensor& ranges, int64_t width,
                    int64_t height, int ts) {
  TORCH_CHECK(width > 0 && height > 0, "image size must be positive");
  const int64_t n = means2d.size(0);
  const int64_t tiles_x = (width + ts - 1) / ts, tiles_y = (height + ts - 1) / ts;
  const int64_t n_tiles = tiles_x * tiles_y;
  const int32_t* rg = ranges.data_ptr<int32_t>();
  const std::vector<int32_t> slots = with_footprint(rg, n);
  const int64_t nc = int64_t(slots.size());
  const int64_t m = pair_count(rg, slots.data(), nc, ts);
  auto i64 = torch::TensorOptions().dtype(torch::kInt64);
  Binned b{tiles_x, n_tiles,
           torch::from_blob(const_cast<int32_t*>(slots.data()), {nc},
                            torch::TensorOptions().dtype(torch::kInt32)).clone(),
           torch::empty({n_tiles + 1}, i64), torch::empty({m}, i64),
           torch::empty({nc, int64_t(sizeof(Packed))},
                        torch::TensorOptions().dtype(torch::kUInt8))};
  bin_gaussians(rg, depths.data_ptr<float>(), slots.data(), nc, ts, tiles_x, tiles_y,
                m, b.tile_off.data_ptr<int64_t>(), b.keys.data_ptr<int64_t>());
  pack(slots.data(), nc, means2d.data_ptr<float>(), conics.data_ptr<float>(), colors,
       opac.data_ptr<float>(), depths.data_ptr<float>(), rg, packed_ptr(b.packed));
  return b;
}

// Returns rgb (H,W,3), depth (H,W), alpha (H,W), T_final (H,W), visible (N,) uint8,
// tile_off (n_tiles+1,) int64, keys (M,) int64, and for the backward the packed Gaussians
// with a footprint (uint8, 64 bytes each) and their indices ids (int32).
std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor colors, torch::Tensor opac,
                                             torch::Tensor depths, torch::Tensor ranges,
                                             torch::Tensor bg, int64_t width, int64_t height,
                                             int64_t tile_size) {
  check_inputs(means2d, conics, opac, depths, ranges);
  TORCH_CHECK(colors.dim() == 2 && colors.size(0) == means2d.size(0) && colors.size(1) == 3,
              "colors (N, 3)");
  check_float32(colors);
  TORCH_CHECK(bg.numel() == 3 && bg.scalar_type() == torch::kFloat32 && bg.is_contiguous(),
              "background must be 3 float32");
  const int ts = int(tile_size);
  Binned b = bin_and_pack(means2d, conics, colors.data_ptr<float>(), opac, depths, ranges,
                          width, height, ts);
  auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  torch::Tensor rgb = torch::empty({height, width, 3}, f32);
  torch::Tensor depth = torch::empty({height, width}, f32);
  torch::Tensor alpha = torch::empty({height, width}, f32);
  torch::Tensor tfin = torch::empty({height, width}, f32);
  torch::Tensor visible =
      torch::zeros({means2d.size(0)}, torch::TensorOptions().dtype(torch::kUInt8));
  DISPATCH_TILE(ts, forward_tiles<TS>(
      width, height, b.tiles_x, b.n_tiles, b.tile_off.data_ptr<int64_t>(),
      b.keys.data_ptr<int64_t>(), packed_ptr(b.packed), b.ids.data_ptr<int32_t>(),
      bg.data_ptr<float>(), rgb.data_ptr<float>(), depth.data_ptr<float>(),
      alpha.data_ptr<float>(), tfin.data_ptr<float>(), visible.data_ptr<uint8_t>()));
  return {rgb, depth, alpha, tfin, visible, b.tile_off, b.keys, b.packed, b.ids};
}

// The forward's visible (N,) uint8 alone (visible_tiles: no colour, depth or alpha).
torch::Tensor rasterize_visible(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                torch::Tensor depths, torch::Tensor ranges, int64_t width,
                                int64_t height, int64_t tile_size) {
  check_inputs(means2d, conics, opac, depths, ranges);
  const int ts = int(tile_size);
  Binned b = bin_and_pack(means2d, conics, nullptr, opac, depths, ranges, width, height, ts);
  torch::Tensor visible =
      torch::zeros({means2d.size(0)}, torch::TensorOptions().dtype(torch::kUInt8));
  DISPATCH_TILE(ts, visible_tiles<TS>(
      width, height, b.tiles_x, b.n_tiles, b.tile_off.data_ptr<int64_t>(),
      b.keys.data_ptr<int64_t>(), packed_ptr(b.packed), b.ids.data_ptr<int32_t>(),
      visible.data_ptr<uint8_t>()));
  return visible;
}

// Returns grads w.r.t. means2d (N,2), conics (N,3), colors (N,3), opacities (N,), depths (N,)
// from the forward's packed Gaussians, ids, binning and outputs.
std::vector<torch::Tensor> rasterize_backward(
    int64_t n, torch::Tensor packed, torch::Tensor ids, torch::Tensor tile_off,
    torch::Tensor keys, torch::Tensor out_rgb, torch::Tensor out_depth, torch::Tensor out_T,
    torch::Tensor g_rgb, torch::Tensor g_depth, torch::Tensor g_alpha, int64_t width,
    int64_t height, int64_t tile_size) {
  for (const auto* t : {&out_rgb, &out_depth, &out_T, &g_rgb, &g_depth, &g_alpha}) {
    TORCH_CHECK(t->scalar_type() == torch::kFloat32 && t->is_contiguous(),
                "float32 contiguous image tensors expected");
  }
  TORCH_CHECK(out_rgb.numel() == width * height * 3 && g_rgb.numel() == width * height * 3 &&
                  out_depth.numel() == width * height && out_T.numel() == width * height &&
                  g_depth.numel() == width * height && g_alpha.numel() == width * height,
              "image tensors do not match the image size");
  const int64_t nc = ids.numel();
  TORCH_CHECK(ids.scalar_type() == torch::kInt32 && ids.is_contiguous() && nc <= n,
              "ids must be int32 contiguous, at most N");
  const int ts = int(tile_size);
  const int64_t tiles_x = (width + ts - 1) / ts, tiles_y = (height + ts - 1) / ts;
  const int64_t n_tiles = tiles_x * tiles_y;
  TORCH_CHECK(tile_off.numel() == n_tiles + 1, "tile offsets do not match the image size");
  TORCH_CHECK(keys.scalar_type() == torch::kInt64 && keys.is_contiguous() &&
                  tile_off.scalar_type() == torch::kInt64 && tile_off.is_contiguous() &&
                  tile_off.data_ptr<int64_t>()[n_tiles] == keys.numel(),
              "binning does not match");
  TORCH_CHECK(packed.scalar_type() == torch::kUInt8 && packed.is_contiguous() &&
                  packed.numel() == nc * int64_t(sizeof(Packed)),
              "packed Gaussians do not match ids");
  const int64_t m = keys.numel();
  auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  torch::Tensor pair_grad = torch::empty({m, kNumGrad}, f32);
  DISPATCH_TILE(ts, backward_tiles<TS>(
      width, height, tiles_x, n_tiles, tile_off.data_ptr<int64_t>(), keys.data_ptr<int64_t>(),
      packed_ptr(packed), out_rgb.data_ptr<float>(), out_depth.data_ptr<float>(),
      out_T.data_ptr<float>(), g_rgb.data_ptr<float>(), g_depth.data_ptr<float>(),
      g_alpha.data_ptr<float>(), pair_grad.data_ptr<float>()));
  torch::Tensor d_m2d = torch::empty({n, 2}, f32), d_conic = torch::empty({n, 3}, f32);
  torch::Tensor d_col = torch::empty({n, 3}, f32), d_op = torch::empty({n}, f32);
  torch::Tensor d_depth = torch::empty({n}, f32);
  reduce_pairs(n, ids.data_ptr<int32_t>(), nc, m, keys.data_ptr<int64_t>(),
               pair_grad.data_ptr<float>(),
               {d_m2d.data_ptr<float>(), d_conic.data_ptr<float>(), d_col.data_ptr<float>(),
                d_op.data_ptr<float>(), d_depth.data_ptr<float>()});
  return {d_m2d, d_conic, d_col, d_op, d_depth};
}

// ------------------------------------------------------------------ projection
void check_projection(const torch::Tensor& means, const torch::Tensor& quats,
                      const torch::Tensor& scales, const torch::Tensor& viewmat) {
  const int64_t n = means.size(0);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "means must be (N, 3)");
  TORCH_CHECK(quats.dim() == 2 && quats.size(0) == n && quats.size(1) == 4, "quats (N, 4)");
  TORCH_CHECK(scales.dim() == 2 && scales.size(0) == n && scales.size(1) == 3, "scales (N, 3)");
  TORCH_CHECK(viewmat.dim() == 2 && viewmat.size(0) == 4 && viewmat.size(1) == 4,
              "viewmat (4, 4)");
  for (const auto* t : {&means, &quats, &scales, &viewmat}) {
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == means.scalar_type() &&
                    t->is_contiguous(),
                "contiguous CPU tensors of one floating dtype expected");
  }
}

// Returns means2d (N,2), conics (N,3), depths (N,), ranges (N,4) int32, radii (N,) int32,
// valid (N,) uint8.
std::vector<torch::Tensor> project_fwd(torch::Tensor means, torch::Tensor quats,
                                       torch::Tensor scales, torch::Tensor viewmat, double fx,
                                       double fy, double cx, double cy, int64_t width,
                                       int64_t height, double near, double low_pass) {
  check_projection(means, quats, scales, viewmat);
  const int64_t n = means.size(0);
  auto opt = means.options();
  torch::Tensor means2d = torch::empty({n, 2}, opt), conics = torch::empty({n, 3}, opt);
  torch::Tensor depths = torch::empty({n}, opt);
  auto i32 = torch::TensorOptions().dtype(torch::kInt32);
  torch::Tensor ranges = torch::empty({n, 4}, i32), radii = torch::empty({n}, i32);
  torch::Tensor valid = torch::empty({n}, torch::TensorOptions().dtype(torch::kUInt8));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_fwd", [&] {
    const Camera<scalar_t> cam = make_camera<scalar_t>(viewmat.data_ptr<scalar_t>(), fx, fy,
                                                       cx, cy, width, height, near,
                                                       low_pass);
    project_forward<scalar_t>(n, cam, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                              scales.data_ptr<scalar_t>(), means2d.data_ptr<scalar_t>(),
                              conics.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
                              ranges.data_ptr<int32_t>(), radii.data_ptr<int32_t>(),
                              valid.data_ptr<uint8_t>());
  });
  return {means2d, conics, depths, ranges, radii, valid};
}

// Returns grads w.r.t. means (N,3), quats (N,4), scales (N,3).
std::vector<torch::Tensor> project_bwd(torch::Tensor means, torch::Tensor quats,
                                       torch::Tensor scales, torch::Tensor viewmat, double fx,
                                       double fy, double cx, double cy, int64_t width,
                                       int64_t height, double near, double low_pass,
                                       torch::Tensor g_m2d,
                                       torch::Tensor g_con, torch::Tensor g_dep) {
  check_projection(means, quats, scales, viewmat);
  const int64_t n = means.size(0);
  const int64_t per[3] = {2, 3, 1};  // means2d, conics, depths
  int i = 0;
  for (const auto* t : {&g_m2d, &g_con, &g_dep}) {
    TORCH_CHECK(t->scalar_type() == means.scalar_type() && t->is_contiguous() &&
                    t->dim() >= 1 && t->size(0) == n && t->numel() == n * per[i++],
                "projection gradients must match the projected outputs");
  }
  torch::Tensor d_means = torch::empty_like(means), d_quats = torch::empty_like(quats);
  torch::Tensor d_scales = torch::empty_like(scales);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_bwd", [&] {
    const Camera<scalar_t> cam = make_camera<scalar_t>(viewmat.data_ptr<scalar_t>(), fx, fy,
                                                       cx, cy, width, height, near,
                                                       low_pass);
    project_backward<scalar_t>(n, cam, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                               scales.data_ptr<scalar_t>(), g_m2d.data_ptr<scalar_t>(),
                               g_con.data_ptr<scalar_t>(), g_dep.data_ptr<scalar_t>(),
                               d_means.data_ptr<scalar_t>(), d_quats.data_ptr<scalar_t>(),
                               d_scales.data_ptr<scalar_t>());
  });
  return {d_means, d_quats, d_scales};
}

// ------------------------------------------------------------------ view loss
// The render (rgb, depth) and the keyframe's targets (image uint8 (h,w,3) with unit channel
// stride, depth float, weights float or bool, each (h,w) possibly strided), the r^2 map
// ((h,w) or empty: no vignetting) and the scalars as in loss_kernels.h.
splat_loss::ViewLossArgs view_loss_args(const torch::Tensor& rgb, const torch::Tensor& depth,
                                        const torch::Tensor& image, const torch::Tensor& tdepth,
                                        const torch::Tensor& weight, const torch::Tensor& r2,
                                        double v1, double v2, double a, double b, double lam) {
  TORCH_CHECK(rgb.dim() == 3 && rgb.size(2) == 3, "rgb must be (h, w, 3)");
  const int64_t h = rgb.size(0), w = rgb.size(1);
  TORCH_CHECK(rgb.scalar_type() == torch::kFloat32 && rgb.is_contiguous() &&
                  depth.scalar_type() == torch::kFloat32 && depth.is_contiguous() &&
                  depth.numel() == h * w,
              "rgb and depth must be contiguous float32 renders of one size");
  TORCH_CHECK(image.dim() == 3 && image.size(0) == h && image.size(1) == w &&
                  image.size(2) == 3 && image.stride(2) == 1 &&
                  image.scalar_type() == torch::kUInt8,
              "image must be uint8 (h, w, 3) with unit channel stride");
  for (const auto* t : {&tdepth, &weight}) {
    TORCH_CHECK(t->dim() == 2 && t->size(0) == h && t->size(1) == w, "targets must be (h, w)");
  }
  TORCH_CHECK(tdepth.scalar_type() == torch::kFloat32, "target depth must be float32");
  TORCH_CHECK(weight.scalar_type() == torch::kFloat32 || weight.scalar_type() == torch::kBool,
              "weights must be float32 or bool");
  const bool vig = r2.numel() > 0;
  TORCH_CHECK(!vig || (r2.scalar_type() == torch::kFloat32 && r2.is_contiguous() &&
                       r2.numel() == h * w),
              "r2 must be a contiguous float32 (h, w) map or empty");
  for (const auto* t : {&rgb, &depth, &image, &tdepth, &weight, &r2}) {
    TORCH_CHECK(t->device().is_cpu(), "view loss tensors must be on the CPU");
  }
  splat_loss::ViewLossArgs p;
  p.h = h;
  p.w = w;
  p.rgb = rgb.data_ptr<float>();
  p.depth = depth.data_ptr<float>();
  p.image = {image.data_ptr<uint8_t>(), image.stride(0), image.stride(1)};
  p.target_depth = {tdepth.data_ptr<float>(), tdepth.stride(0), tdepth.stride(1)};
  p.weight_is_mask = weight.scalar_type() == torch::kBool;
  p.weight = {p.weight_is_mask ? static_cast<const void*>(weight.data_ptr<bool>())
                               : static_cast<const void*>(weight.data_ptr<float>()),
              weight.stride(0), weight.stride(1)};
  p.r2 = vig ? r2.data_ptr<float>() : nullptr;
  p.v1 = float(v1);
  p.v2 = float(v2);
  p.a = float(a);
  p.b = float(b);
  p.lam = float(lam);
  return p;
}

torch::Tensor view_loss_fwd(torch::Tensor rgb, torch::Tensor depth, torch::Tensor image,
                            torch::Tensor tdepth, torch::Tensor weight, torch::Tensor r2,
                            double v1, double v2, double a, double b, double lam) {
  const auto p = view_loss_args(rgb, depth, image, tdepth, weight, r2, v1, v2, a, b, lam);
  return torch::full({}, splat_loss::view_loss_forward(p),
                     torch::TensorOptions().dtype(torch::kFloat32));
}

// Returns g_rgb (h,w,3), g_depth (h,w) and (d log a, d b, d v1, d v2) as float64 (4,).
std::vector<torch::Tensor> view_loss_bwd(torch::Tensor rgb, torch::Tensor depth,
                                         torch::Tensor image, torch::Tensor tdepth,
                                         torch::Tensor weight, torch::Tensor r2, double v1,
                                         double v2, double a, double b, double lam, double g) {
  const auto p = view_loss_args(rgb, depth, image, tdepth, weight, r2, v1, v2, a, b, lam);
  torch::Tensor g_rgb = torch::empty_like(rgb), g_depth = torch::empty_like(depth);
  const auto d = splat_loss::view_loss_backward(p, float(g), g_rgb.data_ptr<float>(),
                                                g_depth.data_ptr<float>());
  torch::Tensor params = torch::tensor({d.log_a, d.b, d.v1, d.v2},
                                       torch::TensorOptions().dtype(torch::kFloat64));
  return {g_rgb, g_depth, params};
}

}  // namespace

// ------------------------------------------------------------------ dense BA (Eq. 1)
// geometry (E, 33): per edge Rji, tji, Ri, ti, Rj (ba_kernels.h EdgeGeometry, float32);
// disps (E, P), target and weight (E, P, 2) float32. Returns H (E, 6, 6), v (E, 6),
// stats (E, 3: cost, weight sum, valid pixels) in float64 and a (E, P, 6), c, b (E, P).
std::vector<torch::Tensor> ba_edge_blocks(const torch::Tensor& geometry,
                                          const torch::Tensor& intr, const torch::Tensor& disps,
                                          const torch::Tensor& target,
                                          const torch::Tensor& weight, int64_t h, int64_t w,
                                          double huber) {
  for (const auto* t : {&geometry, &intr, &disps, &target, &weight}) check_float32(*t);
  const int64_t E = geometry.size(0), P = h * w;
  static_assert(sizeof(splat_ba::EdgeGeometry) == 33 * sizeof(float), "EdgeGeometry layout");
  TORCH_CHECK(geometry.dim() == 2 && geometry.size(1) == 33, "geometry must be (E, 33)");
  TORCH_CHECK(intr.numel() == 4, "intrinsics must be (fx, fy, cx, cy)");
  TORCH_CHECK(disps.numel() == E * P && target.numel() == E * P * 2 &&
                  weight.numel() == E * P * 2,
              "disparities (E, P), target and weight (E, P, 2) expected");
  auto f64 = torch::TensorOptions().dtype(torch::kFloat64);
  auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  auto H = torch::empty({E, 6, 6}, f64), v = torch::empty({E, 6}, f64);
  auto stats = torch::empty({E, 3}, f64);
  auto a = torch::empty({E, P, 6}, f32), c = torch::empty({E, P}, f32);
  auto b = torch::empty({E, P}, f32);
  const auto* geo = reinterpret_cast<const splat_ba::EdgeGeometry*>(geometry.data_ptr<float>());
  const float* K = intr.data_ptr<float>();
  const float *dp = disps.data_ptr<float>(), *tp = target.data_ptr<float>(),
              *wp = weight.data_ptr<float>();
  float *ap = a.data_ptr<float>(), *cp = c.data_ptr<float>(), *bp = b.data_ptr<float>();
  double *Hp = H.data_ptr<double>(), *vp = v.data_ptr<double>(), *sp = stats.data_ptr<double>();
#pragma omp parallel for schedule(dynamic, 1)
  for (int64_t e = 0; e < E; ++e)
    splat_ba::edge_blocks(geo[e], K, int(h), int(w), float(huber), dp + e * P,
                          tp + e * P * 2, wp + e * P * 2, ap + e * P * 6, cp + e * P,
                          bp + e * P, Hp + e * 36, vp + e * 6, sp + e * 3);
  return {H, v, a, c, b, stats};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "splat_slam_ros CPU kernels: Gaussian rasterizer (tile-based), dense-BA terms (OpenMP)";
  m.def("forward", &rasterize_forward, "rasterize forward");
  m.def("backward", &rasterize_backward, "rasterize backward");
  m.def("visible", &rasterize_visible, "the forward's visible flags alone");
  m.def("project_forward", &project_fwd, "EWA projection forward");
  m.def("project_backward", &project_bwd, "EWA projection backward");
  m.def("view_loss_forward", &view_loss_fwd, "Eq. 11 data terms of one view");
  m.def("view_loss_backward", &view_loss_bwd, "their gradients");
  m.def("ba_edge_blocks", &ba_edge_blocks, "dense BA per-edge blocks (Eq. 1)");
}
