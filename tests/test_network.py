"""DDS discovery range (localhost by default, subnet on request) and splat-slam-launch --nodes."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from splat_slam_nodes.tools import launch, launch_net
from splat_slam_ros import ros_env

from test_graph_support import TINY_FAST_RUN_CFG, isolated_env, need_ros

REPO = Path(__file__).resolve().parents[1]
PROBE = REPO / "tests" / "ros_helpers" / "dds_discovery_probe.py"
OUTSIDE_ADDR = "10.200.0.1"    # exists only inside the test's own network namespace

OUTSIDER_XML = """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors><transport_descriptor>
    <transport_id>outside</transport_id><type>UDPv4</type>
    <interfaceWhiteList><address>{addr}</address></interfaceWhiteList>
  </transport_descriptor></transport_descriptors>
  <participant profile_name="outsider" is_default_profile="true"><rtps>
    <useBuiltinTransports>false</useBuiltinTransports>
    <userTransports><transport_id>outside</transport_id></userTransports>
  </rtps></participant>
</profiles>
"""


def test_range_selects_the_shipped_profile():
    env = ros_env.ros_environment({})
    assert Path(env["FASTRTPS_DEFAULT_PROFILES_FILE"]) == REPO / "config" / "fastdds.xml"
    env = ros_env.ros_environment({"SPLAT_SLAM_DDS_RANGE": "Subnet"})
    assert Path(env["FASTRTPS_DEFAULT_PROFILES_FILE"]) == REPO / "config" / "fastdds_subnet.xml"
    # a shipped profile inherited from a parent follows the child's range; a user's file wins
    env = ros_env.ros_environment({"SPLAT_SLAM_DDS_RANGE": "subnet",
                                   "FASTRTPS_DEFAULT_PROFILES_FILE": str(REPO / "config/fastdds.xml")})
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith("fastdds_subnet.xml")
    env = ros_env.ros_environment({"SPLAT_SLAM_DDS_RANGE": "subnet",
                                   "FASTRTPS_DEFAULT_PROFILES_FILE": "/mine.xml"})
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/mine.xml"
    with pytest.raises(ros_env.RosEnvError, match="SPLAT_SLAM_DDS_RANGE must be one of"):
        ros_env.ros_environment({"SPLAT_SLAM_DDS_RANGE": "internet"})


def test_localhost_profile_whitelists_loopback_only():
    import xml.etree.ElementTree as ET
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    for name, want in (("fastdds.xml", ["127.0.0.1"]), ("fastdds_subnet.xml", [])):
        root = ET.parse(REPO / "config" / name).getroot()
        udp = [t for t in root.iterfind(".//f:transport_descriptor", ns)
               if t.findtext("f:type", namespaces=ns) == "UDPv4"]
        assert len(udp) == 1
        got = [a.text for a in udp[0].iterfind("f:interfaceWhiteList/f:address", ns)]
        assert got == want, name


def test_select_nodes_and_network_args():
    planned = ["tracker", "loop_closure", "depth", "mapper"]
    assert launch_net.select_nodes(None, planned) == planned
    assert launch_net.select_nodes("depth, tracker", planned) == ["tracker", "depth"]
    for bad, msg in ((",", "is empty"), ("tracker,gpu", "unknown node 'gpu'")):
        with pytest.raises(launch_net.NetworkArgError, match=msg):
            launch_net.select_nodes(bad, planned)
    with pytest.raises(launch_net.NetworkArgError, match="not part of this graph"):
        launch_net.select_nodes("mapper", ["tracker"])
    env = {}
    assert launch_net.apply_network("subnet", env) == "subnet" and env["SPLAT_SLAM_DDS_RANGE"] == "subnet"
    assert launch_net.apply_network(None, {}) == "localhost"


def test_launch_rejects_bad_nodes_with_one_line(capsys, monkeypatch):
    monkeypatch.delenv("SPLAT_SLAM_DDS_RANGE", raising=False)
    assert launch.main(["--tracking-only", "--nodes", "tracker,mapper"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --nodes: mapper is not part of this graph")
    assert os.environ.get("SPLAT_SLAM_DDS_RANGE") is None
    monkeypatch.setenv("SPLAT_SLAM_DDS_RANGE", "wan")
    assert launch.main(["--tracking-only"]) == 2
    assert "SPLAT_SLAM_DDS_RANGE must be one of" in capsys.readouterr().err


def _netns_prefix():
    """Command prefix for a private network namespace (nothing can leave it), or a skip."""
    unshare = shutil.which("unshare")
    pre = [unshare, "-rn"] if os.geteuid() != 0 else [unshare, "-n"]
    r = subprocess.run(pre + ["true"], capture_output=True, text=True) if unshare else None
    if r is None or r.returncode != 0:
        pytest.skip("cannot create a private network namespace here (unshare -n not permitted)")
    return pre


def _outsider_sees_graph(tmp_path, dds_range: str) -> bool:
    xml = tmp_path / "outsider.xml"
    xml.write_text(OUTSIDER_XML.format(addr=OUTSIDE_ADDR))
    graph_env = isolated_env(SPLAT_SLAM_DDS_RANGE=dds_range)       # what every node gets
    out_env = dict(graph_env, FASTRTPS_DEFAULT_PROFILES_FILE=str(xml))
    q = lambda e: " ".join(f"{k}={json.dumps(v)}" for k, v in e.items()   # noqa: E731
                           if k.startswith(("ROS_", "RMW_", "FASTRTPS_")))
    script = (f"ip link set lo up && ip link set lo multicast on && "
              f"ip addr add {OUTSIDE_ADDR}/24 dev lo && "
              f"(env {q(graph_env)} {sys.executable} {PROBE} graph 9 >/dev/null &) && "
              f"env {q(out_env)} {sys.executable} {PROBE} outsider 7")
    r = subprocess.run(_netns_prefix() + ["sh", "-c", script], capture_output=True, text=True,
                       timeout=90, cwd=str(REPO), env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])["seen"]


def test_outsider_on_a_non_loopback_address_discovers_the_graph_only_with_subnet(tmp_path):
    need_ros()
    assert not _outsider_sees_graph(tmp_path, "localhost")
    assert _outsider_sees_graph(tmp_path, "subnet")


def test_launcher_network_switch_and_node_subset(monkeypatch):
    monkeypatch.setenv("SPLAT_SLAM_DDS_RANGE", "localhost")        # restored after the test
    monkeypatch.delenv("FASTRTPS_DEFAULT_PROFILES_FILE", raising=False)
    args = ["--network", "subnet", "--nodes", "mapper,depth", "--no-loop-closure"]
    L = launch.Launcher(launch.build_parser().parse_args(args))
    L.plan()
    assert L.dds_range == "subnet"
    assert L.env["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith("fastdds_subnet.xml")
    assert L.nodes == ["tracker", "depth", "mapper"] and L.local_nodes == ["depth", "mapper"]


SPLIT_CFG = TINY_FAST_RUN_CFG


def test_graph_split_over_two_launchers(tmp_path):
    """'Two hosts' on one machine: launcher A runs the tracker + player, launcher B the depth
    and mapper nodes (--nodes); together they finish the run, B saves the map."""
    need_ros()
    from splat_slam_ros.io.bagio import write_bag
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_synth import generate_sequence
    from test_graph_support import PY, start, stop
    generate_sequence("builtin", 24, (160, 120), tmp_path / "seq", overwrite=True,
                      progress=False, realism="clean", fps=5)
    with open_dataset(tmp_path / "seq") as ds:
        write_bag(ds, tmp_path / "bag", progress=False)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(SPLIT_CFG)
    env = isolated_env()
    base = [PY, "-m", "splat_slam_nodes.tools.launch", "--config", str(cfg), "--no-loop-closure"]
    b = start(base + ["--nodes", "depth,mapper", "--out", str(tmp_path / "B")], env,
              tmp_path / "B.log")
    a = start(base + ["--nodes", "tracker", "--bag", str(tmp_path / "bag"), "--out",
                      str(tmp_path / "A")], env, tmp_path / "A.log")
    try:
        rc_a = a.wait(timeout=600)
        rc_b = b.wait(timeout=120)
    finally:
        stop(a)
        stop(b)
    la, lb = ((tmp_path / f"{x}.log").read_text(errors="replace") for x in "AB")
    assert rc_a == 0 and rc_b == 0, (la[-3000:], lb[-3000:])
    assert "started tracker, player" in la and "started depth, mapper" in lb
    assert (tmp_path / "A" / "trajectory_full.txt").is_file()
    assert (tmp_path / "B" / "map.ply").is_file()
