"""Small helpers shared by the command-line entry points."""
from __future__ import annotations

import sys
from typing import Callable, Dict, List, Tuple, Type

import yaml

from splat_slam_ros.config import ConfigError

# Every project exception type that signals a user mistake (printed as ``error: ...``), by
# module: a command imports only the stages it runs (``splat-slam-run --tracking-only``
# neither the mapper, scipy nor Open3D: 90 MB and 1 s less), and an exception can only come
# from a module that was imported.
USER_ERROR_TYPES: Tuple[Tuple[str, str], ...] = (
    ("splat_slam_ros.config", "ConfigError"), ("splat_slam_ros.types", "IntrinsicsError"),
    ("splat_slam_ros.runtime", "DeviceError"),
    ("splat_slam_ros.io.trajectory_io", "TrajectoryFormatError"),
    ("splat_slam_ros.io.dataset_base", "DatasetError"),
    ("splat_slam_ros.io.sensor_codec", "ConversionError"),
    ("splat_slam_ros.evaluation.inputs", "MetricError"),
    ("splat_slam_ros.tracking.mono_depth", "MonoDepthError"),
    ("splat_slam_ros.depth.proxy_depth", "ProxyDepthError"),
    ("splat_slam_ros.mapping.rasterizer", "RasterizerBuildError"),
    ("splat_slam_ros.mapping.mapper", "MapError"), ("splat_slam_ros.mapping.mesh", "MeshError"),
    ("splat_slam_ros.mapping.ply_io", "PlyError"),
    ("splat_slam_ros.tracking.tracker", "TrackingError"),
    ("splat_slam_ros.tracking.flow_frontend", "FrontendError"),
    ("splat_slam_ros.io.keyframe_store", "StoreError"),
    ("splat_slam_ros.io.session", "SessionError"))


def user_errors() -> Tuple[Type[BaseException], ...]:
    """All project exception types that signal a user mistake (imports their modules)."""
    import splat_slam_ros.depth.proxy_depth  # noqa: F401  (every module of USER_ERROR_TYPES)
    import splat_slam_ros.evaluation.inputs  # noqa: F401
    import splat_slam_ros.io.dataset_base  # noqa: F401
    import splat_slam_ros.io.keyframe_store  # noqa: F401
    import splat_slam_ros.io.sensor_codec  # noqa: F401
    import splat_slam_ros.io.session  # noqa: F401
    import splat_slam_ros.io.trajectory_io  # noqa: F401
    import splat_slam_ros.mapping.mapper  # noqa: F401
    import splat_slam_ros.mapping.mesh  # noqa: F401
    import splat_slam_ros.mapping.ply_io  # noqa: F401
    import splat_slam_ros.mapping.rasterizer  # noqa: F401
    import splat_slam_ros.runtime  # noqa: F401
    import splat_slam_ros.tracking.flow_frontend  # noqa: F401
    import splat_slam_ros.tracking.mono_depth  # noqa: F401
    import splat_slam_ros.tracking.tracker  # noqa: F401
    import splat_slam_ros.types  # noqa: F401
    return tuple(getattr(sys.modules[m], n) for m, n in USER_ERROR_TYPES) + \
        (FileNotFoundError,)


def is_user_error(e: BaseException, extra: Tuple[Type[BaseException], ...] = ()) -> bool:
    """Whether ``e`` is one of :func:`user_errors` (looked up among the modules already
    imported: none is imported for the check) or of ``extra``."""
    for m, n in USER_ERROR_TYPES:
        mod = sys.modules.get(m)
        if mod is not None and isinstance(e, getattr(mod, n)):
            return True
    return isinstance(e, (FileNotFoundError,) + tuple(extra))


def run_main(body: Callable[[], int], extra_errors: Tuple[Type[BaseException], ...] = ()) -> int:
    """Run a CLI body; user errors (and ``extra_errors``, those of a package beside the
    library such as the scene generator's) become `error: ...` and exit code 2."""
    try:
        return body() or 0
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        if not is_user_error(e, tuple(extra_errors)):
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2


def parse_overrides(items: List[str]) -> Dict[str, object]:
    """`--set key=value` items -> dict with YAML-parsed values (ConfigError if malformed)."""
    out: Dict[str, object] = {}
    for it in items or []:
        if "=" not in it:
            raise ConfigError(f"--set expects KEY=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        out[k.strip()] = yaml.safe_load(v)
    return out
