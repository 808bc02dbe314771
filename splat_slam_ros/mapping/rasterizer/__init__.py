"""Differentiable 3D Gaussian rasterizer (paper §3.2, "Rendering").

Three layers, as in gsplat: this functional API; autograd wrappers (``kernel.RasterizeCpp``,
``kernel.ProjectCpp``; the torch path uses plain autograd); kernels (``csrc/``, with
``reference.py`` and ``projection.py`` as their pure-torch ground truth). The C++ backend
projects in C++ too, unless ``viewmat`` needs a gradient (the torch projection gives that).

Backends: ``"cpp"`` (CPU, tile-based C++/OpenMP kernel, hand-written backward), ``"torch"``
(pure torch, any device, slow), ``"gsplat"`` (CUDA, needs ``pip install gsplat``), ``"auto"``.
:func:`select_backend` turns a requested backend (``mapping.raster_backend``) into the one that
runs and why; an explicit backend that cannot run raises :class:`RasterBackendError`.
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import torch

from splat_slam_ros.config import ConfigError
from splat_slam_ros.mapping.rasterizer.kernel import (ProjectCpp, RasterizerBuildError, RasterizerError,
                                                     RasterizeCpp, load_extension)
from splat_slam_ros.mapping.rasterizer.projection import LOW_PASS, Projected, project_gaussians
from splat_slam_ros.mapping.rasterizer.reference import rasterize_reference

__all__ = ["rasterize", "visible_gaussians", "RasterOutput", "RasterizerError", "RasterizerBuildError",
           "RasterizerInputError", "RasterBackendError", "BackendChoice", "select_backend",
           "project_gaussians", "available_backends"]

BACKENDS = ("auto", "cpp", "torch", "gsplat")
_warned_fallback = False
log = logging.getLogger(__name__)


class RasterizerInputError(RasterizerError, ValueError):
    """Bad arguments to :func:`rasterize` (shapes, backend name, device)."""


class RasterBackendError(RasterizerError, ConfigError):
    """A requested backend (``mapping.raster_backend``) that cannot run here: unknown name, C++
    extension not loadable, gsplat not installed, or the wrong device. Never a fallback."""


@dataclass(frozen=True)
class BackendChoice:
    """The backend that runs (``name``: cpp, torch or gsplat), why, and what was asked."""
    name: str
    reason: str
    requested: str = "auto"
    fallback: bool = False     # auto settled on the slow torch path (no faster one available)

    def __str__(self) -> str:
        return f"{self.name} ({self.reason})"


@dataclass
class RasterOutput:
    rgb: torch.Tensor        # (H, W, 3)
    depth: torch.Tensor      # (H, W) alpha-blended camera z of the Gaussian centres
    alpha: torch.Tensor      # (H, W) accumulated opacity 1 - T_N
    visible: torch.Tensor    # (N,) bool: composited while T >= 0.5 (covisibility)
    radii: torch.Tensor      # (N,) int32 3-sigma radius in px, 0 if culled
    means2d: Optional[torch.Tensor] = None  # (N, 2) projected centres (call .retain_grad())


def _gsplat_error() -> Optional[str]:
    """None when gsplat imports, else why not."""
    try:
        import gsplat  # noqa: F401
        return None
    except Exception as e:
        return f"{type(e).__name__}: {e}"


def _gsplat_available() -> bool:
    return _gsplat_error() is None


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


def _auto_backend(device: torch.device) -> BackendChoice:
    """``auto``: gsplat on CUDA when it imports, the C++ kernel on CPU when it loads, else torch."""
    if device.type == "cuda":
        err = _gsplat_error()
        if err is None:
            return BackendChoice("gsplat", "auto: CUDA device, gsplat installed")
        return BackendChoice("torch", f"auto: CUDA device without gsplat ({err}); "
                             "pip install gsplat for the fast CUDA rasterizer", fallback=True)
    if device.type != "cpu":
        return BackendChoice("torch", f"auto: no dedicated rasterizer for {device.type} devices",
                             fallback=True)
    try:
        load_extension()
    except RasterizerBuildError as e:
        return BackendChoice("torch", f"auto: C++ extension unavailable: {e}", fallback=True)
    return BackendChoice("cpp", "auto: C++ OpenMP extension loaded")


def _explicit_backend(name: str, device: torch.device, key: str) -> BackendChoice:
    """An explicitly requested backend, or RasterBackendError saying why it cannot run."""
    if name == "torch":
        return BackendChoice("torch", f"{key}: torch (pure torch, slow)", name)
    if name == "cpp":
        if device.type != "cpu":
            raise RasterBackendError(
                f"{key} is 'cpp' but the map is on {device}: the C++ rasterizer runs on CPU "
                f"only; set mapping.device: cpu, or {key}: gsplat or auto on CUDA")
        try:
            load_extension()
        except RasterizerBuildError as e:
            raise RasterBackendError(
                f"{key} is 'cpp' but the C++ rasterizer extension cannot be loaded ({e}); "
                f"install g++ and ninja (./run.sh does) so it builds, or set {key}: torch "
                f"(about 30x slower) or auto (torch with a warning)") from None
        return BackendChoice("cpp", f"{key}: cpp (C++ OpenMP extension loaded)", name)
    if device.type != "cuda":
        raise RasterBackendError(
            f"{key} is 'gsplat' but the map is on {device}: gsplat needs a CUDA device; set "
            f"mapping.device: cuda on a CUDA machine, or {key}: cpp or auto on CPU")
    err = _gsplat_error()
    if err is not None:
        raise RasterBackendError(
            f"{key} is 'gsplat' but gsplat cannot be imported ({err}); pip install gsplat, "
            f"or set {key}: torch or auto")
    return BackendChoice("gsplat", f"{key}: gsplat (CUDA device, gsplat installed)", name)


def select_backend(requested: str, device, key: str = "mapping.raster_backend",
                   announce: bool = False) -> BackendChoice:
    """The backend that ``requested`` (auto, cpp, torch, gsplat) runs on ``device``, and why.

    An explicit backend that cannot run there raises :class:`RasterBackendError` naming ``key``
    and the fix (never a silent fallback). ``auto`` picks as :func:`rasterize` does. With
    ``announce`` the choice is logged: a warning when auto fell back to the slow torch path."""
    device = torch.device(device)
    if requested not in BACKENDS:
        raise RasterBackendError(f"{key}: unknown rasterizer backend {requested!r} "
                                 f"(use one of {', '.join(BACKENDS)})")
    choice = (_auto_backend(device) if requested == "auto"
              else _explicit_backend(requested, device, key))
    if announce and choice.fallback:
        log.warning("rasterizer backend: %s; the pure-torch rasterizer is about 30x slower "
                    "(set %s: cpp or gsplat to make this an error)", choice, key)
    elif announce:
        log.info("rasterizer backend: %s", choice)
    return choice


def _resolve_backend(backend: str, device: torch.device) -> str:
    global _warned_fallback
    if backend not in BACKENDS:
        raise RasterizerInputError(f"unknown rasterizer backend '{backend}' (use one of {BACKENDS})")
    if backend != "auto":
        return backend
    choice = _auto_backend(device)
    if choice.fallback and not _warned_fallback:
        warnings.warn(f"{choice.reason.removeprefix('auto: ')}; falling back to the slow "
                      "pure-torch rasterizer", RuntimeWarning, stacklevel=3)
        _warned_fallback = True
    return choice.name


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


def _intrinsics4(intrinsics) -> tuple:
    """(fx, fy, cx, cy) as floats, from a sequence or a tensor."""
    return tuple(float(v) for v in (intrinsics.tolist() if torch.is_tensor(intrinsics)
                                    else intrinsics))


def rasterize(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
              opacities: torch.Tensor, colors: torch.Tensor, viewmat: torch.Tensor,
              intrinsics: Union[Sequence[float], torch.Tensor], width: int, height: int,
              backend: str = "auto", near: float = 0.01,
              background: Optional[Union[Sequence[float], torch.Tensor]] = None,
              tile_size: int = 16, low_pass: float = LOW_PASS) -> RasterOutput:
    """Render N Gaussians (world frame) from world-to-camera ``viewmat``.

    ``quats`` are (x, y, z, w) (normalised here), ``scales`` positive std-devs (not log),
    ``opacities`` in [0, 1], ``intrinsics`` = (fx, fy, cx, cy). Differentiable w.r.t. means,
    quats, scales, opacities, colors (and background; viewmat only on the torch/cpp
    projection, not guaranteed). ``low_pass``: px^2 added to every projected covariance's
    diagonal (anti-aliasing; 0.3 as in 3DGS; a render on a 1/n pixel lattice passes 0.3 / n^2
    for the filter of the full-resolution image).
    """
    _check(means, quats, scales, opacities, colors, viewmat, width, height, near, tile_size)
    width, height = int(width), int(height)
    fx, fy, cx, cy = _intrinsics4(intrinsics)
    dev, dtype = means.device, means.dtype
    bg = (torch.zeros(3, dtype=dtype, device=dev) if background is None
          else torch.as_tensor(background, dtype=dtype, device=dev).reshape(3))
    which = _resolve_backend(backend, dev)
    if which == "gsplat" and dev.type != "cuda":
        raise RasterizerInputError(f"rasterize: backend 'gsplat' needs CUDA tensors, got {dev}")
    if which == "gsplat":
        return _rasterize_gsplat(means, quats, scales, opacities, colors, viewmat,
                                 (fx, fy, cx, cy), width, height, near, bg, tile_size, low_pass)

    if which == "cpp" and dev.type != "cpu":
        raise RasterizerInputError(f"rasterize: backend 'cpp' needs CPU tensors, got {dev}")
    proj = _project(which, means, quats, scales, viewmat, fx, fy, cx, cy, width, height, near,
                    low_pass)
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


@torch.no_grad()
def visible_gaussians(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                      opacities: torch.Tensor, viewmat: torch.Tensor,
                      intrinsics: Union[Sequence[float], torch.Tensor], width: int, height: int,
                      backend: str = "auto", near: float = 0.01, tile_size: int = 16,
                      low_pass: float = LOW_PASS) -> torch.Tensor:
    """(N,) bool: :func:`rasterize`'s ``visible`` (composited while T >= 0.5: the covisibility
    sets), without the render. The C++ kernel stops a pixel once T < 0.5, where the render
    has nothing more to flag, so it skips the pixels' back layers (the same flags to the
    bit); the other backends render and take them."""
    zeros = torch.zeros_like(means)
    which = _resolve_backend(backend, means.device)
    if which != "cpp" or means.device.type != "cpu":      # rasterize checks and says why
        return rasterize(means, quats, scales, opacities, zeros, viewmat, intrinsics, width,
                         height, backend=which, near=near, tile_size=tile_size,
                         low_pass=low_pass).visible
    _check(means, quats, scales, opacities, zeros, viewmat, width, height, near, tile_size)
    fx, fy, cx, cy = _intrinsics4(intrinsics)
    proj = _project(which, means, quats, scales, viewmat, fx, fy, cx, cy, int(width),
                    int(height), near, low_pass)
    m2d, conics, opac, depths = (t.float().contiguous() for t in
                                 (proj.means2d, proj.conics, opacities, proj.depths))
    return load_extension().visible(m2d, conics, opac, depths, proj.ranges.contiguous(),
                                    int(width), int(height), tile_size).bool()


def _project(which, means, quats, scales, viewmat, fx, fy, cx, cy, width, height,
             near, low_pass=LOW_PASS) -> Projected:
    """The C++ projection for the C++ kernel when ``viewmat`` needs no gradient, else the
    torch one (``projection.project_gaussians``, the same rules)."""
    if which != "cpp" or viewmat.requires_grad:
        return project_gaussians(means, quats, scales, viewmat, fx, fy, cx, cy, width, height,
                                 near, low_pass)
    dt = means.dtype
    m2d, conics, depths, ranges, radii, valid = ProjectCpp.apply(
        means.contiguous(), quats.to(dt).contiguous(), scales.to(dt).contiguous(),
        viewmat.to(dt).contiguous(), fx, fy, cx, cy, width, height, float(near),
        float(low_pass))
    return Projected(means2d=m2d, conics=conics, depths=depths, ranges=ranges, radii=radii,
                     valid=valid)


def _rasterize_gsplat(means, quats, scales, opacities, colors, viewmat, intr, width, height,
                      near, bg, tile_size, low_pass=LOW_PASS) -> RasterOutput:
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
        near_plane=near, render_mode="RGB+D", tile_size=tile_size, packed=False, eps2d=low_pass)
    alpha = alphas[0, ..., 0]
    rgb = img[0, ..., :3] + (1 - alpha)[..., None] * bg
    radii = info["radii"][0]
    if radii.dim() == 2:   # gsplat >= 1.5 returns per-axis radii
        radii = radii.max(-1).values
    means2d = info["means2d"][0] - 0.5
    return RasterOutput(rgb=rgb, depth=img[0, ..., 3], alpha=alpha, visible=radii > 0,
                        radii=radii.to(torch.int32), means2d=means2d)
