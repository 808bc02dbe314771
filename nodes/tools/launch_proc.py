"""The graph's node processes as the launcher runs them: start (dying with the launcher, at
an OS priority), each output line forwarded with the node's prefix (the first ``error:`` /
FATAL line kept as the reason it stopped), peak RSS and CPU time sampled from /proc, signals,
restarts."""
from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import threading
from pathlib import Path
from typing import Dict, List, Optional

from splat_slam_ros.heap import proc_memory_mb


def _pdeathsig():
    """Child side: die with the launcher (SIGTERM when the parent goes away)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except Exception:
        pass


def _child_setup(nice: int):
    """Child side: :func:`_pdeathsig`, then the OS priority ``nice`` (0: unchanged)."""
    def setup():
        _pdeathsig()
        if nice:
            os.nice(nice)
    return setup


class Child:
    def __init__(self, name: str, args: List[str], env: Dict[str, str], out, prefix_width: int,
                 nice: int = 0):
        self.name = name
        self.nice = int(nice)
        self.args = args
        self.env = env
        self.out = out
        self.prefix = f"[{name}]".ljust(prefix_width + 2)
        self.proc: Optional[subprocess.Popen] = None
        self.restarts = 0
        self.expected_exit = False
        self.cpu_s_prev = 0.0            # CPU of earlier incarnations
        self.cpu_s_last = 0.0            # CPU of the current one, last sample
        self.peak_rss = 0
        self.thread: Optional[threading.Thread] = None
        self.error: Optional[str] = None     # the first fatal / ``error:`` line it logged

    def start(self) -> None:
        self.error = None
        # a process group of its own (signals reach it through the launcher only), in the
        # launcher's session: a session of its own is a scheduler autogroup of its own, and
        # autogroups share the CPU per group whatever the nice value (a niced mapper then
        # took as much CPU as the tracker)
        self.proc = subprocess.Popen(self.args, env=self.env, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     process_group=0,
                                     preexec_fn=_child_setup(self.nice))
        self.thread = threading.Thread(target=self._forward, args=(self.proc,), daemon=True)
        self.thread.start()

    def _forward(self, proc) -> None:
        for line in iter(proc.stdout.readline, b""):
            text = line.decode(errors='replace').rstrip()
            if self.error is None:
                self.error = error_text(text)
            try:
                self.out.write(f"{self.prefix} {text}\n")
                self.out.flush()
            except ValueError:
                break

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def sample(self) -> None:
        """Peak RSS (VmHWM) and CPU time (utime + stime) of the current process (/proc)."""
        if not self.alive():
            return
        hwm_mb = proc_memory_mb(self.proc.pid).get("VmHWM", 0.0)
        self.peak_rss = max(self.peak_rss, int(hwm_mb * 2**20))
        self.cpu_s_last = max(self.cpu_s_last, _proc_cpu(self.proc.pid))

    def cpu_s(self) -> float:
        return self.cpu_s_prev + self.cpu_s_last

    def restarted(self) -> None:
        self.cpu_s_prev += self.cpu_s_last
        self.cpu_s_last = 0.0
        self.restarts += 1

    def signal(self, sig) -> None:
        if self.alive():
            try:
                os.kill(self.proc.pid, sig)
            except ProcessLookupError:
                pass


def error_text(line: str) -> Optional[str]:
    """The message of a node's log line that says why it stops (``error: ...`` or a FATAL
    log line), else None."""
    if line.startswith("error: "):
        return line[len("error: "):].strip()
    i = line.find("[FATAL]")
    if i < 0:
        return None
    rest = line[i + len("[FATAL]"):]
    j = rest.find("]: ")                      # [time] [node]: message
    return (rest[j + 3:] if j >= 0 else rest).strip()


def _proc_cpu(pid: int) -> float:
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        tck = os.sysconf("SC_CLK_TCK")
        return (int(f[11]) + int(f[12])) / tck          # utime + stime (fields 14, 15)
    except (OSError, ValueError, IndexError):
        return 0.0
