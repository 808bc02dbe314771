"""Message classes by ROS type name ('pkg/msg/Name') for the tools that handle topics whose
type is known only at run time (bag player, splat-slam-topic).

Plain imports of every message package the project's graph uses; a type outside them is
reported as unknown (no dynamic imports).
"""
from __future__ import annotations

import builtin_interfaces.msg
import geometry_msgs.msg
import nav_msgs.msg
import rcl_interfaces.msg
import rosgraph_msgs.msg
import sensor_msgs.msg
import splat_slam_msgs.msg
import std_msgs.msg
import tf2_msgs.msg
import visualization_msgs.msg

PACKAGES = {
    "builtin_interfaces/msg": builtin_interfaces.msg,
    "geometry_msgs/msg": geometry_msgs.msg,
    "nav_msgs/msg": nav_msgs.msg,
    "rcl_interfaces/msg": rcl_interfaces.msg,
    "rosgraph_msgs/msg": rosgraph_msgs.msg,
    "sensor_msgs/msg": sensor_msgs.msg,
    "splat_slam_msgs/msg": splat_slam_msgs.msg,
    "std_msgs/msg": std_msgs.msg,
    "tf2_msgs/msg": tf2_msgs.msg,
    "visualization_msgs/msg": visualization_msgs.msg,
}


class UnknownMessageType(LookupError):
    """A type name that is malformed or not in :data:`PACKAGES`."""


def message_class(type_name: str):
    """'pkg/msg/Name' -> the rclpy message class; UnknownMessageType otherwise."""
    parts = str(type_name).split("/")
    if len(parts) != 3:
        raise UnknownMessageType(f"unexpected message type name {type_name!r} "
                                 "(expected pkg/msg/Name)")
    mod = PACKAGES.get(f"{parts[0]}/{parts[1]}")
    cls = getattr(mod, parts[2], None) if mod is not None else None
    if not isinstance(cls, type):
        raise UnknownMessageType(f"message type {type_name} is not one of the packages this "
                                 f"tool knows ({', '.join(p.split('/')[0] for p in PACKAGES)})")
    return cls
