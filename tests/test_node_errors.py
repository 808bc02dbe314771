"""Configuration errors stop a node (exit status 2, one line) and the launcher with it; a
malformed message is only dropped and counted; an evaluation that fails at the end of a
launcher run is an error (exit 1, ``evaluation_error``), a bag without ground truth is not."""
import json
import subprocess
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from test_graph_support import (PY, TINY_TRACKING_CFG, isolated_env, need_ros, run_launch,
                                write_tiny_bag)

from splat_slam_ros.config import ConfigError, SlamConfig
from splat_slam_ros.io.sensor_codec import ConversionError


def not_a_model(tmp_path, sidecar: bool = True):
    """A file named like an ONNX model that holds text, with a valid sidecar (so that only
    loading the network can tell)."""
    p = tmp_path / "not_a_model.onnx"
    p.write_text("this is not a model\n")
    if sidecar:
        (tmp_path / "not_a_model.onnx.yaml").write_text("output: disparity\n")
    return p


# --------------------------------------------------------------------------- node worker
class _Log:
    def __init__(self):
        self.lines = []

    def fatal(self, text):
        self.lines.append(("fatal", text))

    def error(self, text):
        self.lines.append(("error", text))


class _Owner:
    name = "t"

    def __init__(self):
        self.log = _Log()
        self.warned = []

    def warn_throttled(self, key, text, error=True):
        self.warned.append(text)


@pytest.fixture
def worker(monkeypatch):
    """A node Worker on a stub owner; rclpy's context calls are stubbed (no ROS here)."""
    rclpy = pytest.importorskip("rclpy", reason="the node worker needs rclpy (./run.sh setup)")
    from splat_slam_nodes.node_common import Worker
    shut = []
    monkeypatch.setattr(rclpy, "ok", lambda *a, **k: not shut)
    monkeypatch.setattr(rclpy, "try_shutdown", lambda *a, **k: shut.append(1))
    w = Worker(_Owner())
    w.shut = shut
    yield w
    w.stop()


def _run_jobs(w, *jobs):
    """Submit ``jobs``, then a marker; wait for the marker or the worker's end."""
    done = threading.Event()
    for j in jobs:
        w.submit(j)
    w.submit(done.set)
    w.start()
    t0 = time.monotonic()
    while not done.is_set() and w.thread.is_alive() and time.monotonic() - t0 < 20:
        time.sleep(0.02)
    return done.is_set()


def test_a_malformed_message_is_dropped_and_counted_the_worker_goes_on(worker):
    ran = []

    def malformed():
        raise ConversionError("image data has 100 bytes, 9216 expected")
    assert _run_jobs(worker, malformed, lambda: ran.append(1), malformed)   # it kept running
    assert ran == [1] and worker.dropped == 2 and worker.fatal_rc == 0 and not worker.shut
    assert "image data has 100 bytes" in worker.owner.warned[0]
    assert worker.thread.is_alive()


def test_an_error_in_the_finalisation_stops_the_worker_with_status_1(worker):
    """An error in an ordinary job is logged and the worker goes on; one in the node's
    finalisation (``submit_final``) stops it with status 1: nothing would save the run's
    results after it, and the launcher would wait for them."""
    ran = []

    def broken():
        raise AttributeError("'Localizer' object has no attribute 'keyframe_summary'")
    assert _run_jobs(worker, broken, lambda: ran.append(1))          # ordinary: goes on
    assert ran == [1] and worker.fatal_rc == 0 and worker.owner.log.lines[-1][0] == "error"
    done = threading.Event()
    worker.submit_final(broken)
    worker.submit(done.set)
    worker.thread.join(5)
    assert not worker.thread.is_alive() and not done.is_set()
    assert worker.fatal_rc == 1 and worker.shut
    kind, text = worker.owner.log.lines[-1]
    assert kind == "fatal" and "finalisation failed (AttributeError" in text


def test_a_configuration_error_stops_the_worker_with_status_2(worker):
    ran = []

    def bad_config():
        raise ConfigError("depth.mono_fit_space must be auto, depth or disparity, got 'x'")
    assert not _run_jobs(worker, bad_config, lambda: ran.append(1))
    worker.thread.join(5)
    assert worker.fatal_rc == 2 and worker.shut and ran == [] and worker.dropped == 0
    kind, text = worker.owner.log.lines[-1]
    assert kind == "fatal" and "\n" not in text
    assert text == "configuration error: depth.mono_fit_space must be auto, depth or " \
                   "disparity, got 'x'"


def test_a_model_that_does_not_load_is_a_configuration_error_of_the_depth_stage(worker,
                                                                                 tmp_path):
    """depth.mono_model passes the start check (file + sidecar) but is no network: the first
    keyframe's load raises a ConfigError, which stops the node (it used to be logged as a
    dropped input, for every keyframe)."""
    from splat_slam_ros.roles import DepthRole
    from splat_slam_ros.types import Intrinsics, KeyframeData
    cfg = SlamConfig()
    cfg.depth.mono_model = str(not_a_model(tmp_path))
    cfg.depth.device = "cpu"
    role = DepthRole(cfg, loop_closure=False)
    rng = np.random.default_rng(0)
    kf = KeyframeData(0, 0, 1.0, np.eye(4), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8),
                      Intrinsics(50.0, 50.0, 31.5, 23.5, 64, 48),
                      np.full((12, 16), 0.5, np.float32), np.ones((12, 16), np.float32))
    with pytest.raises(ConfigError, match="cannot load .*not_a_model.onnx as an ONNX model"):
        role.on_keyframe(kf)
    role = DepthRole(cfg, loop_closure=False)
    assert not _run_jobs(worker, lambda: role.on_keyframe(kf))
    worker.thread.join(5)
    assert worker.fatal_rc == 2 and worker.dropped == 0
    assert "as an ONNX model" in worker.owner.log.lines[-1][1]


# --------------------------------------------------------------------------- processes
@pytest.mark.ros
def test_depth_node_with_a_file_that_is_not_a_model_exits_2(tmp_path):
    need_ros()
    bad = not_a_model(tmp_path, sidecar=False)
    r = subprocess.run([PY, "-m", "splat_slam_nodes.depth_node", "--ros-args",
                        "-p", f"depth.mono_model:={bad}"], env=isolated_env(),
                       capture_output=True, text=True, timeout=180, stdin=subprocess.DEVNULL)
    out = r.stdout + r.stderr
    assert r.returncode == 2, out[-3000:]
    assert "error: configuration error: depth.mono_model: no sidecar for mono depth model" \
        in r.stderr, out[-3000:]
    assert "Traceback" not in out, out[-3000:]


@pytest.mark.ros
def test_mapper_node_with_a_rasterizer_it_cannot_run_exits_2_at_start():
    """An explicit mapping.raster_backend that cannot run here (gsplat needs CUDA) stops the
    mapper node at start, not at its first keyframe."""
    need_ros()
    import torch
    if torch.cuda.is_available():
        pytest.skip("gsplat may run on this machine's CUDA device")
    r = subprocess.run([PY, "-m", "splat_slam_nodes.mapper_node", "--ros-args",
                        "-p", "mapping.raster_backend:=gsplat"], env=isolated_env(),
                       capture_output=True, text=True, timeout=180, stdin=subprocess.DEVNULL)
    out = r.stdout + r.stderr
    assert r.returncode == 2, out[-3000:]
    assert "mapping.raster_backend" in r.stderr and "Traceback" not in out, out[-3000:]


@pytest.mark.ros
def test_node_start_checks_its_configuration(tmp_path):
    """An unknown key, a value of the wrong type or an unreadable config file: exit 2 with
    one line naming it, at start (an unknown -p key used to be ignored)."""
    need_ros()
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("tracking: [unclosed\n")
    for args, msg in ((["-p", "tracking.keyframe_thres:=3.0"],
                       "parameter tracking.keyframe_thres: unknown config key"),
                      (["-p", "tracking.keyframe_thresh:=many"],
                       "parameter tracking.keyframe_thresh:"),
                      (["-p", f"config_file:={bad_yaml}"], "is not valid YAML")):
        r = subprocess.run([PY, "-m", "splat_slam_nodes.depth_node", "--ros-args", *args],
                           env=isolated_env(), capture_output=True, text=True, timeout=180,
                           stdin=subprocess.DEVNULL)
        out = r.stdout + r.stderr
        assert r.returncode == 2 and msg in out and "Traceback" not in out, (args, out[-3000:])
    # the launcher checks --set before it starts any node
    r = subprocess.run([PY, "-m", "splat_slam_nodes.tools.launch", "--out", str(tmp_path / "o"),
                        "--set", "depth.mono_modl=x.onnx"], env=isolated_env(),
                       capture_output=True, text=True, timeout=180, stdin=subprocess.DEVNULL)
    assert r.returncode == 2 and r.stderr.startswith("error: unknown config key 'depth.mono_modl'")
    assert "started" not in r.stdout, r.stdout


@pytest.mark.ros
def test_launcher_stops_the_graph_on_a_node_configuration_error(tmp_path):
    """A node exiting 2 is not restarted: the launcher stops every node and exits 2 naming
    the node and its error (before, the depth node logged 'dropped input' per keyframe)."""
    need_ros()
    bag = write_tiny_bag(tmp_path / "bag", n=6)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(TINY_TRACKING_CFG)
    bad = not_a_model(tmp_path, sidecar=False)
    log = tmp_path / "launch.log"
    t0 = time.monotonic()
    rc = run_launch([PY, "-m", "splat_slam_nodes.tools.launch", "--bag", str(bag), "--out",
                     str(tmp_path / "out"), "--config", str(cfg), "--no-loop-closure",
                     "--start-timeout", "60", "--set", f"depth.mono_model={bad}"],
                    isolated_env(), log, timeout=300)
    text = log.read_text(errors="replace")
    assert rc == 2, text[-4000:]
    assert "error: the depth node stopped on a configuration error (exit status 2): " \
           "depth.mono_model: no sidecar for mono depth model" in text, text[-4000:]
    assert "restarting it" not in text, text[-4000:]
    # (the other nodes, stopped while they import, may print a KeyboardInterrupt)
    ours = [ln for ln in text.splitlines() if ln.startswith(("[depth]", "[launch]", "error:"))]
    assert not any("Traceback" in ln for ln in ours), text[-4000:]
    assert time.monotonic() - t0 < 120        # not the player's start timeout


# --------------------------------------------------------------------------- evaluation
def _finished_launcher(tmp_path, monkeypatch, with_gt: bool):
    """A Launcher planned on a tiny bag whose graph 'finished' (the nodes' final events),
    without starting any process; the report is stubbed."""
    pytest.importorskip("rosbags", reason="the tiny bag needs rosbags")
    from splat_slam_nodes.tools import launch
    from splat_slam_ros.report import build as report
    bag = write_tiny_bag(tmp_path / "bag", n=6, with_gt=with_gt)
    out = tmp_path / "out"
    L = launch.Launcher(launch.build_parser().parse_args(["--bag", str(bag), "--out", str(out)]),
                        out=SimpleNamespace(write=lambda s: None, flush=lambda: None, lines=[]))
    L.plan()
    L.events = [{"node": "player", "event": "end_of_stream", "frames": 6},
                {"node": "tracker", "event": "saved", "frames": 6, "posed": 6, "keyframes": 4,
                 "dropped_inputs": 0},
                {"node": "depth", "event": "finalized", "dropped_inputs": 3},
                {"node": "mapper", "event": "saved", "metrics": {"gaussians": 100},
                 "dropped_inputs": 0}]
    L.children = {n: SimpleNamespace(cpu_s=lambda: 1.0, peak_rss=2**20, restarts=0,
                                     alive=lambda: False, thread=None)
                  for n in ("tracker", "depth", "mapper")}
    monkeypatch.setattr(report, "write_report", lambda d, cfg=None: (d / "report.html", None))
    return L, out


def test_a_failing_evaluation_is_exit_1_with_evaluation_error(tmp_path, monkeypatch, capsys):
    from splat_slam_nodes.tools.launch_results import finish
    from splat_slam_ros.evaluation import run as run_eval
    L, out = _finished_launcher(tmp_path, monkeypatch, with_gt=True)

    def corrupt(*a, **k):
        raise ValueError("ground truth pose 3 is not a rotation")
    monkeypatch.setattr(run_eval, "evaluate_map_depth", corrupt)
    rc = finish(L, time.monotonic())
    m = json.loads((out / "metrics.json").read_text())
    assert rc == 1, m
    assert m["evaluation_error"] == "ValueError: ground truth pose 3 is not a rotation"
    assert m["keyframes"] == 4 and m["gaussians"] == 100      # what it could still write
    assert (out / "groundtruth.txt").is_file()                # the evaluation's first part
    assert "evaluation_skipped" not in m
    err = capsys.readouterr().err
    assert "error: the evaluation failed: ValueError: ground truth pose 3" in err
    # a malformed-input count per node reaches metrics.json
    assert m["nodes"]["depth"]["dropped_inputs"] == 3
    assert m["nodes"]["tracker"]["dropped_inputs"] == 0


def test_a_failing_lpips_that_was_asked_for_is_exit_1(tmp_path, monkeypatch):
    from splat_slam_nodes.tools.launch_results import finish
    from splat_slam_ros.evaluation import run as run_eval
    L, out = _finished_launcher(tmp_path, monkeypatch, with_gt=True)

    def gone(out_dir, cfg, m):
        m["lpips"], m["lpips_error"] = None, "LPIPS backbone file not found: b.pt"
    monkeypatch.setattr(run_eval, "evaluate_lpips", gone)
    rc = finish(L, time.monotonic())
    m = json.loads((out / "metrics.json").read_text())
    assert rc == 1 and m["lpips_error"].startswith("LPIPS backbone file not found"), m
    assert "evaluation_error" not in m


def test_a_bag_without_ground_truth_skips_the_evaluation_and_exits_0(tmp_path, monkeypatch,
                                                                     capsys):
    from splat_slam_nodes.tools.launch_results import finish
    L, out = _finished_launcher(tmp_path, monkeypatch, with_gt=False)
    rc = finish(L, time.monotonic())
    m = json.loads((out / "metrics.json").read_text())
    assert rc == 0, m
    assert m["evaluation_skipped"] == "no ground truth in the bag"
    assert "evaluation_error" not in m and "ate_rmse_cm_full" not in m
    assert "error:" not in capsys.readouterr().err
