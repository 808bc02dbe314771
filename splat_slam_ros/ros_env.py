"""The ROS 2 / DDS environment every splat_slam_ros process runs with (no rclpy import here).

Every project process (nodes, launcher, bag player, topic tool, tests) uses the same
environment so that they discover each other quickly and move large messages through shared
memory:

- ``FASTRTPS_DEFAULT_PROFILES_FILE``: the shipped Fast DDS profile for the discovery range
  ``SPLAT_SLAM_DDS_RANGE`` (default ``localhost``: ``config/fastdds.xml``, shared memory 32 MiB +
  UDPv4 on 127.0.0.1 only, the equivalent of ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``;
  ``subnet``: ``config/fastdds_subnet.xml``, UDPv4 on every interface, for multi-host graphs),
  unless the user already set one;
- ``RMW_IMPLEMENTATION``: ``rmw_fastrtps_cpp`` (the only RMW on PyPI) unless set;
- ``ROS_DOMAIN_ID`` and the other ``ROS_*`` variables: passed through (validated).

Use :func:`ros_environment` for the ``env=`` of subprocesses, and call
:func:`apply_ros_environment` in a process before ``import rclpy`` (RMW_IMPLEMENTATION is
checked when rclpy's library loads) and in any case before ``rclpy.init()`` (the DDS profile
is read when the first DDS participant is created; measured: setting it in-process after
``import rclpy`` but before ``rclpy.init()`` takes effect).

``SPLAT_SLAM_DDS_PROFILE=none`` turns the shipped profile off (Fast DDS defaults);
``SPLAT_SLAM_DDS_PROFILE=/path.xml`` picks another one.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Mapping, MutableMapping, Optional

PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
RMW_ENV = "RMW_IMPLEMENTATION"
DEFAULT_RMW = "rmw_fastrtps_cpp"
OVERRIDE_ENV = "SPLAT_SLAM_DDS_PROFILE"
RANGE_ENV = "SPLAT_SLAM_DDS_RANGE"
RANGES = {"localhost": "fastdds.xml", "subnet": "fastdds_subnet.xml"}  # range -> shipped profile
MAX_DOMAIN_ID = 232  # the largest domain id the RTPS port mapping allows (ROS 2 docs)


class RosEnvError(ValueError):
    """The ROS environment given by the user is invalid (one-line message)."""


def dds_range(env: Mapping[str, str]) -> str:
    """The discovery range named by ``SPLAT_SLAM_DDS_RANGE`` in ``env`` (default ``localhost``)."""
    r = env.get(RANGE_ENV, "").strip().lower() or "localhost"
    if r not in RANGES:
        raise RosEnvError(f"{RANGE_ENV} must be one of {', '.join(RANGES)}, got {env[RANGE_ENV]!r}")
    return r


def shipped_profile(dds_range_name: str = "localhost") -> Optional[Path]:
    """Path of the shipped Fast DDS profile of a discovery range, or None when not found."""
    name = RANGES[dds_range_name]
    here = Path(__file__).resolve().parent
    candidates = [
        here.parent / "config" / name,                                # source / editable install
        here / "config" / name,                                       # packaged as package data
        Path(sys.prefix) / "share" / "splat_slam_ros" / "config" / name,  # data_files
    ]
    for c in candidates:
        if c.is_file():
            return c
    return None


def _is_shipped(path: str) -> bool:
    shipped = {shipped_profile(r) for r in RANGES} - {None}
    return Path(path).expanduser().resolve() in shipped


def ros_environment(base: Optional[Mapping[str, str]] = None) -> dict:
    """A copy of ``base`` (default ``os.environ``) with the project's ROS/DDS settings.

    Raises :class:`RosEnvError` for an invalid ``ROS_DOMAIN_ID`` or ``SPLAT_SLAM_DDS_RANGE``, or
    a missing profile file named by ``SPLAT_SLAM_DDS_PROFILE``.
    """
    env = dict(os.environ if base is None else base)

    dom = env.get("ROS_DOMAIN_ID", "").strip()
    if dom:
        try:
            d = int(dom)
        except ValueError:
            d = -1
        if not 0 <= d <= MAX_DOMAIN_ID:
            raise RosEnvError(f"ROS_DOMAIN_ID must be an integer in 0..{MAX_DOMAIN_ID}, got {dom!r}")
        env["ROS_DOMAIN_ID"] = str(d)

    # Idle OpenMP threads sleep instead of spinning: with several node processes on a 2-core
    # machine, spinning made the rasterizer up to 50x slower (measured). Must precede torch.
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")

    env.setdefault(RMW_ENV, DEFAULT_RMW)
    if not env[RMW_ENV]:
        env[RMW_ENV] = DEFAULT_RMW

    rng = dds_range(env)
    choice = env.get(OVERRIDE_ENV, "").strip()
    if choice.lower() == "none":
        pass                                         # user wants Fast DDS defaults / own file
    elif choice:
        p = Path(choice).expanduser()
        if not p.is_file():
            raise RosEnvError(f"{OVERRIDE_ENV} names a missing file: {p}")
        env[PROFILE_ENV] = str(p.resolve())
    elif not env.get(PROFILE_ENV) or _is_shipped(env[PROFILE_ENV]):
        # a shipped profile inherited from a parent process follows this process's range
        prof = shipped_profile(rng)
        if prof is None:
            raise RosEnvError(f"the shipped Fast DDS profile {RANGES[rng]} is missing "
                              "(broken install)")
        env[PROFILE_ENV] = str(prof)
    return env


def apply_ros_environment(environ: Optional[MutableMapping[str, str]] = None) -> dict:
    """Set :func:`ros_environment` in ``environ`` (default ``os.environ``) and return it.

    Call before ``import rclpy`` / ``rclpy.init()``. Only variables that change are written.
    """
    target = os.environ if environ is None else environ
    env = ros_environment(target)
    for k, v in env.items():
        if target.get(k) != v:
            target[k] = v
    return env


def random_domain_id(low: int = 1, high: int = 101) -> int:
    """A random ROS_DOMAIN_ID for isolated test runs (avoids crosstalk between runs).

    Stays in 1..101: higher ids map to UDP ports inside Linux's ephemeral port range.
    """
    import random
    return random.SystemRandom().randint(low, high)
