"""splat-slam-launch: start the Splat-SLAM ROS 2 node graph (``launch`` is not on PyPI).

    splat-slam-launch --bag BAG_DIR --out DIR [--config FILE] [--mode lockstep|realtime]
                      [--rate R] [--rerun FILE.rrd] [--set KEY=VALUE ...]
    splat-slam-launch --out DIR [--config FILE] [--set ros.image_topic=/cam/image ...]
    splat-slam-launch --camera SOURCE [--camera-info CAM.yaml] [--camera-rate HZ]
                      [--camera-jpeg Q] --out DIR

Each node runs as its own process with the project's DDS profile (ros_env) and a prefix on
every log line. With ``--bag`` the bag player feeds the graph; at the end of the bag the
graph finalises itself (final global BA, final map refinement) and the outputs land in
``--out``: trajectory_full.txt, trajectory_keyframes.txt, map.ply, renders/, metrics.json
(ATE when the bag has ground truth, keyframe PSNR/SSIM, frames/s, per-node CPU and RSS).
Without ``--bag`` the graph runs on live topics until Ctrl-C; the first Ctrl-C finalises and
saves (when ``--out`` is given), a second one stops at once.

Supervision: a node that dies is restarted (``--max-restarts``) and resumes from its
crash-safe store in ``OUT/state/<node>``: the tracker from its last checkpoint (keyframe ids
and update numbers continue; the player plays again from the frame after it), depth,
loop_closure (with its loop edges) and mapper from what they stored, the player from its last
acknowledged frame (``OUT/state/player/progress.json``). ``--resume`` after the whole graph
was killed continues the same run from these stores. A node that exits with status 2 stopped
on a configuration error (e.g. a ``depth.mono_model`` that is not a model): no restart, the
launcher stops the graph and names the node and its error.

Exit status: 0 done; 2 configuration or usage error (of the launcher or of a node); 3 no result
(no keyframe, or an empty map); 1 any other failure (a node died more than ``--max-restarts``
times, finalisation timed out, the evaluation against the bag's ground truth failed:
metrics.json then holds ``evaluation_error``; a bag without ground truth is no failure:
``evaluation_skipped``); 130 interrupted.

End-of-stream / finalisation protocol (graph events on /splat/graph_events; the rules are
the stage roles' in splat_slam_ros/roles.py, the same the in-process coordinator runs):
  player  end_of_stream -> tracker finalize() (local BA), ``finalized`` {last_seq}
  -> loop_closure (after applying the tracker's updates up to last_seq) finalize() (final
     global BA), ``finalized`` {last_seq}
  -> tracker applies those updates, writes the trajectories, ``saved``
  -> depth (after both update streams) ``finalized`` {digest: last ProxyDepth revision per kf}
  -> mapper (after taking every revision of the digest) final_refine(), writes map.ply /
     renders / mapper_metrics.json, ``saved``
  -> launcher: metrics.json, summary, clean stop.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

from ..node_options import NodeOptionError, node_overrides, ros_param
from ..tool_runner import usage_error
from .launch_proc import Child
from .launch_results import finish

NODE_MODULES = {
    "tracker": "splat_slam_nodes.tracker_node",
    "depth": "splat_slam_nodes.depth_node",
    "loop_closure": "splat_slam_nodes.loop_closure_node",
    "mapper": "splat_slam_nodes.mapper_node",
    "player": "splat_slam_nodes.tools.bag_player",
    "camera": "splat_slam_nodes.tools.camera_node",
    "rerun": "splat_slam_nodes.tools.rerun_logger",
}
RESUMABLE = ("tracker", "depth", "loop_closure", "mapper", "player")
REALTIME_KEEP_UP = 0.8      # mapping.keep_up on realtime input unless the config sets one
# realtime input, unless the config sets them: the first keyframe's (1.5 s: keyframes
# queue behind it; 4 s gave the same PSNR and twice the map lag) and the final
# refinement's wall seconds, the steps of a keyframe while input waits, and steps on a 1/2
# pixel lattice (half the cost; docs/mapping.md "Lattice steps"), so the map keeps pace and is
# done soon after the stream (background steps refine it while the mapper has
# time; docs/live-camera.md "What the graph does on live input")
REALTIME_MAPPING = {"budget_s_first": 1.5, "min_iters_per_keyframe": 1, "final_refine_s": 8.0,
                    "final_deadline_s": 8.0, "step_subsample": 2, "refine_subsample": 2}
# niced on realtime input; not the depth node: the mapper waits for its proxy depth, and niced
# too it finalised about 5 s after the stream, leaving the mapper's refinement no time
BACKGROUND_NODES = ("mapper", "loop_closure", "rerun")
FINISHED_MARK = "FINISHED"  # in OUT/state once a run finished: a new run may discard it


class LaunchError(Exception):
    """User-facing error: ``error: ...``, exit 2."""


# --------------------------------------------------------------------------- launcher
class Launcher:
    def __init__(self, args, out=sys.stdout):
        self.args = args
        self.out = out
        self.children: Dict[str, Child] = {}
        self.events: List[dict] = []
        self.stop_requested = 0
        self.failed: Optional[str] = None
        self.t0 = time.monotonic()
        self.t_play = None
        self.t_eos = None
        self.t_mapped = None
        self.keep_up_note = ""
        self.services = None                     # /splat/save_map, /splat/load_map (init_ros)

    # ------------------------------------------------------------ setup
    def plan(self) -> None:
        from splat_slam_ros.cli.common import parse_overrides
        from splat_slam_ros.config import ConfigError, load_config
        from splat_slam_ros.ros_env import RosEnvError, ros_environment
        a = self.args
        try:
            sets = parse_overrides(a.set)       # node.* keys: the nodes' own, checked below
            self.overrides = {k: v for k, v in sets.items() if not k.startswith("node.")}
            self.cfg = load_config(a.config, self.overrides, preset=a.preset)
            self.config_file = a.config
            if a.preset:                 # the nodes read one file: preset + --config merged
                import tempfile
                from splat_slam_ros.config import dump_config
                fd, name = tempfile.mkstemp(prefix=f"splat_{a.preset}_", suffix=".yaml")
                os.close(fd)
                self.config_file = str(dump_config(load_config(a.config, preset=a.preset), name))
        except ConfigError as e:
            raise LaunchError(str(e)) from None
        from .launch_net import NetworkArgError, apply_network
        try:
            self.dds_range = apply_network(a.network)   # before the env is built (--network)
            self.env = ros_environment()
        except (RosEnvError, NetworkArgError) as e:
            raise LaunchError(str(e)) from None
        self.env.setdefault("PYTHONUNBUFFERED", "1")
        self.out_dir = Path(a.out).resolve() if a.out else None
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self._check_state()
        from . import launch_map
        try:
            self.session = launch_map.plan(a, self.cfg, self.overrides, self.out_dir)
        except launch_map.LoadMapError as e:
            raise LaunchError(str(e)) from None
        self.intrinsics_file = None     # --camera-info on topics or a bag: the tracker's own
        if a.camera_info and not a.camera:
            from .camera_node import CameraError, calibration_yaml
            try:
                self.intrinsics_file = calibration_yaml(a.camera_info)
            except CameraError as e:
                raise LaunchError(str(e)) from None
        self.bag = None
        if a.bag:
            from .bag_player import BagReader, PlayerError, graph_topics
            try:
                self.bag = BagReader(a.bag)
            except PlayerError as e:
                raise LaunchError(str(e)) from None
            try:
                self.bag_topics = graph_topics(self.bag, a.bag, self.overrides,
                                               self.intrinsics_file is not None)
            except PlayerError as e:
                raise LaunchError(str(e)) from None
        self._realtime_keep_up()
        tc = self.cfg.tracking
        localize = bool(a.localize)     # --load-map RUN --localize: the tracker alone
        self.with_loop = bool(tc.loop_closure or tc.global_ba) and not (a.no_loop_closure or
                                                                         localize)
        self.with_mapping = not (a.tracking_only or localize)
        ec = self.cfg.evaluation
        if self.with_mapping and (ec.lpips_backbone or ec.lpips_weights):
            from splat_slam_ros.evaluation.run import check_lpips_config
            try:
                check_lpips_config(self.cfg)      # a missing / invalid file: before the run
            except ConfigError as e:
                raise LaunchError(str(e)) from None
        self.nodes = ["tracker"] + (["loop_closure"] if self.with_loop else []) + \
            (["depth", "mapper"] if self.with_mapping else [])
        from .launch_net import select_nodes
        try:
            self.local_nodes = select_nodes(a.nodes, self.nodes)   # --nodes: this host's share
            self.node_sets = node_overrides(sets, self.input_waits_for())
        except (NetworkArgError, NodeOptionError) as e:
            raise LaunchError(str(e)) from None
        if self.bag is not None and "node.input_qos" in self.node_sets["tracker"]:
            raise LaunchError("node.input_qos: with --bag the tracker takes the player's "
                              "reliable input (the setting is for live topics)")
        if a.camera:
            from .camera_node import CameraError, camera_topic, check_camera_args
            try:
                check_camera_args(a.camera, a.camera_info)
                camera_topic(a.camera_jpeg, self.cfg, self.overrides)
            except CameraError as e:
                raise LaunchError(str(e)) from None

    def realtime(self) -> bool:
        """Realtime input: ``--mode realtime``, live topics or ``--camera`` (not lockstep)."""
        return self.args.mode == "realtime" or self.bag is None

    def _check_state(self) -> None:
        """``OUT/state`` of an earlier run: kept with ``--resume``; discarded when that run
        finished (nothing to continue) or with ``--fresh``; else an error, never a silent loss
        of the state that ``--resume`` needs after a crash."""
        st, a = self.out_dir / "state", self.args
        if a.resume and a.fresh:
            raise LaunchError("--resume and --fresh exclude each other")
        if not st.exists() or a.resume:
            return
        if not (a.fresh or (st / FINISHED_MARK).exists()):
            raise LaunchError(f"{st} holds the crash-safe state of a run that did not finish: "
                              "--resume continues that run, --fresh discards it and starts "
                              "over (or choose another --out)")
        import shutil
        shutil.rmtree(st)

    def mark_finished(self) -> None:
        """The run finished (every stage saved): its state has nothing left to resume."""
        st = self.out_dir / "state"
        st.mkdir(parents=True, exist_ok=True)
        (st / FINISHED_MARK).write_text(f"{time.time():.3f}\n")

    def _realtime_keep_up(self) -> None:
        """Realtime input (``--mode realtime``, live topics, ``--camera``): the camera sets the
        pace, so the mapper's budgets are wall-clock (``mapping.time_budget``) and it keeps
        pace with the stream (``mapping.keep_up`` REALTIME_KEEP_UP), unless the configuration
        or ``--set`` chose otherwise; it skips optimisation steps, never keyframes. Lockstep
        replay keeps the step budgets: the same map whatever the load."""
        if not self.realtime():
            return
        notes = []
        m = self.cfg.mapping
        if not m.time_budget and "mapping.time_budget" not in self.overrides:
            self.overrides["mapping.time_budget"] = True
            m.time_budget = True
            notes.append("mapping.time_budget on (wall-clock budgets; --set "
                         "mapping.time_budget=false keeps the step budgets)")
        if m.time_budget and m.keep_up <= 0 and "mapping.keep_up" not in self.overrides:
            self.overrides["mapping.keep_up"] = REALTIME_KEEP_UP
            m.keep_up = REALTIME_KEEP_UP
            notes.append(f"mapping.keep_up {REALTIME_KEEP_UP} (the mapper keeps pace; --set "
                         "mapping.keep_up=0 turns it off)")
        from splat_slam_ros.config import MappingConfig
        defaults = MappingConfig()
        for key, cap in REALTIME_MAPPING.items():
            if m.time_budget and getattr(m, key) == getattr(defaults, key) and \
                    f"mapping.{key}" not in self.overrides:
                self.overrides[f"mapping.{key}"] = cap
                setattr(m, key, cap)
                notes.append(f"mapping.{key} {cap}")
        if notes:
            self.keep_up_note = "realtime input: " + ", ".join(notes)

    def _node_args(self, name: str) -> List[str]:
        a = self.args
        py = [sys.executable, "-m", NODE_MODULES[name]]
        p = ["--ros-args", "-r", f"__node:={name}"]
        mine = self.node_sets.get(name, {})       # --set node.KEY=V: the user's over ours

        def param(k, v):
            if k not in mine:
                p.extend(ros_param(k, v))
        if self.config_file:
            param("config_file", str(Path(self.config_file).resolve()))
        for k, v in self.overrides.items():
            param(k, v)
        if self.bag is not None:
            param("use_sim_time", True)
        if self.out_dir is not None:
            param("node.output_dir", str(self.out_dir))
            param("node.state_dir", str(self.out_dir / "state" / name))
        param("node.loop_closure", self.with_loop)
        param("node.mapping", self.with_mapping)
        if name in ("tracker", "rerun"):          # the rerun logger records the input too
            if self.bag is not None:
                bt = self.bag_topics
                if "ros.image_topic" not in self.overrides:
                    param("ros.image_topic", bt["image_out"])
                if "ros.camera_info_topic" not in self.overrides and bt["info_out"]:
                    param("ros.camera_info_topic", bt["info_out"])
            if name == "tracker" and self.intrinsics_file:
                param("node.intrinsics_file", self.intrinsics_file)
            if self.bag is not None and name == "tracker":
                param("node.input_qos", "reliable")
                param("node.max_queue", 0 if a.mode == "lockstep" else 1)
        from .launch_map import node_params
        for k, v in node_params(self.session, name).items():
            param(k, v)
        if name == "mapper" and a.allow_reset:
            param("node.allow_reset", True)          # /splat/map/reset is off by default
        if name == "rerun":
            if a.rerun:
                param("node.rrd", str(Path(a.rerun).resolve()))
            if a.rerun_connect:
                param("node.connect", a.rerun_connect)
        for k, v in mine.items():
            p.extend(ros_param(k, v))
        return py + p

    def input_waits_for(self) -> List[str]:
        """The nodes whose ``ready`` the player or camera waits for before the first frame:
        the graph's and the rerun logger when one records (niced on realtime input, it
        starts last and would miss the first frames)."""
        return self.nodes + (["rerun"] if self.args.rerun or self.args.rerun_connect else [])

    def start_all(self) -> None:
        from .bag_player import launch_args as player_args
        from .camera_node import launch_args
        names = list(self.local_nodes) + (["rerun"] if self.args.rerun or self.args.rerun_connect
                                    else []) + \
            (["player"] if self.bag is not None else []) + (["camera"] if self.args.camera else [])
        w = max(len(n) for n in names)
        for n in names:
            if n == "player":
                args = player_args(self.args, self.bag_topics, self.nodes, self.input_waits_for(),
                                   self.out_dir)
            elif n == "camera":
                args = launch_args(self.args, self.cfg, self.input_waits_for(),
                                   self.out_dir is not None)
            else:
                args = self._node_args(n)
            c = Child(n, args, self.env, self.out, w, nice=self.nice_of(n))
            self.children[n] = c
        for n in names:
            self.children[n].start()
        self.say(f"started {', '.join(names)} (ROS_DOMAIN_ID={self.env.get('ROS_DOMAIN_ID', '0')}, "
                 f"network {self.dds_range})")
        if self.keep_up_note:
            self.say(self.keep_up_note)
        if self.session is not None:
            s = self.session
            self.say(f"{'localizing' if s['localize'] else 'extending the map'} in the session "
                     f"of {s['run']} ({s['keyframes']} keyframes)" +
                     (f"; {', '.join(s['notes'])}" if s["notes"] else ""))

    def nice_of(self, name: str) -> int:
        """OS priority of a node: on realtime input the tracker (and the input) get the CPU
        first, the stages that work per keyframe run ``--background-nice`` lower."""
        if self.realtime() and name in BACKGROUND_NODES:
            return int(self.args.background_nice)
        return 0

    def say(self, text: str) -> None:
        self.out.write(f"[launch] {text}\n")
        self.out.flush()

    # ------------------------------------------------------------ ROS side
    def init_ros(self) -> None:
        from splat_slam_ros.ros_env import apply_ros_environment
        apply_ros_environment()
        import rclpy
        from std_msgs.msg import String

        from ..node_common import TOPICS, events_qos
        rclpy.init(args=["splat_slam_launch"], signal_handler_options=_no_signal_handlers())
        self.rclpy = rclpy
        self.node = rclpy.create_node("launch", enable_rosout=False)
        self.String = String
        self.ev_pub = self.node.create_publisher(String, TOPICS["events"], events_qos())
        self.node.create_subscription(String, TOPICS["events"], self._on_event, events_qos())
        if self.out_dir is not None:             # /splat/save_map, /splat/load_map
            from .launch_services import LaunchServices
            self.services = LaunchServices(self)

    def _on_event(self, m) -> None:
        from ..node_common import graph_event
        d = graph_event(m)
        if d is None:
            return
        self.events.append(d)
        ev, node = d.get("event"), d.get("node")
        if self.services is not None:
            self.services.on_event(d)
        if node == "player" and ev == "start" and self.t_play is None:
            self.t_play = time.monotonic()
        if ev == "end_of_stream" and self.t_eos is None:
            self.t_eos = time.monotonic()
        if node == "mapper" and ev == "saved" and self.t_mapped is None:
            self.t_mapped = time.monotonic()       # the map is done: refined and written
        if ev in ("finalized", "saved"):
            self.say(f"{node} {ev}")
        if ev == "relocalised":
            self.say(f"{node}: frame {d.get('frame')} relocalised in the loaded map (keyframe "
                     f"{d.get('keyframe')})" + ("" if d.get("first") else ", again"))

    def has_event(self, node: str, event: str) -> Optional[dict]:
        for d in reversed(self.events):
            if d.get("node") == node and d.get("event") == event:
                return d
        return None

    def publish_eos(self) -> None:
        d = {"node": "launch", "event": "end_of_stream", "t": time.time(), "frames": -1}
        self.ev_pub.publish(self.String(data=json.dumps(d)))

    # ------------------------------------------------------------ main loop
    def supervise(self) -> int:
        a = self.args
        last_sample = 0.0
        eos_sent = False
        while True:
            self.rclpy.spin_once(self.node, timeout_sec=0.25)
            now = time.monotonic()
            if now - last_sample > 0.5:
                last_sample = now
                for c in self.children.values():
                    c.sample()
            if self.stop_requested >= 2 or (self.stop_requested == 1 and
                                            (self.bag is not None or self.out_dir is None)):
                self.say("stopping (interrupted)")
                return 130
            if self.stop_requested == 1 and not eos_sent:
                self.say("finalising and saving (Ctrl-C again to stop at once)")
                self.publish_eos()
                eos_sent = True
            for name, c in self.children.items():
                if c.alive() or c.expected_exit:
                    continue
                rc = c.proc.returncode
                if name in ("player", "camera") and rc == 0:
                    c.expected_exit = True
                    continue
                if rc == 2:                       # configuration error: a restart cannot help
                    if c.thread is not None:
                        c.thread.join(timeout=2)  # its last lines (the reason)
                    why = (c.error or "no message").replace("configuration error: ", "", 1)
                    self.failed = (f"the {name} node stopped on a configuration error "
                                   f"(exit status 2): {why}")
                    self.say(self.failed)
                    return 2
                if name in RESUMABLE and self.out_dir is not None and c.restarts < a.max_restarts:
                    c.restarted()
                    self.say(f"{name} died (exit status {rc}); restarting it "
                             f"({c.restarts}/{a.max_restarts}), it resumes from "
                             f"{self.out_dir / 'state' / name}")
                    c.start()
                    continue
                self.failed = f"{name} died unexpectedly (exit status {rc})"
                self.say(self.failed)
                return 1
            if self.finished():
                return 0
            if self.t_eos is not None and now - self.t_eos > a.final_timeout:
                self.failed = f"finalisation did not complete within {a.final_timeout:g} s"
                self.say(self.failed)
                return 1

    def finished(self) -> bool:
        if self.t_eos is None or self.out_dir is None:
            return False
        need = ["tracker"] + (["mapper"] if self.with_mapping else [])
        return all(self.has_event(n, "saved") for n in need)

    def stop_children(self) -> None:
        for sig, wait in ((signal.SIGINT, 15.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            live = [c for c in self.children.values() if c.alive()]
            if not live:
                break
            for c in live:
                c.expected_exit = True
                c.sample()
                c.signal(sig)
            t0 = time.monotonic()
            while time.monotonic() - t0 < wait and any(c.alive() for c in live):
                time.sleep(0.05)
        for c in self.children.values():
            if c.thread is not None:
                c.thread.join(timeout=2)


def _no_signal_handlers():
    try:
        from rclpy.signals import SignalHandlerOptions
        return SignalHandlerOptions.NO
    except ImportError:  # pragma: no cover
        return None


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="splat-slam-launch", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", help="rosbag2 (MCAP) to play; without it: live topics")
    ap.add_argument("--out", help="output directory (outputs, crash-safe node state)")
    ap.add_argument("--config", help="SLAM config YAML (config/*.yaml)")
    ap.add_argument("--preset", metavar="NAME", help="start from the shipped config/NAME.yaml "
                    "(e.g. paper); --config and --set apply on top")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config value, e.g. --set ros.image_topic=/cam/image_raw, "
                         "or a node's own parameter, e.g. --set node.max_backlog=120")
    ap.add_argument("--mode", choices=["lockstep", "realtime"], default="lockstep",
                    help="bag playback: lockstep (no frame dropped, default) or realtime")
    ap.add_argument("--rate", type=float, default=1.0, help="realtime playback speed factor")
    ap.add_argument("--rerun", metavar="FILE.rrd", help="also record the run to a rerun .rrd file "
                    "(needs rerun-sdk: the [rerun] extra)")
    ap.add_argument("--rerun-connect", metavar="URL", help="also stream to a rerun viewer, e.g. "
                    "rerun+http://HOST:9876/proxy")
    ap.add_argument("--max-frames", type=int, default=0, help="play at most N frames")
    ap.add_argument("--loop-bag", type=int, default=1, metavar="N",
                    help="play the bag N times in a row, shifted in time (long soak runs)")
    ap.add_argument("--camera", metavar="SOURCE", help="start splat-slam-camera on SOURCE (device "
                    "index, /dev/videoN, video file or image folder) instead of a bag")
    ap.add_argument("--camera-info", metavar="YAML", help="the camera's calibration (ROS "
                    "camera_info / OpenCV / intrinsics YAML): what --camera publishes; on live "
                    "topics or a bag, the tracker's while the camera publishes none (or an "
                    "uncalibrated one)")
    ap.add_argument("--camera-rate", type=float, default=0.0, metavar="HZ",
                    help="--camera frame rate (default: the source's own)")
    ap.add_argument("--camera-jpeg", type=int, default=0, metavar="Q", help="--camera publishes "
                    "JPEG CompressedImage at quality Q on ros.image_topic/compressed")
    ap.add_argument("--network", choices=["localhost", "subnet"], default=None,
                    help="DDS discovery range: localhost (default, this machine only) or subnet "
                         "(every interface, for nodes on several hosts; sets SPLAT_SLAM_DDS_RANGE)")
    ap.add_argument("--nodes", metavar="LIST", help="start only these graph nodes, e.g. "
                    "tracker,loop_closure (the others run on another host, --network subnet)")
    ap.add_argument("--allow-reset", action="store_true",
                    help="enable the /splat/map/reset service (disabled by default)")
    ap.add_argument("--tracking-only", action="store_true", help="no depth / mapper nodes")
    ap.add_argument("--load-map", metavar="RUN", help="the saved session of an earlier run "
                    "(RUN/session/, written by splat-slam-run and splat-slam-launch): extend its "
                    "map, or with --localize track in it; the tracker relocalises first")
    ap.add_argument("--localize", action="store_true", help="with --load-map: localize-only "
                    "(the tracker alone, the map read-only; poses in the loaded map's frame)")
    ap.add_argument("--no-loop-closure", action="store_true", help="no loop_closure node")
    ap.add_argument("--background-nice", type=int, default=10, metavar="N",
                    help="realtime input: run the mapper, loop-closure (and rerun) nodes "
                         "at OS priority +N so that the tracker gets the CPU first (default 10; "
                         "0 = off; lockstep replay never changes priorities)")
    ap.add_argument("--max-restarts", type=int, default=3,
                    help="restarts of a resumable node before giving up (default 3)")
    ap.add_argument("--fresh", action="store_true",
                    help="discard the crash-safe state an unfinished run left in OUT/state and "
                         "start over (without it, such a state stops the launcher: --resume "
                         "or --fresh; the state of a finished run is replaced silently)")
    ap.add_argument("--resume", action="store_true",
                    help="continue the run in OUT from its crash-safe state (after the graph "
                         "was killed); default: a new run")
    ap.add_argument("--start-timeout", type=float, default=180.0,
                    help="seconds the player waits for the nodes to be ready")
    ap.add_argument("--final-timeout", type=float, default=3600.0,
                    help="seconds allowed for finalisation after the end of the bag")
    return ap


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    if usage_error((args.bag and args.camera,
                    "--camera and --bag exclude each other (one input at a time)"),
                   (args.bag and not args.out, "--bag needs --out (where the outputs go)"),
                   (args.rate <= 0, "--rate must be positive"),
                   (args.loop_bag < 1, "--loop-bag must be at least 1"),
                   (args.camera_jpeg and not args.camera, "--camera-jpeg needs --camera")):
        return 2
    from splat_slam_ros.report.recording import WarningTee
    L = Launcher(args, out=WarningTee(sys.stdout))        # keeps warnings for the report
    try:
        L.plan()
    except LaunchError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2

    def on_signal(signum, frame):
        L.stop_requested += 1
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    rc = 1
    try:
        L.init_ros()
        L.start_all()
        rc = L.supervise()
        end = time.monotonic()
        if rc == 0 and L.out_dir is not None:
            rc = finish(L, end)
        elif rc == 2:                               # a node's configuration error
            print(f"error: {L.failed}", file=sys.stderr)
    finally:
        L.stop_children()
        for f in (L.intrinsics_file, L.config_file if args.preset else None):
            if f:                                   # the temporary files of plan()
                Path(f).unlink(missing_ok=True)
        try:
            if L.services is not None:
                L.services.close()
            L.node.destroy_node()
        except Exception:
            pass
        try:
            L.rclpy.try_shutdown()
        except Exception:
            pass
        for s, h in old.items():
            signal.signal(s, h)
    return rc


if __name__ == "__main__":
    sys.exit(main())
