"""A command imports the stages it runs: ``splat-slam-run --tracking-only`` never loads the
mapper, scipy's spatial module or Open3D (90 MB of memory and a second of start-up), nor
matplotlib before its report, and a user mistake is still one ``error:`` line, whatever
module raised it."""
import json
import subprocess
import sys

import pytest
from conftest import synth_sequence

HEAVY = ["splat_slam_ros.mapping.mapper", "splat_slam_ros.mapping.mesh", "open3d",
         "scipy.spatial"]

PROBE = """
import json, sys
from splat_slam_ros.cli.run import main
rc = main(sys.argv[1:])
print(json.dumps({{"rc": rc, "loaded": [m for m in {heavy!r} if m in sys.modules]}}))
"""


@pytest.fixture(scope="module")
def small_seq(tmp_path_factory):
    return synth_sequence(tmp_path_factory.mktemp("imports") / "seq", 30, "128x96")


def _probe(*args):
    r = subprocess.run([sys.executable, "-c", PROBE.format(heavy=HEAVY), *map(str, args)],
                       capture_output=True, text=True, timeout=600)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    assert lines, r.stdout[-2000:] + r.stderr[-2000:]
    return json.loads(lines[-1]), r.stderr


def test_a_tracking_only_run_loads_neither_the_mapper_scipy_nor_open3d(small_seq, tmp_path):
    res, err = _probe(small_seq, "--out", tmp_path / "trk", "--tracking-only", "--no-progress")
    assert res["rc"] in (0, 3), err[-2000:]           # 3: too little motion to initialise
    assert (tmp_path / "trk" / "metrics.json").is_file()
    assert res["loaded"] == [], res


def test_the_run_loads_the_plotting_library_only_for_its_report():
    """What ``splat-slam-run`` imports before its first frame leaves matplotlib out (30 MB of
    memory through the whole run); the report imports it when it is written."""
    code = ("import sys, splat_slam_ros.pipeline, splat_slam_ros.io.datasets; "
            "print('matplotlib' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "False", r.stdout + r.stderr[-2000:]


def test_a_user_mistake_is_one_error_line_from_a_module_loaded_on_demand(small_seq, tmp_path):
    # a mapping setting the mapper rejects (MapError, raised in a module the command
    # imported only for the full run)
    res, err = _probe(small_seq, "--out", tmp_path / "full", "--no-progress", "--set",
                      "mapping.init_scale=0")
    assert res["rc"] == 2 and "mapping.init_scale must be > 0" in err, err[-2000:]
    assert "Traceback" not in err


def test_every_user_error_type_names_an_exception_class():
    import importlib

    from splat_slam_ros.cli.common import USER_ERROR_TYPES
    for module, name in USER_ERROR_TYPES:
        assert issubclass(getattr(importlib.import_module(module), name), Exception), name
