"""rerun_logger: optional visualisation node (needs the optional ``rerun-sdk``, ~790 MB:
``pip install 'splat_slam_ros[viz]'``).

Logs to a .rrd file (``node.rrd``) or streams to a viewer (``node.connect``, a rerun gRPC
URL; empty + no file = spawn a viewer):
  world/camera            the current camera pose (/splat/camera_pose) + pinhole + keyframe image
  world/camera/rendered   rendered colour / depth of the map (/splat/map/rendered_*)
  world/trajectory        the trajectory (/splat/trajectory) as a line strip
  world/map/points        Gaussian centres with colours (/splat/map/points)
  world/map/gaussians     Gaussians as ellipsoids (2 sigma), read from map.ply when the
                          mapper reports ``saved``
Every entity is stamped with the message time on the ``stamp`` timeline.
"""
from __future__ import annotations

import sys

import numpy as np

from .node_common import TOPICS, SplatNode, pointcloud2_to_arrays, run_node

MAX_ELLIPSOIDS = 50_000


def rerun_or_none():
    try:
        import rerun as rr
        return rr
    except ImportError:
        return None


class RerunLogger(SplatNode):
    def __init__(self):
        super().__init__("rerun", {"rrd": "", "connect": "", "loop_closure": True,
                                   "mapping": True})
        rr = rerun_or_none()
        if rr is None:
            self.log.fatal("the rerun logger needs the optional rerun-sdk package "
                           "(pip install 'splat_slam_ros[viz]')")
            raise SystemExit(2)
        self.rr = rr
        rr.init("splat_slam_ros", spawn=False)
        if self.opts["rrd"]:
            rr.save(self.opts["rrd"])
            where = self.opts["rrd"]
        elif self.opts["connect"]:
            (getattr(rr, "connect_grpc", None) or rr.connect)(self.opts["connect"])
            where = self.opts["connect"]
        else:
            rr.spawn()
            where = "a spawned viewer"
        # the map frame of monocular SLAM is the first camera's: x right, y down, z forward
        rr.log("world", rr.ViewCoordinates.RDF, static=True)
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path as PathMsg
        from sensor_msgs.msg import Image, PointCloud2
        from splat_slam_msgs.msg import Keyframe

        from . import qos as Q
        self.subscribe(Keyframe, TOPICS["keyframes"], Q.keyframe_qos(), self._keyframe, "Keyframe")
        self.subscribe(PoseStamped, TOPICS["camera_pose"], Q.pose_qos(), self._pose, "pose")
        self.subscribe(PathMsg, TOPICS["trajectory"], Q.status_qos(), self._path, "Path")
        self.subscribe(Image, TOPICS["rendered_rgb"], Q.rendered_qos(),
                       lambda m, raw: self._image(m, "world/camera/rendered/rgb"), "Image")
        self.subscribe(Image, TOPICS["rendered_depth"], Q.rendered_qos(),
                       lambda m, raw: self._image(m, "world/camera/rendered/depth"), "Image")
        self.subscribe(PointCloud2, TOPICS["points"], Q.status_qos(), self._points, "PointCloud2")
        self.on_events(self._event)
        self.log.info(f"logging to {where}")
        self.publish_event("ready")

    # ------------------------------------------------------------ helpers
    def _time(self, stamp) -> None:
        t = stamp.sec + stamp.nanosec * 1e-9
        rr = self.rr
        try:
            rr.set_time("stamp", timestamp=t)
        except (AttributeError, TypeError):
            rr.set_time_seconds("stamp", t)

    def _transform(self, T):
        return self.rr.Transform3D(translation=np.asarray(T)[:3, 3],
                                   mat3x3=np.asarray(T)[:3, :3])

    # ------------------------------------------------------------ callbacks
    def _keyframe(self, m, raw) -> None:
        from .convert import msg_to_keyframe
        kf = msg_to_keyframe(m)
        rr = self.rr
        self._time(m.header.stamp)
        k = kf.intrinsics
        rr.log(f"world/keyframes/{kf.kf_id}", self._transform(kf.pose))
        rr.log(f"world/keyframes/{kf.kf_id}/image",
               rr.Pinhole(focal_length=[k.fx, k.fy], principal_point=[k.cx, k.cy],
                          width=k.width, height=k.height))
        rr.log("world/camera/image", rr.Pinhole(focal_length=[k.fx, k.fy],
                                                principal_point=[k.cx, k.cy], width=k.width,
                                                height=k.height))
        rr.log("world/camera/image", rr.Image(kf.image))

    def _pose(self, m, raw) -> None:
        from .convert import msg_to_pose
        self._time(m.header.stamp)
        self.rr.log("world/camera", self._transform(msg_to_pose(m.pose)))

    def _path(self, m, raw) -> None:
        if not m.poses:
            return
        self._time(m.header.stamp)
        pts = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                        for p in m.poses], np.float32)
        self.rr.log("world/trajectory", self.rr.LineStrips3D([pts]))

    def _image(self, m, path: str) -> None:
        from .convert import msg_to_image
        self._time(m.header.stamp)
        a = msg_to_image(m)
        if m.encoding == "32FC1":
            self.rr.log(path, self.rr.DepthImage(a, meter=1.0))
        else:
            self.rr.log(path, self.rr.Image(a))

    def _points(self, m, raw) -> None:
        pts, cols = pointcloud2_to_arrays(m)
        self._time(m.header.stamp)
        self.rr.log("world/map/points", self.rr.Points3D(pts, colors=cols, radii=0.003))

    def _event(self, d: dict) -> None:
        if d.get("node") != "mapper" or d.get("event") != "saved" or self.output_dir is None:
            return
        ply = self.output_dir / "map.ply"
        if not ply.is_file():
            return
        from splat_slam_ros.mapping.ply_io import load_gaussians_ply
        g = load_gaussians_ply(ply)
        order = np.argsort(-g["opacity_logits"])[:MAX_ELLIPSOIDS]
        cols = (np.clip(g["colors"][order], 0, 1) * 255).astype(np.uint8)
        rr = self.rr
        rr.log("world/map/gaussians",
               rr.Ellipsoids3D(centers=g["means"][order],
                               half_sizes=2.0 * np.exp(g["log_scales"][order]),
                               quaternions=[rr.Quaternion(xyzw=q) for q in g["quats"][order]],
                               colors=cols))
        self.log.info(f"logged {len(order)} Gaussians as ellipsoids from {ply}")


def main(argv=None) -> int:
    return run_node(RerunLogger, argv)


if __name__ == "__main__":
    sys.exit(main())
