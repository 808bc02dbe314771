"""Maps across sessions through the node graph: ``splat-slam-launch --bag B --load-map RUN
[--localize]`` on the session a first run saved; the graph's own session loads again."""
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from splat_slam_ros.evaluation.trajectory import umeyama_alignment
from splat_slam_ros.io import session as ss
from splat_slam_ros.io.trajectory_io import read_trajectory
from test_graph_support import PY, SERVICE_CALLER, isolated_env, need_ros, run_launch
from test_multisession import CFG, _render, _run

pytestmark = pytest.mark.ros


def _bag(seq: Path, out: Path, start: int = 0) -> Path:
    """A bag of the frames of ``seq`` from ``start`` on."""
    from splat_slam_ros.io.bagio import write_bag
    from splat_slam_ros.io.datasets import FromFrame, open_dataset
    write_bag(FromFrame(open_dataset(seq), start), out, progress=False)
    return out


def _launch(bag: Path, out: Path, cfg: Path, *extra) -> tuple:
    log = out.parent / f"{out.name}.log"
    args = [PY, "-m", "splat_slam_nodes.tools.launch", "--bag", str(bag), "--out", str(out),
            "--config", str(cfg), *map(str, extra)]
    rc = run_launch(args, isolated_env(), log)
    return rc, log.read_text(errors="replace")


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    """A map of frames 0-29 (splat-slam-run), then the graph on frames 20-49: localize-only
    and extend."""
    need_ros()
    root = tmp_path_factory.mktemp("graph_multisession")
    seq = _render(root / "seq", 50)
    cfg = root / "cfg.yaml"
    cfg.write_text(CFG)
    s1 = root / "s1"
    r = _run(seq, "--out", s1, "--config", cfg, "--max-frames", 30)
    assert r.returncode == 0, r.stderr[-2000:]
    bag = _bag(seq, root / "bag", 20)
    runs = {"root": root, "seq": seq, "cfg": cfg, "s1": s1, "bag": bag}
    for name, extra in (("loc", ["--localize"]), ("ext", [])):
        runs[name] = _launch(bag, root / name, cfg, "--load-map", s1, *extra)
    return runs


def _stamps(path: Path) -> dict:
    ts, P = read_trajectory(path)
    return {round(float(t), 3): p for t, p in zip(ts, P)}


def test_graph_localize_tracks_in_the_loaded_map(graph):
    rc, log = graph["loc"]
    assert rc == 0, log[-4000:]
    out, s1 = graph["root"] / "loc", graph["s1"]
    assert "relocalised in the loaded map" in log and "started tracker," in log
    assert "mapper" not in log.split("started ", 1)[1].splitlines()[0]   # the tracker alone
    m = json.loads((out / "metrics.json").read_text())
    assert m["localize"]["relocalised_frame"] == 0 and m["localize"]["session"] == str(s1)
    assert m["frames_posed"] == 30 and m["frames_received"] == 30
    assert "keyframe_causes" not in m            # a localize run makes no keyframe
    # the loaded map, byte for byte; no keyframes, no session of its own
    assert (out / "map.ply").read_bytes() == (s1 / "map.ply").read_bytes()
    assert not (out / "trajectory_keyframes.txt").exists()
    assert not (out / "session" / "manifest.json").exists()
    # poses in the first run's frame: the frames both runs posed agree without alignment
    a, b = _stamps(s1 / "trajectory_full.txt"), _stamps(out / "trajectory_full.txt")
    both = sorted(set(a) & set(b))
    assert len(both) == 10
    err = [np.linalg.norm(a[t][:3, 3] - b[t][:3, 3]) for t in both]
    scene = np.ptp(np.stack([p[:3, 3] for p in a.values()]), 0).max()
    assert max(err) < 0.05 * scene, (err, scene)


def test_graph_extend_grows_the_loaded_map_and_saves_a_session(graph):
    rc, log = graph["ext"]
    assert rc == 0, log[-4000:]
    out, s1 = graph["root"] / "ext", graph["s1"]
    assert "relocalised in the loaded map" in log and "extending the map" in log
    m = json.loads((out / "metrics.json").read_text())
    e = m["extend"]
    first = ss.load_session(s1)
    assert e["relocalised_frame"] == 0 and e["loaded"]["keyframes"] == len(first.keyframes)
    assert e["new_keyframes"] >= 2 and e["loop_edges"] >= e["loop_edges_to_loaded"] >= 0
    assert e["gaussians"] > e["loaded"]["gaussians"]
    # the graph's session: loaded + new keyframes, the loaded ones where they were
    s2 = ss.load_session(out)
    k1, k2 = first.keyframes, s2.keyframes
    assert len(k2) == len(k1) + e["new_keyframes"]
    np.testing.assert_array_equal(k2.kf_ids[:len(k1)], k1.kf_ids)
    np.testing.assert_allclose(k2.poses[:len(k1), :3, 3], k1.poses[:, :3, 3], atol=1e-6)
    assert k2.kf_ids[len(k1):].min() > k1.kf_ids.max()
    arrays, _meta, _cam = ss.map_state(s2)
    assert len(arrays["means"]) == e["gaussians"] and s2.map_path == (out / "map.ply").resolve()
    # the loop closer's part: the loaded graph kept, the new loops to loaded keyframes added
    g1, g2 = ss.loop_graph(first), ss.loop_graph(s2)
    assert {tuple(x) for x in g1["edges"]} <= {tuple(x) for x in g2["edges"]}
    pairs = {tuple(p) for p in g2["loop_pairs"]}
    assert len(pairs) == e["loop_edges"]
    assert sum(len(set(p) & set(k1.kf_ids.tolist())) == 1 for p in pairs) == \
        e["loop_edges_to_loaded"]
    # both runs' frames under one Sim(3) against the ground truth: one map, one frame
    gt = {round(float(r[0]), 3): np.array(r[1:4], float) for r in
          (ln.split() for ln in (graph["seq"] / "groundtruth.txt").read_text().splitlines()
           if ln and not ln.startswith("#"))}
    est = {**_stamps(s1 / "trajectory_full.txt"), **_stamps(out / "trajectory_full.txt")}
    ts = sorted(t for t in est if t in gt)
    assert len(ts) == 50
    X = np.stack([est[t][:3, 3] for t in ts])
    Y = np.stack([gt[t] for t in ts])
    s, R, t = umeyama_alignment(X, Y, with_scale=True)
    rmse = np.sqrt(np.mean(np.sum((s * X @ R.T + t - Y) ** 2, 1)))
    assert rmse < 0.02, rmse
    # the graph's session loads into a later in-process run
    r = _run(graph["seq"], "--out", graph["root"] / "again", "--config", graph["cfg"],
             "--start-frame", 40, "--load-map", out, "--localize")
    assert r.returncode == 0, r.stderr[-2000:]
    m3 = json.loads((graph["root"] / "again" / "metrics.json").read_text())
    assert m3["relocalised_frame"] == 40 and m3["frames_posed"] == 10


def test_graph_load_map_usage_errors(graph, tmp_path):
    """Checked before any node starts: exit 2, one line."""
    def launch(*extra):
        r = subprocess.run([PY, "-m", "splat_slam_nodes.tools.launch", "--bag", str(graph["bag"]),
                            "--out", str(tmp_path / "o"), *map(str, extra)],
                           capture_output=True, text=True, timeout=120, env=isolated_env())
        return r.returncode, r.stderr.strip()
    rc, err = launch("--localize")
    assert rc == 2 and "--localize needs --load-map" in err
    rc, err = launch("--load-map", tmp_path / "nothing")
    assert rc == 2 and "no saved session" in err
    rc, err = launch("--load-map", graph["root"] / "loc")     # a localize run saves none
    assert rc == 2 and "no saved session" in err
    rc, err = launch("--load-map", graph["s1"], "--tracking-only")
    assert rc == 2 and "--tracking-only cannot extend" in err
    bad = tmp_path / "bad"
    import shutil
    shutil.copytree(graph["s1"], bad)
    with open(bad / "session" / "map_state.npz", "r+b") as f:
        f.seek(100)
        f.write(b"corrupt!")
    rc, err = launch("--load-map", bad)
    assert rc == 2 and "map_state.npz does not match its sha256" in err


def test_graph_never_relocalised_writes_no_result(graph, tmp_path):
    other = _render(tmp_path / "other", 12, seed=7)
    bag = _bag(other, tmp_path / "bag")
    rc, log = _launch(bag, tmp_path / "out", graph["cfg"], "--load-map", graph["s1"],
                      "--localize")
    assert rc == 3, log[-3000:]
    out = tmp_path / "out"
    m = json.loads((out / "metrics.json").read_text())
    assert "never relocalised" in m["error"] and m["frames_posed"] == 0
    assert not (out / "trajectory_full.txt").exists() and not (out / "map.ply").exists()


CALLER = SERVICE_CALLER + r'''
from splat_slam_msgs.srv import LoadMap, SaveMap
res = []
for c in json.loads(sys.argv[1]):
    res.append(call(LoadMap, "graph_load_map", LoadMap.Request(directory=c[1], localize=c[2]))
               if c[0] == "load" else
               call(SaveMap, "graph_save_map", SaveMap.Request(directory=c[1])))
print("RESULT " + json.dumps(res), flush=True)
rclpy.try_shutdown()
'''


def _call(calls, env, log: Path) -> list:
    r = subprocess.run([PY, "-c", CALLER, json.dumps(calls)], env=env, capture_output=True,
                       text=True, timeout=900)
    log.write_text(r.stdout + r.stderr)
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
    assert line, (r.stdout + r.stderr)[-3000:]
    return json.loads(line[0][7:])


def test_graph_services_load_then_save_a_map_live(graph, tmp_path):
    """Live topics: /splat/load_map (extend) before the first frame, a camera, then
    /splat/save_map mid-run; the saved directory is a session a later run loads."""
    import shutil
    import signal
    import time

    from test_graph_support import start, stop, wait_for
    env = isolated_env()
    out = tmp_path / "out"
    shutil.copytree(graph["s1"], out / "maps" / "s1")
    # --background-nice 0: live topics nice the loop-closure and mapper nodes, and beside the
    # test suite's other worker (CPU-bound, not niced) they started too late to answer the
    # load within the service's 300 s; this test is about the services, not priorities
    launch = start([PY, "-m", "splat_slam_nodes.tools.launch", "--out", str(out), "--config",
                    str(graph["cfg"]), "--set", "ros.image_topic=/camera/image_raw",
                    "--set", "ros.camera_info_topic=/camera/camera_info",
                    "--background-nice", "0"], env, tmp_path / "launch.log")
    try:
        # the graph is up (a request sent the moment a service is discovered can be lost)
        assert wait_for(lambda: "listening on" in (tmp_path / "launch.log").read_text(), 300)
        time.sleep(2.0)
        res = _call([["load", "../s1", False], ["load", "maps/none", False],
                     ["load", "maps/s1", False], ["load", "maps/s1", True]], env,
                    tmp_path / "load.log")
        assert not res[0][0] and "'..'" in res[0][1], res
        assert not res[1][0] and "no saved session" in res[1][1], res
        assert res[2][0], res
        assert not res[3][0] and "loaded already" in res[3][1], res
        cam = start([PY, "-m", "splat_slam_nodes.tools.bag_player", str(graph["bag"]), "--mode",
                     "realtime", "--rate", "2.0", "--wait-nodes",
                     "tracker,loop_closure,depth,mapper", "--wait-acks", "",
                     "--no-end-of-stream", "--no-clock", "--start-timeout", "300"], env,
                    tmp_path / "camera.log")
        assert cam.wait(timeout=600) == 0, (tmp_path / "camera.log").read_text()[-2000:]
        time.sleep(3.0)
        res = _call([["save", "saved"], ["save", "/abs"]], env, tmp_path / "save.log")
        assert res[0][0] and "session" in res[0][1], res
        assert not res[1][0] and "absolute" in res[1][1], res
        launch.send_signal(signal.SIGINT)
        rc = launch.wait(timeout=600)
    finally:
        stop(launch)
    log = (tmp_path / "launch.log").read_text(errors="replace")
    assert rc == 0, log[-4000:]
    assert "relocalised in the loaded map" in log and "extending the map" in log
    first = ss.load_session(graph["s1"])
    for d in (out / "saved", out):        # the service's save and the run's final session
        s = ss.load_session(d)
        assert set(first.keyframes.kf_ids) <= set(s.keyframes.kf_ids), d
        arrays, _meta, _cam = ss.map_state(s)
        assert len(arrays["means"]) >= first.manifest["map_state"]["gaussians"], d
        assert len(ss.loop_graph(s)["edges"]) > len(ss.loop_graph(first)["edges"]), d
    m = json.loads((out / "metrics.json").read_text())
    assert m["extend"]["relocalised_frame"] is not None and m["extend"]["new_keyframes"] >= 1
