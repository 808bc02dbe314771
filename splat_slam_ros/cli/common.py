"""Small helpers shared by the command-line entry points."""
from __future__ import annotations

import sys
from typing import Callable, Dict, List, Tuple, Type

import yaml

from splat_slam_ros.config import ConfigError
from splat_slam_ros.tracking.mono_depth import MonoDepthError
from splat_slam_ros.depth.proxy_depth import ProxyDepthError
from splat_slam_ros.evaluation.inputs import MetricError
from splat_slam_ros.io.dataset_base import DatasetError
from splat_slam_ros.io.keyframe_store import StoreError
from splat_slam_ros.io.sensor_codec import ConversionError
from splat_slam_ros.io.session import SessionError
from splat_slam_ros.io.trajectory_io import TrajectoryFormatError
from splat_slam_ros.mapping.mapper import MapError
from splat_slam_ros.mapping.mesh import MeshError
from splat_slam_ros.mapping.ply_io import PlyError
from splat_slam_ros.mapping.rasterizer import RasterizerBuildError
from splat_slam_ros.runtime import DeviceError
from splat_slam_ros.tracking.flow_frontend import FrontendError
from splat_slam_ros.tracking.tracker import TrackingError
from splat_slam_ros.types import IntrinsicsError

# Every project exception type that signals a user mistake (printed as ``error: ...``).
USER_ERRORS: Tuple[Type[BaseException], ...] = (
    ConfigError, IntrinsicsError, DeviceError, TrajectoryFormatError, DatasetError,
    ConversionError, MetricError, MonoDepthError, ProxyDepthError,
    RasterizerBuildError, MapError, MeshError, PlyError, TrackingError, FrontendError, StoreError,
    SessionError, FileNotFoundError)


def user_errors() -> Tuple[Type[BaseException], ...]:
    """All project exception types that signal a user mistake."""
    return USER_ERRORS


def run_main(body: Callable[[], int], extra_errors: Tuple[Type[BaseException], ...] = ()) -> int:
    """Run a CLI body; user errors (and ``extra_errors``, those of a package beside the
    library such as the scene generator's) become `error: ...` and exit code 2."""
    errs = user_errors() + tuple(extra_errors)
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
    out: Dict[str, object] = {}
    for it in items or []:
        if "=" not in it:
            raise ConfigError(f"--set expects KEY=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        out[k.strip()] = yaml.safe_load(v)
    return out
