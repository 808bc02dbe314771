"""Input checks of the mapper's services (pure Python: testable without ROS).

- ``/splat/map/save`` (and the launcher's ``/splat/save_map`` and ``/splat/load_map``)
  write and read only inside the run's output directory (``node.output_dir``, ``--out``):
  the request names a relative sub-directory ("" = the output directory itself); absolute
  paths, ``..`` and symlinks leading outside are refused.
- ``/splat/map/reset`` is refused unless the node parameter ``node.allow_reset`` is true.
- ``/splat/map/render`` sizes are bounded: width x height <= ``node.max_render_pixels``
  (0 = 4x the camera image area); poses and intrinsics must be finite.

Every check raises :class:`ServiceInputError` with a one-line message that the node returns
as the service's error response.
"""
from __future__ import annotations

import math
from pathlib import Path, PurePosixPath
from typing import Optional, Sequence

MAX_NAME = 255          # longest accepted save directory name (characters)


class ServiceInputError(ValueError):
    """A service request the node refuses (one-line message for the response)."""


def save_dir(requested: str, output_dir: Optional[Path]) -> Path:
    """The directory a SaveMap request may write: inside ``output_dir``, never outside."""
    if output_dir is None:
        raise ServiceInputError("saving is disabled: the mapper has no node.output_dir "
                                "(start it with splat-slam-launch --out DIR)")
    name = (requested or "").strip()
    if len(name) > MAX_NAME or any(c in name for c in "\0\n\r"):
        raise ServiceInputError("directory must be a short relative name without control "
                                "characters")
    p = PurePosixPath(name)
    if p.is_absolute() or name.startswith("~"):
        raise ServiceInputError(f"directory {name!r} is absolute: give a name relative to the "
                                f"output directory {output_dir}")
    if ".." in p.parts:
        raise ServiceInputError(f"directory {name!r} contains '..': map services stay inside "
                                f"the output directory {output_dir}")
    base = Path(output_dir).resolve()
    target = (base / p).resolve()
    if target != base and base not in target.parents:
        raise ServiceInputError(f"directory {name!r} leads outside the output directory {base}")
    return target


def inside(path, output_dir: Optional[Path]) -> Path:
    """``path`` (absolute, as the launcher resolved it from a request) when it lies inside
    ``output_dir``: a node checks again what a graph event asks it to write."""
    if output_dir is None or not isinstance(path, str) or not path:
        raise ServiceInputError("no output directory to save into (node.output_dir)")
    base, target = Path(output_dir).resolve(), Path(path).resolve()
    if target != base and base not in target.parents:
        raise ServiceInputError(f"{path!r} is outside the output directory {base}")
    return target


def check_reset(allowed: bool) -> None:
    if not allowed:
        raise ServiceInputError("map reset is disabled (set the node parameter "
                                "node.allow_reset:=true to enable it)")


def render_size(width: int, height: int, cam_w: int, cam_h: int, max_pixels: int) -> tuple:
    """(w, h) of a RenderPose request: 0 = the camera size; w*h bounded by ``max_pixels``."""
    w, h = int(width) or int(cam_w), int(height) or int(cam_h)
    limit = int(max_pixels) if int(max_pixels) > 0 else 4 * int(cam_w) * int(cam_h)
    if w <= 0 or h <= 0:
        raise ServiceInputError(f"render size {w}x{h} must be positive")
    if w * h > limit:
        raise ServiceInputError(f"render size {w}x{h} exceeds the limit of {limit} pixels "
                                "(node.max_render_pixels; default 4x the camera image area)")
    return w, h


def check_finite(values: Sequence[float], what: str) -> None:
    if not all(math.isfinite(float(v)) for v in values):
        raise ServiceInputError(f"{what} contains NaN or infinite values")


def check_pose_msg(pose) -> None:
    """A geometry_msgs/Pose with finite values and a non-zero quaternion (it is normalised)."""
    p, q = pose.position, pose.orientation
    check_finite([p.x, p.y, p.z, q.x, q.y, q.z, q.w], "pose")
    n = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    if n < 1e-6:
        raise ServiceInputError("pose orientation is a zero quaternion")


def check_intrinsics(intrinsics: Sequence[float]) -> Optional[list]:
    """None for all zeros (the map camera's), else finite positive fx, fy."""
    vals = [float(x) for x in intrinsics]
    check_finite(vals, "intrinsics")
    if not any(abs(v) > 0 for v in vals):
        return None
    if vals[0] <= 0 or vals[1] <= 0:
        raise ServiceInputError("intrinsics fx, fy must be positive (or all four zero)")
    return vals


def message(e: BaseException) -> str:
    """The error response text: a refusal as is, anything else with its exception type."""
    return str(e) if isinstance(e, ServiceInputError) else f"{type(e).__name__}: {e}"
