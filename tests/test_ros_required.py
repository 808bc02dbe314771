"""The ROS tests fail (never skip) when rclpy or the messages cannot be imported, in CI or not:
a broken ROS build must not leave the suite green with the node graph untested."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# one test per way a ROS test checks for rclpy: module level, test_graph_support, test_msgs_dds
TARGETS = ["tests/test_ros_convert.py",
           "tests/test_services.py::test_mapper_services_refuse_bad_requests",
           "tests/test_msgs_dds.py::test_profile_applied_in_process_after_import_before_init"]


@pytest.mark.parametrize("ci", ["true", ""])
def test_ros_tests_fail_without_rclpy(tmp_path, ci):
    shadow = tmp_path / "shadow"
    (shadow / "rclpy").mkdir(parents=True, exist_ok=True)
    (shadow / "rclpy" / "__init__.py").write_text('raise ImportError("rclpy hidden by the test")\n')
    env = dict(os.environ, CI=ci, PYTHONPATH=os.pathsep.join([str(shadow)] + sys.path))
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider",
                        "--continue-on-collection-errors", *TARGETS], cwd=str(REPO), env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode != 0, r.stdout[-3000:]
    assert "rclpy hidden by the test" in r.stdout, r.stdout[-3000:]
    assert "2 failed, 1 error" in r.stdout and "skipped" not in r.stdout, r.stdout[-3000:]
