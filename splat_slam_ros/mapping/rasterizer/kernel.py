"""The C++/OpenMP kernel: JIT build with a per-machine cache, and its autograd.Function.

The extension is compiled once per (sources, flags, torch, python, CPU) combination into
``$XDG_CACHE_HOME/splat_slam_ros/ext/<hash>/`` (default ``~/.cache/...``; override the
root with ``SPLAT_SLAM_EXT_DIR``). Later loads import the built module directly (no
compiler, no ninja). A file lock keeps concurrent processes from building at once.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import math
import os
import platform
import shlex
import shutil
import sys
import threading
from pathlib import Path

import torch

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: no inter-process build lock
    fcntl = None

CSRC = Path(__file__).resolve().parent / "csrc"
SOURCES = ("raster.cpp",)              # compiled
# part of the cache key
HASHED = ("raster.cpp", "raster_kernels.h", "project_kernels.h", "loss_kernels.h", "lanes.h")
_lock = threading.Lock()
_module = None
_failure: "RasterizerBuildError | None" = None


class RasterizerError(RuntimeError):
    """Base class of rasterizer errors (one-line, user-facing messages)."""


class RasterizerBuildError(RasterizerError):
    """The C++ kernel could not be compiled or loaded."""


def _cpu_flags() -> list[str]:
    """Portable ISA flags: what torch itself detected on this CPU (part of the cache key)."""
    if platform.machine() not in ("x86_64", "AMD64"):
        return []
    cap = torch.backends.cpu.get_cpu_capability()
    if cap.startswith("AVX512"):
        return ["-mavx2", "-mfma", "-mavx512f", "-mavx512dq", "-mavx512vl", "-mavx512bw",
                "-mprefer-vector-width=512"]
    if cap.startswith("AVX2"):
        return ["-mavx2", "-mfma"]
    return []


def build_flags() -> list[str]:
    extra = shlex.split(os.environ.get("SPLAT_SLAM_CXXFLAGS", ""))
    # -fno-trapping-math: without it GCC refuses to if-convert (and so to vectorise) the
    # compositing loops; it changes no results (no FP traps are enabled).
    # -ffp-contract=off: the kernels fuse multiply-adds themselves, the same way in the
    # forward and in the backward's recomputation of it (raster_kernels.h).
    return ["-O3", "-fno-trapping-math", "-ffp-contract=off", "-fopenmp", "-DNDEBUG",
            *_cpu_flags(), *extra]


def _compiler() -> str:
    cxx = os.environ.get("CXX", "c++")
    return shlex.split(cxx)[0] if cxx.strip() else "c++"


def cache_dir() -> Path:
    """Build directory of the current sources/flags/torch (created on demand)."""
    root = os.environ.get("SPLAT_SLAM_EXT_DIR")
    if root:
        base = Path(root)
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "splat_slam_ros" / "ext"
    h = hashlib.sha256()
    for name in HASHED:
        h.update((CSRC / name).read_bytes())
    h.update(" ".join(build_flags()).encode())
    h.update(torch.__version__.encode())
    h.update(sys.version.encode())
    h.update(platform.machine().encode())
    h.update(os.environ.get("CXX", "c++").encode())
    return base / h.hexdigest()[:16]


def _module_name(d: Path) -> str:
    return f"splat_raster_{d.name}"


def _import_built(d: Path):
    name = _module_name(d)
    so = d / f"{name}{'.pyd' if os.name == 'nt' else '.so'}"
    if not so.is_file() or not (d / "BUILD_OK").is_file():
        return None
    spec = importlib.util.spec_from_file_location(name, so)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@contextlib.contextmanager
def _file_lock(path: Path):
    with open(path, "a+") as fh:
        if fcntl is not None:
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            if fcntl is not None:
                fcntl.flock(fh, fcntl.LOCK_UN)


@contextlib.contextmanager
def _ninja_on_path():
    """The venv's ninja may not be on PATH when the venv is not activated."""
    old = os.environ.get("PATH", "")
    dirs = [os.path.dirname(sys.executable)]
    try:
        import ninja  # type: ignore
        dirs.append(ninja.BIN_DIR)
    except Exception:
        pass
    os.environ["PATH"] = os.pathsep.join([*dirs, old])
    try:
        yield
    finally:
        os.environ["PATH"] = old


def _build(d: Path, verbose: bool):
    from torch.utils import cpp_extension

    if shutil.which(_compiler()) is None:
        raise RasterizerBuildError(
            f"no C++ compiler found ('{_compiler()}'): install g++ (apt-get install g++)")
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RasterizerBuildError(f"cannot create the kernel cache directory {d} ({e}); set "
                                   "SPLAT_SLAM_EXT_DIR to a writable directory") from None
    with _file_lock(d.parent / f"{d.name}.lock"):
        mod = _import_built(d)  # another process may have finished meanwhile
        if mod is not None:
            return mod
        try:
            with _ninja_on_path():
                mod = cpp_extension.load(
                    name=_module_name(d), sources=[str(CSRC / s) for s in SOURCES],
                    extra_cflags=build_flags(), extra_ldflags=["-fopenmp"],
                    build_directory=str(d), verbose=verbose)
        except Exception as e:  # compiler errors, missing ninja, ...
            lines = [ln.strip() for ln in str(e).strip().splitlines() if ln.strip()]
            errors = [ln for ln in lines if "error:" in ln]   # compiler diagnostics
            detail = " | ".join(errors[:2] or lines[-2:])[:400] if lines else type(e).__name__
            raise RasterizerBuildError(
                f"building the C++ rasterizer failed ({detail}); build directory: {d}") from None
        (d / "BUILD_OK").write_text(" ".join(build_flags()) + "\n")
        return mod


def load_extension(verbose: bool = False):
    """Return the compiled module, building it on first use. Raises RasterizerBuildError."""
    global _module, _failure
    with _lock:
        if _module is not None:
            return _module
        if _failure is not None:
            raise _failure
        d = cache_dir()
        try:
            _module = _import_built(d) or _build(d, verbose)
        except RasterizerBuildError as e:
            _failure = e
            raise
        except Exception as e:
            _failure = RasterizerBuildError(f"loading the C++ rasterizer failed: {e}")
            raise _failure from None
        return _module


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
