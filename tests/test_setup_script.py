"""run.sh set-up: the system-package check is free of races and apt runs only when needed.

The check once piped ``ldconfig -p`` into ``grep -q`` under ``set -o pipefail``: grep exits at
the first match, ldconfig dies of SIGPIPE and the pipeline fails although the library is
installed (measured 4-29 failures in 50-200 runs, depending on the machine)."""
from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from conftest import REPO

RUN_SH = REPO / "run.sh"
RUNS = 200


def expected_missing(as_user: tuple = ()) -> list:
    """The packages ``run.sh check-system`` must report, probed here without pipes; the
    interpreter probe runs as the user the check runs as (``as_user``: a command prefix),
    whose PATH may find another python3."""
    need = [name for tool, name in (("cmake", "cmake"), ("g++", "g++"), ("make", "make"))
            if shutil.which(tool) is None]
    ok = subprocess.run([*as_user, "bash", "-c", "python3 -c 'import ensurepip, venv'"],
                        capture_output=True, cwd="/").returncode == 0
    if not ok:
        need.append("python3-venv")
    if not any(Path(f"/usr/lib/{a}-linux-gnu/libjemalloc.so.2").exists()
               for a in ("x86_64", "aarch64")):
        need.append("libjemalloc2")
    libs = subprocess.run(["/sbin/ldconfig", "-p"], capture_output=True, text=True).stdout
    if "libusb-1.0.so.0 " not in libs:
        need.append("libusb-1.0-0")
    return need


def unprivileged_prefix() -> list:
    """Run as ``nobody`` when the tests run as root (the user without root is the one a
    false 'missing' stops); as the current, unprivileged user otherwise."""
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    assert setpriv, "setpriv (util-linux) is needed to drop root for this test"
    return [setpriv, "--reuid=65534", "--regid=65534", "--clear-groups"]


def test_system_check_is_stable_over_many_runs_without_root():
    want = " ".join(expected_missing(tuple(unprivileged_prefix())))
    # a copy of run.sh in a world-readable folder: the checkout may sit under a private home
    d = Path(tempfile.mkdtemp(prefix="splat-runsh-"))
    try:
        d.chmod(0o755)
        script = d / "run.sh"
        shutil.copy(RUN_SH, script)
        script.chmod(0o755)
        loop = (f'for i in $(seq {RUNS}); do bash "{script}" check-system || echo "rc=$?"; '
                'done')
        out = subprocess.run(unprivileged_prefix() + ["bash", "-c", loop], capture_output=True,
                             text=True, timeout=300, cwd=str(d))
    finally:
        shutil.rmtree(d, ignore_errors=True)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    assert len(lines) == RUNS, out.stdout[-2000:]
    wrong = [ln for ln in lines if ln.strip() != want]
    assert not wrong, f"{len(wrong)} of {RUNS} runs reported {wrong[:3]} (expected {want!r})"


def _fake_bin(folder: Path, hide: tuple = ()) -> Path:
    """A PATH folder whose ``apt-get`` only logs its arguments; with ``hide``, a PATH of its
    own that has every tool run.sh probes except those named."""
    folder.mkdir()
    log = folder / "apt.log"
    apt = folder / "apt-get"
    apt.write_text(f'#!/bin/sh\necho "$@" >> "{log}"\nexit 0\n')
    apt.chmod(apt.stat().st_mode | stat.S_IXUSR)
    if hide:
        for tool in ("cmake", "g++", "make", "python3", "bash", "cat", "sha256sum", "cut",
                     "id", "env", "nproc", "mkdir", "rm", "dirname", "c++"):
            # python3: the interpreter this venv was made from (a shim would need its PATH)
            p = getattr(sys, "_base_executable", None) if tool == "python3" else \
                shutil.which(tool)
            if p and tool not in hide:
                (folder / tool).symlink_to(Path(p).resolve())
    return log


@pytest.mark.skipif(os.geteuid() != 0, reason="run.sh calls apt-get only as root")
def test_set_up_as_root_calls_apt_only_for_missing_packages(tmp_path):
    """``./run.sh setup`` on a machine that has everything (the venv this suite runs in was
    made by it) never calls apt; with cmake hidden from PATH it does, for cmake alone."""
    venv = REPO / ".venv"
    if Path(sys.prefix).resolve() != venv.resolve():
        pytest.skip("the suite runs outside run.sh's .venv: set-up would build a new one")
    assert expected_missing() == [], "run ./run.sh setup once first"
    log = _fake_bin(tmp_path / "bin")
    env = dict(os.environ, PATH=f"{tmp_path / 'bin'}:{os.environ['PATH']}")
    for _ in range(2):
        r = subprocess.run(["bash", str(RUN_SH), "setup"], env=env, capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
    assert not log.exists(), f"apt-get was called: {log.read_text()}"

    log = _fake_bin(tmp_path / "bin2", hide=("cmake",))
    env = dict(os.environ, PATH=str(tmp_path / "bin2"))
    r = subprocess.run(["bash", str(RUN_SH), "check-system"], env=env, capture_output=True,
                       text=True, timeout=60)
    assert r.stdout.split() == ["cmake"], (r.stdout, r.stderr)
    r = subprocess.run(["bash", str(RUN_SH), "setup"], env=env, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert log.read_text().splitlines() == ["update -qq", "install -y -qq cmake"]


def test_no_early_exit_reader_in_a_pipeline_of_the_scripts():
    """The race needs no luck to find: a reader that stops early (``grep -q``, ``head``)
    at the end of a pipeline under ``pipefail`` is one. None in the project's scripts."""
    import re
    out = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True)
    scripts = [REPO / f for f in out.stdout.split()
               if f.endswith(".sh") or f == ".ci/run" or f.startswith("tests/run_")]
    assert RUN_SH in scripts
    bad = re.compile(r"\|\s*(grep\s+(-\w*q|--quiet)|head\b)")
    found = [f"{p.name}:{i}: {ln.strip()}" for p in scripts if p.is_file()
             for i, ln in enumerate(p.read_text().splitlines(), 1)
             if bad.search(ln) and not ln.lstrip().startswith("#")]
    assert not found, found
