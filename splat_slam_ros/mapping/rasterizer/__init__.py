"""Differentiable 3D Gaussian rasterizer (paper §3.2, "Rendering").

Three layers, as in gsplat: this functional API; autograd wrappers (``kernel.RasterizeCpp``,
``kernel.ProjectCpp``; the torch path uses plain autograd); kernels (``csrc/``, with
``reference.py`` and ``projection.py`` as their pure-torch ground truth). The C++ backend
projects in C++ too, unless ``viewmat`` needs a gradient (the torch projection gives that).

Backends: ``"cpp"`` (CPU, tile-based C++/OpenMP kernel, hand-written backward), ``"torch"``
(pure torch, any device, slow), ``"gsplat"`` (CUDA, needs ``pip install gsplat``), ``"auto"``.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import torch

from splat_slam_ros.mapping.rasterizer.kernel import (ProjectCpp, RasterizerBuildError, RasterizerError,
                                                     RasterizeCpp, load_extension)
from splat_slam_ros.mapping.rasterizer.projection import Projected, project_gaussians
from splat_slam_ros.mapping.rasterizer.reference import rasterize_reference

__all__ = ["rasterize", "RasterOutput", "RasterizerError", "RasterizerBuildError",
           "RasterizerInputError", "project_gaussians", "available_backends"]

BACKENDS = ("auto", "cpp", "torch", "gsplat")
_warned_fallback = False


class RasterizerInputError(RasterizerError, ValueError):
    """Bad arguments to :func:`rasterize` (shapes, backend name, device)."""


@dataclass
class RasterOutput:
    rgb: torch.Tensor        # (H, W, 3)
    depth: torch.Tensor      # (H, W) alpha-blended camera z of the Gaussian centres
    alpha: torch.Tensor      # (H, W) accumulated opacity 1 - T_N
    visible: torch.Tensor    # (N,) bool: composited while T >= 0.5 (covisibility)
    radii: torch.Tensor      # (N,) int32 3-sigma radius in px, 0 if culled
    means2d: Optional[torch.Tensor] = None  # (N, 2) projected centres (call .retain_grad())


def _gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
        return True
    except Exception:
        return False


def available_backends() -> list[str]:
    out = ["torch"]
    try:
        load_extension()
        out.insert(0, "cpp")
    except RasterizerBuildError:
        pass
    if torch.cuda.is_available() and _gsplat_available():
        out.append("gsplat")
    return out


def _resolve_backend(backend: str, device: torch.device) -> str:
    global _warned_fallback
    if backend not in BACKENDS:
        raise RasterizerInputError(f"unknown rasterizer backend '{backend}' (use one of {BACKENDS})")
    if backend != "auto":
        return backend
    if device.type == "cuda" and _gsplat_available():
        return "gsplat"
    if device.type != "cpu":
        return "torch"
    try:
        load_extension()
        return "cpp"
    except RasterizerBuildError as e:
        if not _warned_fallback:
            warnings.warn(f"{e}; falling back to the slow pure-torch rasterizer", RuntimeWarning,
                          stacklevel=3)
            _warned_fallback = True
        return "torch"


def _check(means, quats, scales, opacities, colors, viewmat, width, height, near, tile_size):
    n = means.shape[0] if means.dim() == 2 else -1
    for name, t, shape in (("means", means, (n, 3)), ("quats", quats, (n, 4)),
                           ("scales", scales, (n, 3)), ("opacities", opacities, (n,)),
                           ("colors", colors, (n, 3)), ("viewmat", viewmat, (4, 4))):
        if not torch.is_tensor(t) or tuple(t.shape) != shape or n < 0:
            got = tuple(t.shape) if torch.is_tensor(t) else type(t).__name__
            raise RasterizerInputError(f"rasterize: {name} must have shape {shape}, got {got}")
    if not (int(width) > 0 and int(height) > 0):
        raise RasterizerInputError(f"rasterize: image size must be positive, got {width}x{height}")
    if not near > 0:
        raise RasterizerInputError(f"rasterize: near must be > 0, got {near}")
    if tile_size not in (8, 16, 32):
        raise RasterizerInputError(f"rasterize: tile_size must be 8, 16 or 32, got {tile_size}")


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
              opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor,
              intrinsics: Union[Sequence[float], torch.Tensor], width: int, height: int,
              backend: str = "auto", near: float = 0.01,
              background: Optional[Union[Sequence[float], torch.Tensor]] = None,
              tile_size: int = 16) -> RasterOutput:
    """Render N Gaussians (world frame) from world-to-camera ``viewmat``.

    ``quats`` are (x, y, z, w) (normalised here), ``scales`` positive std-devs (not log),
    ``opacities`` in [0, 1], ``intrinsics`` = (fx, fy, cx, cy). Differentiable w.r.t. means,
    quats, scales, opacities, colors (and background; viewmat only on the torch/cpp
    projection, not guaranteed).
    """
    _check(means, quats, scales, opacities, colors, viewmat, width, height, near, tile_size)
    width, height = int(width), int(height)
    fx, fy, cx, cy = (float(v) for v in (intrinsics.tolist() if torch.is_tensor(intrinsics)
                                          else intrinsics))
    dev, dtype = means.device, means.dtype
    bg = (torch.zeros(3, dtype=dtype, device=dev) if background is None
          else torch.as_tensor(background, dtype=dtype, device=dev).reshape(3))
    which = _resolve_backend(backend, dev)
    if which == "gsplat":
        return _rasterize_gsplat(means, quats, scales, opacities, colors, viewmat,
                                 (fx, fy, cx, cy), width, height, near, bg, tile_size)

    if which == "cpp" and dev.type != "cpu":
        raise RasterizerInputError(f"rasterize: backend 'cpp' needs CPU tensors, got {dev}")
    proj = _project(which, means, quats, scales, viewmat, fx, fy, cx, cy, width, height, near)
    if which == "cpp":
        f32 = lambda t: t.float().contiguous()  # noqa: E731
        rgb, depth, alpha, visible = RasterizeCpp.apply(
            f32(proj.means2d), f32(proj.conics), f32(colors), f32(opacities), f32(proj.depths),
            proj.ranges.contiguous(), f32(bg), width, height, tile_size)
        rgb, depth, alpha = rgb.to(dtype), depth.to(dtype), alpha.to(dtype)
    else:
        rgb, depth, alpha, visible = rasterize_reference(
            proj.means2d, proj.conics, colors, opacities, proj.depths, proj.ranges, width, height,
            bg, tile_size=tile_size)
    return RasterOutput(rgb=rgb, depth=depth, alpha=alpha, visible=visible, radii=proj.radii,
                        means2d=proj.means2d)


def _project(which, means, quats, scales, viewmat, fx, fy, cx, cy, width, height,
             near) -> Projected:
    """The C++ projection for the C++ kernel when ``viewmat`` needs no gradient, else the
    torch one (``projection.project_gaussians``, the same rules)."""
    if which != "cpp" or viewmat.requires_grad:
        return project_gaussians(means, quats, scales, viewmat, fx, fy, cx, cy, width, height,
                                 near)
    dt = means.dtype
    m2d, conics, depths, ranges, radii, valid = ProjectCpp.apply(
        means.contiguous(), quats.to(dt).contiguous(), scales.to(dt).contiguous(),
        viewmat.to(dt).contiguous(), fx, fy, cx, cy, width, height, float(near))
    return Projected(means2d=m2d, conics=conics, depths=depths, ranges=ranges, radii=radii,
                     valid=valid)


def _rasterize_gsplat(means, quats, scales, opacities, colors, viewmat, intr, width, height,
                      near, bg, tile_size) -> RasterOutput:
    """CUDA path through gsplat.rasterization (render mode RGB+D = alpha-blended depth).

    Conventions adapted: quaternions (x,y,z,w) -> (w,x,y,z); gsplat samples pixel (u, v) at
    (u + 0.5, v + 0.5), so the principal point is shifted by +0.5 to keep the project's
    integer pixel centres. gsplat exposes no transmittance, so ``visible`` here is
    ``radii > 0`` (in the view frustum), a superset of the T >= 0.5 rule of the other backends.
    """
    from gsplat import rasterization  # type: ignore

    fx, fy, cx, cy = intr
    K = torch.tensor([[fx, 0.0, cx + 0.5], [0.0, fy, cy + 0.5], [0.0, 0.0, 1.0]],
                     dtype=means.dtype, device=means.device)
    wxyz = torch.cat([quats[:, 3:4], quats[:, :3]], -1)
    img, alphas, info = rasterization(
        means, wxyz, scales, opacities, colors, viewmat.to(means)[None], K[None], width, height,
        near_plane=near, render_mode="RGB+D", tile_size=tile_size, packed=False)
    alpha = alphas[0, ..., 0]
    rgb = img[0, ..., :3] + (1 - alpha)[..., None] * bg
    radii = info["radii"][0]
    if radii.dim() == 2:   # gsplat >= 1.5 returns per-axis radii
        radii = radii.max(-1).values
    means2d = info["means2d"][0] - 0.5
    return RasterOutput(rgb=rgb, depth=img[0, ..., 3], alpha=alpha, visible=radii > 0,
                        radii=radii.to(torch.int32), means2d=means2d)
