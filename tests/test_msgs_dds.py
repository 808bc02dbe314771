"""Real DDS transport between processes, with the shipped Fast DDS profile (ros_env).

- two processes exchange Keyframe, PoseGraphUpdate, ProxyDepth and 640x480 rgb8 Image
  messages; every message arrives intact, in order, the first one included;
- the profile is really loaded (its 32 MiB shared-memory segment is mapped), also when
  ``apply_ros_environment()`` runs after ``import rclpy`` but before ``rclpy.init()``;
- ros_environment() rules (pure Python, no rclpy).
Each run uses a random ROS_DOMAIN_ID and topic namespace, so parallel runs do not mix.
"""
import json
import os
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import pytest

from splat_slam_ros import ros_env
from test_graph_support import isolated_env, need_ros


HELPERS = Path(__file__).resolve().parent / "ros_helpers"
REPO = Path(__file__).resolve().parents[1]


def _stop(p: subprocess.Popen):
    """SIGTERM (rclpy shuts down cleanly and Fast DDS frees its shared memory), then SIGKILL."""
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


# ------------------------------------------------------------------ ros_env (pure Python)
def test_ros_environment_defaults_and_passthrough():
    env = ros_env.ros_environment({"ROS_DOMAIN_ID": " 42 ", "FOO": "bar"})
    assert env["ROS_DOMAIN_ID"] == "42" and env["FOO"] == "bar"
    assert env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
    prof = Path(env["FASTRTPS_DEFAULT_PROFILES_FILE"])
    assert prof == REPO / "config" / "fastdds.xml" and prof.is_file()
    # the user's own choices win
    env = ros_env.ros_environment({"FASTRTPS_DEFAULT_PROFILES_FILE": "/mine.xml",
                                   "RMW_IMPLEMENTATION": "rmw_other"})
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/mine.xml"
    assert env["RMW_IMPLEMENTATION"] == "rmw_other"
    assert "ROS_DOMAIN_ID" not in env
    env = ros_env.ros_environment({ros_env.OVERRIDE_ENV: "none"})
    assert "FASTRTPS_DEFAULT_PROFILES_FILE" not in env


def test_ros_environment_errors():
    for bad in ("x", "-1", "233"):
        with pytest.raises(ros_env.RosEnvError, match="ROS_DOMAIN_ID must be an integer"):
            ros_env.ros_environment({"ROS_DOMAIN_ID": bad})
    with pytest.raises(ros_env.RosEnvError, match="missing file"):
        ros_env.ros_environment({ros_env.OVERRIDE_ENV: "/nonexistent/profile.xml"})


def test_apply_ros_environment_only_writes_changes():
    d = {"ROS_DOMAIN_ID": "3"}
    env = ros_env.apply_ros_environment(d)
    assert d == env and d["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
    assert 1 <= ros_env.random_domain_id() <= 101


def test_graph_tests_never_reuse_a_recent_domain(monkeypatch):
    """The graph tests' domains: this worker's share of 1..101, each id once per cycle (a
    reused id let a previous test's lingering node end the next test's run)."""
    import test_graph_support as gs
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw1")
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "2")
    monkeypatch.setattr(gs, "_DOMAINS", None)
    ids = [gs._domain_id() for _ in range(51)]                 # 1, 3, ..., 101
    assert len(set(ids)) == 51 and all(1 <= d <= 101 and d % 2 == 1 for d in ids)
    assert gs._domain_id() == ids[0]                      # the cycle starts again


def test_shipped_profile_is_valid_xml_with_the_measured_settings():
    import xml.etree.ElementTree as ET
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.parse(REPO / "config" / "fastdds.xml").getroot()
    shm = [t for t in root.iterfind(".//f:transport_descriptor", ns)
           if t.findtext("f:type", namespaces=ns) == "SHM"]
    assert int(shm[0].findtext("f:segment_size", namespaces=ns)) == 32 * 1024 * 1024
    part = root.find("f:participant", ns)
    assert part.get("is_default_profile") == "true"
    assert part.findtext(".//f:useBuiltinTransports", namespaces=ns) == "false"
    disc = part.find(".//f:discovery_config", ns)
    assert disc.findtext("f:leaseAnnouncement/f:nanosec", namespaces=ns) == "500000000"
    assert disc.findtext("f:initialAnnouncements/f:count", namespaces=ns) == "10"
    assert disc.findtext("f:initialAnnouncements/f:period/f:nanosec", namespaces=ns) == "50000000"


# ------------------------------------------------------------------ the profile takes effect
PROBE = textwrap.dedent("""
    import sys
    import rclpy                                   # imported BEFORE the environment is set
    if sys.argv[1] == "apply":
        from splat_slam_ros.ros_env import apply_ros_environment
        apply_ros_environment()
    rclpy.init()
    node = rclpy.create_node("splat_env_probe")
    sizes = []
    for line in open("/proc/self/maps"):
        parts = line.split()
        if len(parts) >= 6 and parts[5].startswith("/dev/shm/fastrtps_") and "port" not in parts[5]:
            lo, hi = (int(x, 16) for x in parts[0].split("-"))
            sizes.append(hi - lo)
    print(max(sizes) if sizes else 0)
    node.destroy_node()
    rclpy.try_shutdown()
""")


@pytest.mark.ros
def test_profile_applied_in_process_after_import_before_init():
    """Fast DDS reads the profile when the participant is created: setting it in-process
    after ``import rclpy`` but before ``rclpy.init()`` works (32 MiB segment instead of the
    0.5 MiB default)."""
    need_ros()
    env = isolated_env()
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE")       # the probe must set it itself
    seg = {}
    for mode in ("apply", "none"):
        r = subprocess.run([sys.executable, "-c", PROBE, mode], env=env, capture_output=True,
                           text=True, timeout=60)
        assert r.returncode == 0, r.stderr[-2000:]
        assert "XMLPARSER" not in r.stdout + r.stderr, r.stdout + r.stderr[-2000:]
        seg[mode] = int(r.stdout.split()[-1])
    assert seg["apply"] >= 32 * 1024 * 1024, seg
    assert 0 < seg["none"] < 4 * 1024 * 1024, seg


@pytest.mark.ros
def test_broken_profile_is_reported_by_fast_dds(tmp_path):
    need_ros()
    bad = tmp_path / "broken.xml"
    bad.write_text("<profiles><participant")
    env = isolated_env(**{ros_env.OVERRIDE_ENV: str(bad)})
    r = subprocess.run([sys.executable, "-c", PROBE, "none"], env=env, capture_output=True,
                       text=True, timeout=60)
    log = r.stdout + r.stderr                       # Fast DDS logs to stdout
    assert "XMLPARSER" in log and str(bad) in log, log[-2000:]
    assert int(r.stdout.split()[-1]) < 4 * 1024 * 1024   # fell back to the defaults


# ------------------------------------------------------------------ two processes
@pytest.mark.ros
def test_two_process_transport_delivers_everything_intact():
    need_ros()
    count = 5
    ns = "splat_test_" + uuid.uuid4().hex[:8]
    env = isolated_env()
    t0 = time.monotonic()
    # The publisher starts first: it must wait for the subscriber, so nothing is lost.
    pub = subprocess.Popen([sys.executable, str(HELPERS / "dds_publisher.py"), "--ns", ns,
                            "--count", str(count)], env=env, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    time.sleep(1.0)
    sub = subprocess.Popen([sys.executable, str(HELPERS / "dds_subscriber.py"), "--ns", ns,
                            "--count", str(count), "--timeout", "25"], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        s_out, s_err = sub.communicate(timeout=60)
        p_out, p_err = pub.communicate(timeout=30)
    finally:
        for p in (pub, sub):
            _stop(p)
    elapsed = time.monotonic() - t0
    assert pub.returncode == 0, p_out + p_err[-3000:]
    assert sub.returncode == 0, s_err[-3000:]
    assert "XMLPARSER" not in p_out + p_err + s_out + s_err     # the profile loaded cleanly
    events = {e["event"]: e for e in map(json.loads, p_out.splitlines())}
    assert all(events["acked"]["acked"].values()), events["acked"]
    sent = events["published"]["sha"]
    got = json.loads(s_out.splitlines()[-1])["received"]
    for kind, items in got.items():
        assert [x["i"] for x in items] == list(range(count)), (kind, items)   # first msg too
        assert all(x["ok"] for x in items), (kind, items)
        assert [x["sha"] for x in items] == sent[kind], kind
    assert got["image"][0]["bytes"] > 640 * 480 * 3
    assert elapsed < 45, f"two-process exchange took {elapsed:.1f} s"


# ------------------------------------------------------------------ splat-slam-topic
def _tool(args, env, timeout=40):
    return subprocess.run([sys.executable, "-m", "splat_slam_nodes.tools.topic_tool", *args],
                          env=env, capture_output=True, text=True, timeout=timeout)


def test_topic_tool_help_and_usage_errors():
    r = _tool(["--help"], dict(os.environ))
    assert r.returncode == 0 and "list" in r.stdout and "echo" in r.stdout and "hz" in r.stdout
    r = _tool(["hz", "/x", "--window", "0"], dict(os.environ))
    assert r.returncode == 2 and r.stderr.strip() == "error: --window must be >= 1"
    r = _tool(["list"], {**os.environ, "ROS_DOMAIN_ID": "abc"})
    assert r.returncode == 2 and r.stderr.startswith("error: ROS_DOMAIN_ID must be")


@pytest.mark.ros
def test_topic_tool_list_echo_hz_against_a_publisher():
    need_ros()
    ns = "splat_tt_" + uuid.uuid4().hex[:8]
    env = isolated_env()
    pub = subprocess.Popen([sys.executable, str(HELPERS / "topic_publisher.py"), "--ns", ns,
                            "--rate", "20", "--duration", "30"], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert pub.stdout.readline().strip() == "ready", pub.stderr.read()
        r = _tool(["list", "-v"], env)
        assert r.returncode == 0, r.stderr
        assert f"/{ns}/image  [sensor_msgs/msg/Image]  publishers=1" in r.stdout, r.stdout
        assert f"/{ns}/keyframes  [splat_slam_msgs/msg/Keyframe]  publishers=1" in r.stdout
        # echo a transient-local keyframe published long before the tool started
        r = _tool(["echo", f"{ns}/keyframes", "--once"], env)
        assert r.returncode == 0, r.stderr
        out = r.stdout
        assert "splat_slam_msgs/msg/Keyframe" in out and "kf_id: 3\n" in out
        assert "mono_depth: float32[307200]" in out and "data: uint8[921600]" in out
        assert "intrinsics: [500, 501, 319.5, 239.5]" in out
        r = _tool(["hz", f"/{ns}/image", "--window", "20", "--duration", "2.5"], env)
        assert r.returncode == 0, r.stderr
        rates = [float(line.split()[2]) for line in r.stdout.splitlines()
                 if line.startswith("average rate:")]
        assert rates, r.stdout
        assert 12.0 < rates[-1] < 28.0, r.stdout        # published at 20 Hz (loaded machine)
        r = _tool(["hz", f"/{ns}/missing", "--timeout", "1"], env)
        assert r.returncode == 2 and "no publisher of" in r.stderr
    finally:
        _stop(pub)
