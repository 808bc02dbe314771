"""The project's C++/OpenMP kernels (``csrc/``: the Gaussian rasterizer, the fused view
loss, the dense-BA edge terms): JIT build with a per-machine cache.

The extension is compiled once per (sources, flags, torch, python, CPU) combination into
``$XDG_CACHE_HOME/splat_slam_ros/ext/<hash>/`` (default ``~/.cache/...``; override the
root with ``SPLAT_SLAM_EXT_DIR``). Later loads import the built module directly (no
compiler, no ninja). A file lock keeps concurrent processes from building at once.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib.util
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
SOURCES = ("raster.cpp",)              # compiled (the bindings; the kernels are headers)
_lock = threading.Lock()
_module = None
_failure: "KernelBuildError | None" = None


class KernelBuildError(RuntimeError):
    """The C++ kernels could not be compiled or loaded (a one-line, user-facing message)."""


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
    for path in sorted(CSRC.glob("*.[ch]*")):        # every source and header: the cache key
        h.update(path.name.encode())
        h.update(path.read_bytes())
    h.update(" ".join(build_flags()).encode())
    h.update(torch.__version__.encode())
    h.update(sys.version.encode())
    h.update(platform.machine().encode())
    h.update(os.environ.get("CXX", "c++").encode())
    return base / h.hexdigest()[:16]


def _module_name(d: Path) -> str:
    return f"splat_native_{d.name}"


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
        raise KernelBuildError(
            f"no C++ compiler found ('{_compiler()}'): install g++ (apt-get install g++)")
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise KernelBuildError(f"cannot create the kernel cache directory {d} ({e}); set "
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
            raise KernelBuildError(
                f"building the C++ kernels failed ({detail}); build directory: {d}") from None
        (d / "BUILD_OK").write_text(" ".join(build_flags()) + "\n")
        return mod


def load_extension(verbose: bool = False):
    """Return the compiled module, building it on first use. Raises KernelBuildError."""
    global _module, _failure
    with _lock:
        if _module is not None:
            return _module
        if _failure is not None:
            raise _failure
        d = cache_dir()
        try:
            _module = _import_built(d) or _build(d, verbose)
        except KernelBuildError as e:
            _failure = e
            raise
        except Exception as e:
            _failure = KernelBuildError(f"loading the C++ kernels failed: {e}")
            raise _failure from None
        return _module
