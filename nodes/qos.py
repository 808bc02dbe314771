"""QoS presets of every splat_slam_ros topic, in one place.

Each preset is a plain :class:`QoSSpec` (readable without rclpy) and a function returning a
fresh ``rclpy.qos.QoSProfile``. Measured facts behind the choices (2-core machine, Fast DDS
with config/fastdds.xml): RELIABLE image streams deliver every frame at ~3 ms median latency;
a publisher loses the first messages sent before a subscriber matched, and TRANSIENT_LOCAL
replays at most ``depth`` messages to late joiners.

Compatibility reminder: a RELIABLE subscription does not match a BEST_EFFORT publisher, and a
TRANSIENT_LOCAL subscription does not match a VOLATILE publisher. Subscribe to external
cameras with :func:`sensor_qos` (BEST_EFFORT matches any publisher).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Dict

from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)


@dataclass(frozen=True)
class QoSSpec:
    reliable: bool
    transient_local: bool
    depth: int
    why: str

    def profile(self) -> QoSProfile:
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=self.depth,
            reliability=ReliabilityPolicy.RELIABLE if self.reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=(DurabilityPolicy.TRANSIENT_LOCAL if self.transient_local
                        else DurabilityPolicy.VOLATILE))


PRESETS: Dict[str, QoSSpec] = {
    # Input frames from our bag player / dataset publisher to the tracker.
    "image": QoSSpec(True, False, 10,
                     "every input frame must reach the tracker; RELIABLE costs ~3 ms with the SHM profile"),
    # Subscribing to an external live camera driver.
    "sensor": QoSSpec(False, False, 5,
                      "BEST_EFFORT matches both best-effort and reliable camera drivers; stale frames are useless"),
    # Tracker -> depth / mapper keyframes (~1-3 MB each).
    "keyframe": QoSSpec(True, True, 200,
                        "no keyframe may be lost and late-starting nodes must get the past ones (deep, bounded memory)"),
    # Pose-graph updates (local BA, loop closure, global BA, final).
    "pose_graph": QoSSpec(True, True, 100,
                          "every update changes the map; late joiners replay recent ones after the keyframes"),
    # Proxy depth per keyframe (and re-computed after updates).
    "proxy_depth": QoSSpec(True, True, 100,
                           "the mapper needs the depth of every keyframe, even if it starts later"),
    # Mapper renders for viewers.
    "rendered": QoSSpec(True, False, 1,
                        "viewers only need the latest; RELIABLE matches any viewer, depth 1 never stalls the mapper"),
    # Lockstep acknowledgements tracker -> bag player.
    "ack": QoSSpec(True, True, 10,
                   "a lost ack stalls the player; TRANSIENT_LOCAL covers acks sent before the player matched"),
    # Mapper status / other latched low-rate state.
    "status": QoSSpec(True, True, 1,
                      "latched: a late subscriber gets the latest status at once"),
    # Current camera pose / trajectory stream.
    "pose": QoSSpec(True, False, 50,
                    "small messages, every pose wanted for the trajectory; no replay needed"),
}


def qos(name: str) -> QoSProfile:
    """A fresh QoSProfile of preset ``name`` (one of :data:`PRESETS`)."""
    try:
        return PRESETS[name].profile()
    except KeyError:
        raise KeyError(f"unknown QoS preset {name!r}; known: {', '.join(PRESETS)}") from None


# One factory per preset: image_qos() == qos("image"), and so on.
(image_qos, sensor_qos, keyframe_qos, pose_graph_qos, proxy_depth_qos, rendered_qos, ack_qos,
 status_qos, pose_qos) = (functools.partial(qos, name) for name in (
    "image", "sensor", "keyframe", "pose_graph", "proxy_depth", "rendered", "ack", "status",
    "pose"))


def matching_subscription_qos(node, topic: str, depth: int = 10) -> QoSProfile:
    """A subscription QoS that matches every current publisher of ``topic`` (for tools).

    RELIABLE only if all publishers are reliable, TRANSIENT_LOCAL only if all are
    transient-local; otherwise the weaker policy, which matches both kinds.
    """
    infos = node.get_publishers_info_by_topic(topic)
    rel = bool(infos) and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
    tl = bool(infos) and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    return QoSSpec(rel, tl, depth, "").profile()
