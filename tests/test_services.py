"""Bounded, contained mapper services: save inside the output directory only, reset off by
default, render sizes bounded, bad requests answered with an error (node keeps running)."""
import json
import math
from types import SimpleNamespace as NS

import pytest

from splat_slam_nodes import service_guard as G

from test_graph_support import PY, SERVICE_CALLER, isolated_env, need_ros, start, stop


def test_save_dir_stays_inside_the_output_dir(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    assert G.save_dir("", out) == out.resolve()
    assert G.save_dir("snap/01", out) == (out / "snap" / "01").resolve()
    for bad, msg in (("/etc", "is absolute"), ("~/x", "is absolute"), ("../x", "contains '..'"),
                     ("a/../../x", "contains '..'"), ("a\0b", "control characters"),
                     ("x" * 300, "short relative name")):
        with pytest.raises(G.ServiceInputError, match=msg):
            G.save_dir(bad, out)
    (out / "link").symlink_to(tmp_path)                 # a symlink leading outside
    with pytest.raises(G.ServiceInputError, match="leads outside the output directory"):
        G.save_dir("link/x", out)
    with pytest.raises(G.ServiceInputError, match="no node.output_dir"):
        G.save_dir("x", None)


def test_render_size_pose_intrinsics_and_reset_checks():
    assert G.render_size(0, 0, 64, 48, 0) == (64, 48)
    assert G.render_size(128, 96, 64, 48, 0) == (128, 96)                 # exactly 4x: allowed
    with pytest.raises(G.ServiceInputError, match="exceeds the limit of 12288 pixels"):
        G.render_size(100000, 100000, 64, 48, 0)
    with pytest.raises(G.ServiceInputError, match="exceeds the limit of 100 pixels"):
        G.render_size(11, 10, 64, 48, 100)
    pose = lambda x, w: NS(position=NS(x=x, y=0.0, z=0.0),                   # noqa: E731
                           orientation=NS(x=0.0, y=0.0, z=0.0, w=w))
    G.check_pose_msg(pose(1.0, 2.0))                                        # normalised later
    with pytest.raises(G.ServiceInputError, match="NaN or infinite"):
        G.check_pose_msg(pose(math.nan, 1.0))
    with pytest.raises(G.ServiceInputError, match="zero quaternion"):
        G.check_pose_msg(pose(0.0, 0.0))
    assert G.check_intrinsics([0, 0, 0, 0]) is None
    assert G.check_intrinsics([50, 50, 31.5, 23.5]) == [50, 50, 31.5, 23.5]
    for bad in ([math.inf, 50, 1, 1], [-5, 50, 1, 1]):
        with pytest.raises(G.ServiceInputError):
            G.check_intrinsics(bad)
    with pytest.raises(G.ServiceInputError, match="map reset is disabled"):
        G.check_reset(False)
    G.check_reset(True)
    assert G.message(G.ServiceInputError("x")) == "x" and G.message(KeyError("k")) == "KeyError: 'k'"


CALLER = SERVICE_CALLER + r'''
from splat_slam_msgs.srv import RenderPose, SaveMap
from std_srvs.srv import Trigger
res = {}
res["reset"] = call(Trigger, "reset_map", Trigger.Request())
for k, d in (("abs", sys.argv[1]), ("dotdot", "../evil"), ("rel", "snap")):
    res["save_" + k] = call(SaveMap, "save_map", SaveMap.Request(directory=d))
rq = RenderPose.Request(); rq.pose.position.x = math.nan; rq.pose.orientation.w = 1.0
res["render_nan"] = call(RenderPose, "render", rq)
rq = RenderPose.Request(); rq.pose.orientation.w = 1.0; rq.width = 100000; rq.height = 100000
res["render_huge"] = call(RenderPose, "render", rq)
print("RESULT " + json.dumps(res), flush=True)
rclpy.try_shutdown()
'''


def test_mapper_services_refuse_bad_requests(tmp_path):
    need_ros()
    out = tmp_path / "run"
    env = isolated_env()
    mapper = start([PY, "-m", "splat_slam_nodes.mapper_node", "--ros-args", "-p",
                    f"node.output_dir:={out}"], env, tmp_path / "mapper.log")
    evil = tmp_path / "evil_abs"                      # absolute, outside the output dir
    caller = start([PY, "-c", CALLER, str(evil)], env, tmp_path / "caller.log")
    try:
        assert caller.wait(timeout=240) == 0, (tmp_path / "caller.log").read_text()[-3000:]
        alive = mapper.poll() is None
    finally:
        stop(caller)
        stop(mapper)
    lines = [x for x in (tmp_path / "caller.log").read_text().splitlines() if x.startswith("RESULT ")]
    r = json.loads(lines[-1][7:])
    assert alive, (tmp_path / "mapper.log").read_text()[-3000:]
    assert r["reset"][0] is False and "map reset is disabled" in r["reset"][1]
    assert r["save_abs"][0] is False and "is absolute" in r["save_abs"][1]
    assert r["save_dotdot"][0] is False and "contains '..'" in r["save_dotdot"][1]
    # a valid name passes the containment check and reaches the map (still empty here)
    assert r["save_rel"] == [False, "the map is empty: nothing to save"]
    assert r["render_nan"][0] is False and "NaN" in r["render_nan"][1]
    assert r["render_huge"][0] is False       # the map is empty: refused before any allocation
    assert not evil.exists() and not (tmp_path / "evil").exists()


def test_launcher_passes_allow_reset_to_the_mapper_only():
    from splat_slam_nodes.tools import launch
    for flag, want in (([], False), (["--allow-reset"], True)):
        L = launch.Launcher(launch.build_parser().parse_args(["--no-loop-closure"] + flag))
        L.plan()
        assert ("node.allow_reset:=true" in L._node_args("mapper")) is want
        assert "node.allow_reset:=true" not in L._node_args("depth")
