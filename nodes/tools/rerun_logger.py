"""rerun_logger: visualisation node — records the running graph with rerun (rerun-sdk: the
optional [rerun] extra, ``pip install '.[rerun]'``).

Writes a .rrd file (``node.rrd``) and/or streams to a viewer (``node.connect``, a rerun gRPC
URL such as ``rerun+http://HOST:9876/proxy``); with neither it spawns a local viewer.
Entities (``stamp`` timeline = message time; ``world`` uses the SLAM map frame, RDF axes):

  world/camera                 current camera pose (/splat/camera_pose, Transform3D)
  world/camera/image           pinhole (from camera_info) + input image (every
                               ``node.image_every``-th frame, JPEG-compressed)
  world/trajectory             the camera trajectory (/splat/trajectory) as a line strip
  world/keyframes/<id>         keyframe poses (moved again by loop closure / global BA
                               updates) with a pinhole and the keyframe image
  rendered/rgb, rendered/depth the map rendered at the latest keyframe (/splat/map/rendered_*)
  world/map/points             Gaussian centres with colours (/splat/map/points)
  world/map/gaussians          Gaussians as ellipsoids (2 sigma), read from map.ply when the
                               mapper reports ``saved``
"""
from __future__ import annotations

import sys

import numpy as np

from splat_slam_ros.extras import MissingExtra

from ..node_common import TOPICS, SplatNode, pointcloud2_to_arrays, run_node
from ..node_options import NODE_OPTIONS

MAX_ELLIPSOIDS = 50_000
rr = None      # the rerun module: rerun-sdk is the optional [rerun] extra, see _import_rerun


def _import_rerun():
    """Import rerun-sdk on use (every other command runs without it)."""
    global rr
    if rr is None:
        try:
            import rerun
        except ImportError as e:
            raise MissingExtra("rerun", "the rerun logger node", e) from None
        rr = rerun
    return rr


class RerunLogger(SplatNode):
    def __init__(self):
        super().__init__("rerun", NODE_OPTIONS["rerun"])
        try:
            _import_rerun()
        except MissingExtra as e:
            self.log.fatal(str(e))
            raise SystemExit(2)
        rr.init("splat_slam_ros", spawn=False)
        sinks, where = [], []
        if self.opts["rrd"]:
            sinks.append(rr.FileSink(self.opts["rrd"]))
            where.append(self.opts["rrd"])
        if self.opts["connect"]:
            sinks.append(rr.GrpcSink(self.opts["connect"]))
            where.append(self.opts["connect"])
        if sinks:
            rr.set_sinks(*sinks)
        else:
            rr.spawn()
            where.append("a spawned viewer")
        # the map frame of monocular SLAM is the first camera's: x right, y down, z forward
        rr.log("world", rr.ViewCoordinates.RDF, static=True)
        from geometry_msgs.msg import PoseStamped
        from nav_msgs.msg import Path as PathMsg
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        from splat_slam_msgs.msg import Keyframe, PoseGraphUpdate

        from .. import qos as Q
        self.n_images = 0
        self.info = None
        self.subscribe(Keyframe, TOPICS["keyframes"], Q.keyframe_qos(), self._keyframe, "Keyframe")
        self.subscribe(PoseGraphUpdate, TOPICS["updates"], Q.pose_graph_qos(), self._update,
                       "PoseGraphUpdate")
        self.subscribe(PoseStamped, TOPICS["camera_pose"], Q.pose_qos(), self._pose, "pose")
        self.subscribe(PathMsg, TOPICS["trajectory"], Q.status_qos(), self._path, "Path")
        self.subscribe(CameraInfo, self.cfg.ros.camera_info_topic, Q.sensor_qos(), self._info,
                       "CameraInfo")
        self.subscribe_image(self.cfg.ros.image_topic, Q.sensor_qos(), self._input,
                             lambda: self.n_images > 0)
        self.subscribe(Image, TOPICS["rendered_rgb"], Q.rendered_qos(),
                       lambda m, raw: self._image(m, "rendered/rgb"), "Image")
        self.subscribe(Image, TOPICS["rendered_depth"], Q.rendered_qos(),
                       lambda m, raw: self._image(m, "rendered/depth"), "Image")
        self.subscribe(PointCloud2, TOPICS["points"], Q.status_qos(), self._points, "PointCloud2")
        self.on_events(self._event)
        self.log.info(f"logging to {' and '.join(where)}")
        self.publish_event("ready")

    # ------------------------------------------------------------ helpers
    @staticmethod
    def _time(stamp) -> None:
        rr.set_time("stamp", timestamp=stamp.sec + stamp.nanosec * 1e-9)

    @staticmethod
    def _transform(T):
        T = np.asarray(T)
        return rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])

    @staticmethod
    def _pinhole(k):
        return rr.Pinhole(focal_length=[k.fx, k.fy], principal_point=[k.cx, k.cy],
                          width=k.width, height=k.height)

    def _rgb(self, img):
        q = int(self.opts["jpeg_quality"])
        return rr.Image(img).compress(jpeg_quality=q) if q > 0 else rr.Image(img)

    # ------------------------------------------------------------ callbacks
    def _keyframe(self, m, raw) -> None:
        from ..convert import msg_to_keyframe
        kf = msg_to_keyframe(m)
        self._time(m.header.stamp)
        path = f"world/keyframes/{kf.kf_id}"
        rr.log(path, self._transform(kf.pose))
        rr.log(f"{path}/image", self._pinhole(kf.intrinsics))
        rr.log(f"{path}/image", self._rgb(kf.image))

    def _update(self, m, raw) -> None:
        from ..convert import msg_to_update
        ev = msg_to_update(m)
        self._time(m.header.stamp)
        for kid, T in zip(ev.kf_ids, ev.poses):
            rr.log(f"world/keyframes/{int(kid)}", self._transform(T))

    def _pose(self, m, raw) -> None:
        from ..convert import msg_to_pose
        self._time(m.header.stamp)
        rr.log("world/camera", self._transform(msg_to_pose(m.pose)))

    def _info(self, m, raw) -> None:
        from ..convert import camera_info_to_intrinsics
        k = camera_info_to_intrinsics(m)
        key = (k.fx, k.fy, k.cx, k.cy, k.width, k.height)
        if key != self.info:
            self.info = key
            self._time(m.header.stamp)
            rr.log("world/camera/image", self._pinhole(k))

    def _input(self, m, raw) -> None:
        from ..convert import msg_to_rgb
        every = max(1, int(self.opts["image_every"]))
        self.n_images += 1
        if (self.n_images - 1) % every:
            return
        self._time(m.header.stamp)
        rr.log("world/camera/image", self._rgb(msg_to_rgb(m)))

    def _path(self, m, raw) -> None:
        if not m.poses:
            return
        self._time(m.header.stamp)
        pts = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                        for p in m.poses], np.float32)
        rr.log("world/trajectory", rr.LineStrips3D([pts]))

    def _image(self, m, path: str) -> None:
        from ..convert import msg_to_image
        self._time(m.header.stamp)
        a = msg_to_image(m)
        if m.encoding == "32FC1":
            rr.log(path, rr.DepthImage(a, meter=1.0))
        else:
            rr.log(path, rr.Image(a))

    def _points(self, m, raw) -> None:
        pts, cols = pointcloud2_to_arrays(m)
        self._time(m.header.stamp)
        rr.log("world/map/points", rr.Points3D(pts, colors=cols, radii=0.003))

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
        rr.log("world/map/gaussians",
               rr.Ellipsoids3D(centers=g["means"][order],
                               half_sizes=2.0 * np.exp(g["log_scales"][order]),
                               quaternions=[rr.Quaternion(xyzw=q) for q in g["quats"][order]],
                               colors=cols))
        self.log.info(f"logged {len(order)} Gaussians as ellipsoids from {ply}")

    def spin(self) -> int:
        rc = super().spin()
        rec = rr.get_global_data_recording()
        if rec is not None:
            rec.flush()                 # everything on disk / sent before the process ends
        return rc


def main(argv=None) -> int:
    return run_node(RerunLogger, argv)


if __name__ == "__main__":
    sys.exit(main())
