"""Small helpers shared by the command-line entry points."""
from __future__ import annotations

import sys
from typing import Callable, Dict, List, Tuple, Type

def user_errors() -> Tuple[Type[BaseException], ...]:
    """All project exception types that signal a user mistake (imported lazily)."""
    import importlib
    names = [
        ("splat_slam_ros.config", "ConfigError"),
        ("splat_slam_ros.types", "IntrinsicsError"),
        ("splat_slam_ros.io.trajectory_io", "TrajectoryFormatError"),
        ("splat_slam_ros.io.datasets", "DatasetError"),
        ("splat_slam_ros.evaluation", "MetricError"),
        ("splat_slam_ros.depth.mono_depth", "MonoDepthError"),
        ("splat_slam_ros.io.synth", "SynthError"),
        ("splat_slam_ros.mapping.rasterizer", "RasterizerBuildError"),
        ("splat_slam_ros.mapping.mapper", "MapError"),
        ("splat_slam_ros.mapping.ply_io", "PlyError"),
        ("splat_slam_ros.mapping.mesh", "MeshError"),
    ]
    out: List[Type[BaseException]] = []
    for mod, name in names:
        try:
            m = importlib.import_module(mod)
        except Exception:
            continue
        cls = getattr(m, name, None)
        if isinstance(cls, type) and issubclass(cls, BaseException):
            out.append(cls)
    return tuple(out) + (FileNotFoundError,)


def run_main(body: Callable[[], int]) -> int:
    """Run a CLI body; user errors become `error: ...` and exit code 2."""
    errs = user_errors()
    try:
        return body() or 0
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except errs as e:  # type: ignore[misc]
        print(f"error: {e}", file=sys.stderr)
        return 2


def parse_overrides(items: List[str]) -> Dict[str, object]:
    """`--set key=value` items -> dict with YAML-parsed values (ConfigError if malformed)."""
    import yaml

    from splat_slam_ros.config import ConfigError
    out: Dict[str, object] = {}
    for it in items or []:
        if "=" not in it:
            raise ConfigError(f"--set expects KEY=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        out[k.strip()] = yaml.safe_load(v)
    return out
