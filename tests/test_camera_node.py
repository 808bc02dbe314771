"""splat-slam-camera: sources, intrinsics files, clear errors; on a small video file it
publishes N images + N camera infos at the requested rate, and `splat-slam-launch --camera`
tracks them."""
import json
import os
import subprocess

import cv2
import numpy as np
import pytest
import yaml

from test_graph_support import TINY_TRACKING_CFG, launch_ok, PY, REPO, isolated_env, need_ros, read_jsonl, \
    start, start_probe, stop

pytestmark = pytest.mark.ros

from splat_slam_nodes.tools import camera_node as C  # noqa: E402

N = 24


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """A 192x144 MJPG video of a synthetic sequence + its ROS camera_info YAML."""
    need_ros()
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_synth import generate_sequence
    d = tmp_path_factory.mktemp("camera")
    traj = REPO.parent / "shared" / "data" / "trajectories" / "freiburg1_xyz-groundtruth.txt"
    generate_sequence(str(traj) if traj.is_file() else "builtin", N, (192, 144), d / "seq",
                      overwrite=True, progress=False, realism="clean", fps=10)
    ds = open_dataset(d / "seq")
    w = cv2.VideoWriter(str(d / "cam.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (192, 144))
    for f in ds:
        w.write(cv2.cvtColor(f.image, cv2.COLOR_RGB2BGR))
    w.release()
    K = ds.intrinsics
    (d / "cam.yaml").write_text(yaml.safe_dump({
        "image_width": 192, "image_height": 144, "camera_name": "synthetic",
        "camera_matrix": {"rows": 3, "cols": 3, "data": [K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1]},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0, 0, 0, 0, 0]}}))
    return d / "cam.avi", d / "cam.yaml", K


def test_sources_and_intrinsics_files(video, tmp_path):
    avi, cam_yaml, K = video
    src = C.FrameSource(str(avi))
    frames = list(src.frames())
    assert src.kind == "video" and len(frames) == N and frames[0].shape == (144, 192, 3)
    assert abs(src.fps - 10) < 1e-6
    looped = C.FrameSource(str(avi), loop=True).frames()
    assert len([next(looped) for _ in range(N + 5)]) == N + 5           # --loop restarts
    (tmp_path / "imgs").mkdir()
    for i in (2, 0, 1):
        cv2.imwrite(str(tmp_path / "imgs" / f"{i:03d}.png"), np.full((8, 10, 3), 40 * i, np.uint8))
    fo = list(C.FrameSource(str(tmp_path / "imgs")).frames())
    assert [int(f[0, 0, 0]) for f in fo] == [0, 40, 80]                  # sorted by name
    ri = C.load_camera_info(str(cam_yaml))
    assert (ri.width, ri.height) == (192, 144) and np.isclose(ri.fx, K.fx)
    # OpenCV FileStorage YAML (%YAML:1.0, !!opencv-matrix)
    fs = cv2.FileStorage(str(tmp_path / "cv.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[500.0, 0, 319.5], [0, 501.0, 239.5], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[0.1, -0.2, 0.001, 0.002, 0.05]]))
    fs.release()
    assert "opencv-matrix" in (tmp_path / "cv.yaml").read_text()
    ci = C.load_camera_info(str(tmp_path / "cv.yaml"))
    assert (ci.fx, ci.fy, ci.cx, ci.cy, ci.width, ci.height) == (500, 501, 319.5, 239.5, 640, 480)
    assert ci.distortion_model == "plumb_bob" and np.allclose(ci.distortion,
                                                              [0.1, -0.2, 0.001, 0.002, 0.05])


@pytest.mark.parametrize("args,msg", [
    (["/nonexistent/video.mp4"], "not found"),
    (["EMPTY"], "holds no images"),
    (["/dev/video99"], "does not exist"),
    (["NOTVIDEO"], "cannot read video file"),
    (["VIDEO", "--camera-info", "/nonexistent.yaml"], "camera info file not found"),
    (["VIDEO", "--camera-info", "BADYAML"], "lacks a valid entry"),
])
def test_user_mistakes_are_one_line_errors(video, tmp_path, args, msg):
    (tmp_path / "empty").mkdir()
    (tmp_path / "not.mp4").write_text("hello")
    (tmp_path / "bad.yaml").write_text("fx: 1\n")
    sub = {"EMPTY": str(tmp_path / "empty"), "NOTVIDEO": str(tmp_path / "not.mp4"),
           "VIDEO": str(video[0]), "BADYAML": str(tmp_path / "bad.yaml")}
    r = subprocess.run([PY, "-m", "splat_slam_nodes.tools.camera_node"]
                       + [sub.get(x, x) for x in args], capture_output=True, text=True, timeout=120, env=isolated_env())
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().startswith("error:") and msg in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.parametrize("jpeg", [0, 80])
def test_camera_publishes_images_and_infos_at_the_rate(video, tmp_path, jpeg):
    """Raw rgb8 Images, or with --jpeg JPEG CompressedImages on image_transport's
    .../compressed name (a fraction of the bytes)."""
    avi, cam_yaml, K = video
    env = isolated_env()
    topic, kind = (("/camera/image_raw/compressed", "CompressedImage") if jpeg else
                   ("/camera/image_raw", "Image"))
    subs = [[topic, f"sensor_msgs/msg/{kind}", "sensor"],
            ["/camera/camera_info", "sensor_msgs/msg/CameraInfo", "sensor"]]
    probe = start_probe({"name": "probe", "subs": subs, "duration": 300}, env,
                        tmp_path / "probe.log")
    cam = start([PY, "-m", "splat_slam_nodes.tools.camera_node", str(avi), "--camera-info",
                 str(cam_yaml), "--rate", "8", "--min-subscribers", "1", "--no-progress",
                 "--jpeg", str(jpeg)], env, tmp_path / "camera.log")
    try:
        rc = cam.wait(timeout=300)
        import time
        time.sleep(1.0)
    finally:
        stop(cam)
        stop(probe)
    assert rc == 0, (tmp_path / "camera.log").read_text()[-3000:]
    recs = read_jsonl(tmp_path / "probe.log")
    img = [r for r in recs if r.get("topic") == topic]
    info = [r for r in recs if r.get("topic") == "/camera/camera_info"]
    assert len(img) == N and len(info) == N
    raw = 192 * 144 * 3
    assert all(r["bytes"] < raw / 3 for r in img) if jpeg else all(r["bytes"] > raw for r in img)
    assert [r["stamp"] for r in img] == [r["stamp"] for r in info]      # paired by stamp
    dt = np.diff([r["stamp"] for r in img]) * 1e-9
    print(f"camera period: median {np.median(dt):.4f} s, mean {dt.mean():.4f} s, "
          f"load {os.getloadavg()}")
    assert abs(np.median(dt) - 1 / 8) < 0.02 and abs(dt.mean() - 1 / 8) < 0.03


CFG = TINY_TRACKING_CFG


@pytest.mark.parametrize("jpeg", [0, 85])
def test_launch_with_camera_tracks_the_video(video, tmp_path, jpeg):
    """The camera's raw images, or its JPEG ones (--camera-jpeg: the tracker and the rerun
    logger subscribe to the compressed transport's name)."""
    avi, cam_yaml, K = video
    (tmp_path / "cfg.yaml").write_text(CFG)
    env = isolated_env()
    out = tmp_path / "out"
    log = launch_ok([PY, "-m", "splat_slam_nodes.tools.launch", "--camera", str(avi),
                     "--camera-info", str(cam_yaml), "--camera-rate", "4", "--out", str(out), "--config",
                     str(tmp_path / "cfg.yaml"), "--tracking-only", "--rerun",
                     str(tmp_path / "run.rrd"), "--camera-jpeg", str(jpeg)], env,
                    tmp_path / "launch.log", timeout=600)
    assert "[camera]" in log and "published 24 frames" in log
    assert ("image/compressed (JPEG quality 85)" in log) == bool(jpeg)
    m = json.loads((out / "metrics.json").read_text())
    # a live camera: how many frames the busy tracker drops depends on the machine's speed;
    # the counts must agree whatever it is
    assert m["frames_received"] == N, m                    # every frame reached the tracker
    assert m["frames_tracked"] + m["frames_skipped"] + m["frames_lost"] + \
        m["frames_dropped"] == N, m
    assert m["keyframes"] >= 4
    rows = [ln for ln in (out / "trajectory_full.txt").read_text().splitlines()
            if ln and not ln.startswith("#")]
    assert len(rows) == m["frames_posed"] <= m["frames_received"] - m["frames_dropped"], m
    assert len(rows) >= N - m["frames_dropped"] - 2 and len(rows) >= N // 2
    # the rerun recording of the same run: camera poses, trajectory, input images, keyframes
    from test_graph_rerun import _read_rrd
    arch, nrows, _ = _read_rrd(tmp_path / "run.rrd")
    for ent in ("/world/camera", "/world/trajectory", "/world/camera/image", "/world/keyframes/0"):
        assert ent in arch, sorted(arch)
    assert nrows["/world/camera"] >= 10


def test_launch_rejects_bad_camera_arguments(video, tmp_path):
    avi, cam_yaml, _ = video
    for extra, msg in ((["--camera", "/nonexistent.avi"], "not found"),
                       (["--camera", str(avi), "--bag", str(tmp_path)], "exclude each other"),
                       (["--camera", str(avi), "--camera-info", str(avi)], "not a YAML text"),
                       (["--camera-jpeg", "90"], "--camera-jpeg needs --camera"),
                       (["--camera", str(avi), "--camera-jpeg", "101"], "quality from 1 to 100"),
                       (["--camera", str(avi), "--set", "ros.image_topic=/c/image/compressed"],
                        "add --camera-jpeg Q")):
        r = subprocess.run([PY, "-m", "splat_slam_nodes.tools.launch", "--out", str(tmp_path / "o")]
                           + extra, capture_output=True, text=True, timeout=120,
                           env=isolated_env())
        assert r.returncode == 2 and r.stderr.startswith("error:") and msg in r.stderr, r.stderr
