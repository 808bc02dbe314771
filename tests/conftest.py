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


def synth_sequence(out: Path, frames: int, size: str) -> Path:
    """A small ``splat-slam-synth`` sequence (TUM layout, default scene and motion) in
    ``out``."""
    subprocess.run([sys.executable, "-m", "splat_slam_synth.cli", "--frames", str(frames),
                    "--size", size, "--out", str(out), "--quiet"], check=True,
                   capture_output=True, timeout=300)
    return out
