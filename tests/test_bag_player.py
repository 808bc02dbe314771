"""bag_player: lockstep (never ahead of the consumer's ack), realtime pacing + /clock,
waiting for subscribers / ready nodes, end_of_stream, user errors."""
import json
import subprocess
import time

import pytest

from test_graph_support import (PY, isolated_env, need_ros, read_jsonl, start, start_probe, stop,
                                wait_for, write_tiny_bag)

pytestmark = pytest.mark.ros

SUBS = [["/camera/image_raw", "sensor_msgs/msg/Image", "image"],
        ["/camera/camera_info", "sensor_msgs/msg/CameraInfo", "image"],
        ["/clock", "rosgraph_msgs/msg/Clock", "image"],
        ["/splat/graph_events", "std_msgs/msg/String", "events"]]


def _player(bag, env, log, *extra):
    return start([PY, "-m", "splat_slam_nodes.tools.bag_player", str(bag), "--wait-nodes", "probe",
                  "--start-timeout", "60", *extra], env, log)


def _play(bag, tmp_path, env, probe_spec, *player_args, wait_eos: bool = True):
    """Run the probe and the player until the player exits 0 (and, with ``wait_eos``, the
    probe saw end_of_stream); both are stopped. Returns (probe records, player wall s)."""
    probe = start_probe(probe_spec, env, tmp_path / "probe.log")
    player = _player(bag, env, tmp_path / "player.log", *player_args)
    try:
        t0 = time.monotonic()
        assert player.wait(timeout=90) == 0, (tmp_path / "player.log").read_text()
        wall = time.monotonic() - t0
        if wait_eos:
            assert wait_for(lambda: _eos(read_jsonl(tmp_path / "probe.log")), 10)
    finally:
        stop(player)
        stop(probe)
    return read_jsonl(tmp_path / "probe.log"), wall


def _eos(recs):
    return [json.loads(r["data"]) for r in recs if r.get("topic") == "/splat/graph_events"
            and json.loads(r["data"]).get("event") == "end_of_stream"]


def test_lockstep_waits_for_each_ack(tmp_path):
    need_ros()
    bag = write_tiny_bag(tmp_path / "bag", n=10)
    env = isolated_env()
    recs, _ = _play(bag, tmp_path, env, {"name": "probe", "subs": SUBS, "ack_delay": 0.15,
                                         "ack_topic": "/camera/image_raw", "duration": 90},
                    "--wait-acks", "")
    imgs = [r for r in recs if r.get("topic") == "/camera/image_raw"]
    acks = [r for r in recs if "acked" in r]
    infos = [r for r in recs if r.get("topic") == "/camera/camera_info"]
    clocks = [r for r in recs if r.get("topic") == "/clock"]
    stamps = [r["stamp"] for r in imgs]
    assert len(imgs) == 10 and stamps == sorted(stamps) and len(set(stamps)) == 10
    assert len(infos) == 10 and len(clocks) == 10
    # frame i+1 is never received before the ack of frame i was sent
    ack_t = {a["acked"]: a["t"] for a in acks}
    for prev, nxt in zip(imgs[:-1], imgs[1:]):
        assert nxt["t"] >= ack_t[prev["stamp"]], "player ran ahead of the ack"
    eos = _eos(recs)
    assert eos and eos[0]["frames"] == 10 and eos[0]["mode"] == "lockstep"


def test_lockstep_waits_for_keyframe_consumers(tmp_path):
    """A keyframe ack makes the player wait for the other consumers (here: none acks, so the
    player waits its --ack-timeout per keyframe and reports the missing acks)."""
    need_ros()
    bag = write_tiny_bag(tmp_path / "bag", n=4, with_depth=False, with_gt=False)
    env = isolated_env()
    recs, wall = _play(bag, tmp_path, env, {"name": "probe", "subs": SUBS, "kf_every": 2,
                                            "ack_topic": "/camera/image_raw", "duration": 90},
                       "--wait-acks", "mapper", "--ack-timeout", "1.0", wait_eos=False)
    log = (tmp_path / "player.log").read_text()
    assert "no ack of keyframe 0 from mapper" in log and "no ack of keyframe 1 from mapper" in log
    eos = _eos(recs)
    assert eos and eos[0]["lost_acks"] == 2
    assert wall >= 2.0


def test_realtime_rate_and_clock(tmp_path):
    need_ros()
    bag = write_tiny_bag(tmp_path / "bag", n=12, fps=30.0)
    env = isolated_env()
    recs, _ = _play(bag, tmp_path, env, {"name": "probe", "subs": SUBS, "duration": 90},
                    "--mode", "realtime", "--rate", "0.5")
    imgs = [r for r in recs if r.get("topic") == "/camera/image_raw"]
    clocks = [r for r in recs if r.get("topic") == "/clock"]
    assert len(imgs) == 12
    span = imgs[-1]["t"] - imgs[0]["t"]
    assert 11 / 30 / 0.5 * 0.8 < span < 11 / 30 / 0.5 + 1.0       # paced at bag time / rate
    assert [c["stamp"] for c in clocks] == [r["stamp"] for r in imgs]


def test_loop_passes_and_state_resume(tmp_path):
    """--loop 2: the bag twice, the second pass shifted after the first (stamps and /clock);
    --state: a player started again continues after the last frame it had consumed."""
    need_ros()
    bag = write_tiny_bag(tmp_path / "bag", n=5, fps=10.0, with_depth=False, with_gt=False)
    env = isolated_env()
    spec = {"name": "probe", "subs": SUBS, "ack_topic": "/camera/image_raw", "duration": 90}
    state = tmp_path / "state"
    recs, _ = _play(bag, tmp_path, env, spec, "--wait-acks", "", "--loop", "2", "--state",
                    str(state))
    stamps = [r["stamp"] for r in recs if r.get("topic") == "/camera/image_raw"]
    assert len(stamps) == 10 and all(b - a == 100_000_000 for a, b in zip(stamps, stamps[1:]))
    assert [r["stamp"] for r in recs if r.get("topic") == "/clock"] == stamps
    prog = json.loads((state / "progress.json").read_text())
    assert prog["frames"] == 10 and prog["stamp_ns"] == stamps[-1]
    # as if it had died after 7 frames: it plays the last 3 only, the count goes on
    (state / "progress.json").write_text(json.dumps({"stamp_ns": stamps[6], "frames": 7}))
    (tmp_path / "probe.log").unlink()
    recs, _ = _play(bag, tmp_path, env, spec, "--wait-acks", "", "--loop", "2", "--state",
                    str(state))
    assert [r["stamp"] for r in recs if r.get("topic") == "/camera/image_raw"] == stamps[7:]
    assert _eos(recs)[0]["frames"] == 10
    r = subprocess.run([PY, "-m", "splat_slam_nodes.tools.bag_player", str(bag), "--loop", "0"],
                       env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "error: --loop must be at least 1" in r.stderr


def test_all_topics_and_user_errors(tmp_path):
    need_ros()
    bag = write_tiny_bag(tmp_path / "bag", n=3)
    env = isolated_env()
    r = subprocess.run([PY, "-m", "splat_slam_nodes.tools.bag_player", str(tmp_path / "nope")],
                       env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "error: bag not found" in r.stderr
    (tmp_path / "x.db3").write_bytes(b"")
    r = subprocess.run([PY, "-m", "splat_slam_nodes.tools.bag_player", str(tmp_path / "x.db3")],
                       env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "rosbag2 folder or a .mcap" in r.stderr
    # nobody listens: a clear error after --start-timeout, exit 2
    r = subprocess.run([PY, "-m", "splat_slam_nodes.tools.bag_player", str(bag), "--start-timeout",
                        "1"], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "graph not ready" in r.stderr
    subs = SUBS + [["/camera/depth", "sensor_msgs/msg/Image", "image"],
                   ["/ground_truth/pose", "geometry_msgs/msg/PoseStamped", "image"]]
    recs, _ = _play(bag, tmp_path, env, {"name": "probe", "subs": subs, "duration": 60,
                                         "ack_topic": "/camera/image_raw"},
                    "--topics", "all", "--wait-acks", "")
    for t in ("/camera/depth", "/ground_truth/pose"):
        assert len([r for r in recs if r.get("topic") == t]) == 3
