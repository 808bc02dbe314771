"""Small helpers shared by the command-line entry points."""
from __future__ import annotations

import sys
from typing import Callable, Dict, List, Optional, Tuple, Type

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
    """The project exception types that signal a user mistake, of the modules imported so
    far (an exception can only come from one of these; none is imported here)."""
    return tuple(getattr(sys.modules[m], n) for m, n in USER_ERROR_TYPES
                 if m in sys.modules) + (FileNotFoundError,)


def is_user_error(e: BaseException, extra: Tuple[Type[BaseException], ...] = ()) -> bool:
    """Whether ``e`` is one of :func:`user_errors` or of ``extra``."""
    return isinstance(e, user_errors() + tuple(extra))


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


def bag_topics(image_topic: Optional[str] = None, camera_info_topic: Optional[str] = None
               ) -> dict:
    """``open_dataset`` options of the CLIs' ``--image-topic`` / ``--camera-info-topic``."""
    t = {k: v for k, v in (("image", image_topic), ("camera_info", camera_info_topic)) if v}
    return {"topics": t} if t else {}


def add_topic_arguments(ap) -> None:
    """The CLIs' bag topic options (a bag not written by splat-slam-convert)."""
    ap.add_argument("--image-topic", metavar="TOPIC",
                    help="a bag's image topic (sensor_msgs/Image or CompressedImage; default: "
                         "the bag's only image topic)")
    ap.add_argument("--camera-info-topic", metavar="TOPIC",
                    help="a bag's camera_info topic (default: the image topic's sibling "
                         "camera_info, or the bag's only one)")
