"""The rasterizer's autograd.Functions over the C++/OpenMP kernels (built by
:mod:`splat_slam_ros.native`), and its errors."""
from __future__ import annotations

import math

import torch

from splat_slam_ros import native


class RasterizerError(RuntimeError):
    """Base class of rasterizer errors (one-line, user-facing messages)."""


class RasterizerBuildError(RasterizerError, native.KernelBuildError):
    """The C++ kernel could not be compiled or loaded."""


def load_extension(verbose: bool = False):
    """The compiled module, built on first use. Raises RasterizerBuildError."""
    try:
        return native.load_extension(verbose)
    except native.KernelBuildError as e:
        raise RasterizerBuildError(str(e)) from None


def is_available() -> bool:
    try:
        load_extension()
        return True
    except RasterizerBuildError:
        return False


class RasterizeCpp(torch.autograd.Function):
    """Differentiable w.r.t. means2d, conics, colors, opacities, depths (float32, CPU)."""

    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, ranges, background, width,
                height, tile_size):
        ext = load_extension()
        rgb, depth, alpha, t_final, visible, tile_off, keys, packed, ids = ext.forward(
            means2d, conics, colors, opacities, depths, ranges, background, width, height,
            tile_size)
        ctx.save_for_backward(packed, ids, tile_off, keys, rgb, depth, t_final)
        ctx.size = (means2d.shape[0], width, height, tile_size)
        ctx.bg_needs_grad = background.requires_grad
        visible = visible.bool()
        ctx.mark_non_differentiable(visible)
        return rgb, depth, alpha, visible

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_alpha, _g_vis):
        packed, ids, tile_off, keys, rgb, depth, t_final = ctx.saved_tensors
        n, width, height, tile_size = ctx.size

        def img_grad(g, like):
            return torch.zeros_like(like) if g is None else g.contiguous().float()

        g_rgb, g_depth = img_grad(g_rgb, rgb), img_grad(g_depth, depth)
        g_alpha = img_grad(g_alpha, t_final)
        d_m2d, d_conic, d_col, d_op, d_depth = load_extension().backward(
            n, packed, ids, tile_off, keys, rgb, depth, t_final, g_rgb, g_depth, g_alpha,
            width, height, tile_size)
        d_bg = (g_rgb * t_final[..., None]).sum((0, 1)) if ctx.bg_needs_grad else None
        return d_m2d, d_conic, d_col, d_op, d_depth, None, d_bg, None, None, None


class ProjectCpp(torch.autograd.Function):
    """EWA projection (``projection.project_gaussians``, same rules) in C++: differentiable
    w.r.t. means, quats and scales (CPU, float32 or float64; viewmat without gradient)."""

    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, fx, fy, cx, cy, width, height, near,
                low_pass):
        means2d, conics, depths, ranges, radii, valid = load_extension().project_forward(
            means, quats, scales, viewmat, fx, fy, cx, cy, width, height, near, low_pass)
        ctx.save_for_backward(means, quats, scales, viewmat)
        ctx.cam = (fx, fy, cx, cy, width, height, near, low_pass)
        valid = valid.bool()
        ctx.mark_non_differentiable(ranges, radii, valid)
        return means2d, conics, depths, ranges, radii, valid

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_dep, _g_ranges, _g_radii, _g_valid):
        means, quats, scales, viewmat = ctx.saved_tensors

        def grad(g, n, k):
            return means.new_zeros((n, k) if k else (n,)) if g is None else g.contiguous()
        n = means.shape[0]
        d_means, d_quats, d_scales = load_extension().project_backward(
            means, quats, scales, viewmat, *ctx.cam, grad(g_m2d, n, 2), grad(g_con, n, 3),
            grad(g_dep, n, 0))
        return d_means, d_quats, d_scales, None, None, None, None, None, None, None, None, None


class ViewLossCpp(torch.autograd.Function):
    """Eq. 11's data terms of one view (``optimise.view_loss``, the reference: same
    expressions) in one C++ pass each way (CPU, float32): differentiable w.r.t. the render's
    rgb and depth, the keyframe's exposure (log a, b) and the vignetting (v1, v2).
    ``weight``: float32 depth-loss weights or the bool validity mask; ``r2``: the (h, w)
    r^2 map of the vignetting, or None without it."""

    @staticmethod
    def forward(ctx, rgb, depth, exposure, vignette, image, target_depth, weight, r2, lam):
        log_a, b = (float(x) for x in exposure.detach())
        v1, v2 = (float(x) for x in vignette.detach())
        r2 = rgb.new_empty(0) if r2 is None else r2
        args = (image, target_depth, weight, r2, v1, v2, math.exp(log_a), b, float(lam))
        rgb, depth = rgb.contiguous(), depth.contiguous()
        ctx.save_for_backward(rgb, depth)
        ctx.args = args
        return load_extension().view_loss_forward(rgb, depth, *args)

    @staticmethod
    def backward(ctx, g):
        rgb, depth = ctx.saved_tensors
        g_rgb, g_depth, d = load_extension().view_loss_backward(rgb, depth, *ctx.args,
                                                                float(g))
        d = d.to(rgb.dtype)
        return g_rgb, g_depth, d[:2], d[2:], None, None, None, None, None
