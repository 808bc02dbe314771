"""Shared pytest fixtures."""
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the checkout; tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED_DATA} (only present in the dev/CI setup)")
    return SHARED_DATA


@pytest.fixture
def file_error(tmp_path):
    """``check(name, text, reader, error, pattern)``: ``reader(path)`` of a file ``name``
    holding ``text`` raises ``error`` with a message matching the regex ``pattern``."""
    def check(name, text, reader, error, pattern):
        p = tmp_path / name
        p.write_text(text)
        with pytest.raises(error, match=pattern):
            reader(p)
    return check


def synth_sequence(out: Path, frames: int, size: str, *extra: str) -> Path:
    """A small ``splat-slam-synth`` sequence (TUM layout; default scene and motion unless
    ``extra`` CLI arguments say otherwise) in ``out``."""
    subprocess.run([sys.executable, "-m", "splat_slam_synth.cli", "--frames", str(frames),
                    "--size", size, "--out", str(out), "--quiet", *extra], check=True,
                   capture_output=True, timeout=300)
    return out


def v102_render(out: Path, start: float):
    """80 frames of a realistic 320x240 render along EuRoC V1_02 drone motion at 20 Hz from
    ``start`` s of its trajectory: (dataset, frames); the test skips without the trajectory."""
    from splat_slam_ros.io.datasets import open_dataset
    traj = SHARED_DATA / "trajectories" / "V102_groundtruth.csv"
    if not traj.is_file():
        pytest.skip(f"{traj} not found (only present in the dev/CI setup)")
    synth_sequence(out, 80, "320x240", "--trajectory", str(traj), "--fps", "20",
                   "--start", str(start), "--realism", "realistic")
    ds = open_dataset(out)
    return ds, list(ds)


class FrameList(list):
    """Frames (``timestamp``, ``gt_depth``) standing in for a dataset where the evaluation
    reads the keyframes' frames by timestamp (``Dataset.frames_at_stamps``)."""

    def frames_at_stamps(self, stamps, depth=True):
        from splat_slam_ros.io.dataset_base import stamp_key
        want = {stamp_key(t) for t in stamps}
        return [f for f in self if stamp_key(f.timestamp) in want]
