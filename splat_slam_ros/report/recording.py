"""What a run records for its report while it runs: the configuration it used
(:func:`save_config`), the warnings its loggers emit (:class:`WarningRecorder`) and the
warning lines of the launcher's console (:class:`WarningTee`); the keyframe rate line of its
summary (:func:`keyframe_rate_text`)."""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import List, Optional

from splat_slam_ros.config import dump_config

MAX_WARNINGS = 200


def save_config(cfg, path) -> Path:
    """The configuration a run used, as YAML that ``--config`` loads back (the core keys at
    their sections, the rest under ``advanced:``)."""
    return dump_config(cfg, path, header="# configuration used by this run "
                                         "(load it back with --config)\n")


class WarningRecorder(logging.Handler):
    """Collects the WARNING (and worse) log records of the project's loggers during a run.

    ``WarningRecorder()`` starts listening; ``close()`` stops and returns the messages.
    Messages still reach stderr as before when no other handler is configured."""

    def __init__(self, logger_name: str = "splat_slam_ros"):
        super().__init__(logging.WARNING)
        self.messages: List[str] = []
        self.n_dropped = 0
        self._logger = logging.getLogger(logger_name)
        self._logger.addHandler(self)

    def emit(self, record: logging.LogRecord) -> None:
        if len(self.messages) < MAX_WARNINGS:
            self.messages.append(f"{record.levelname.lower()}: {record.getMessage()}")
        else:
            self.n_dropped += 1
        lg: Optional[logging.Logger] = logging.getLogger(record.name)
        others, recorders = 0, []
        while lg is not None:
            for h in lg.handlers:
                if isinstance(h, WarningRecorder):
                    recorders.append(h)
                else:
                    others += 1
            lg = lg.parent if lg.propagate else None
        if others == 0 and recorders[0] is self and logging.lastResort is not None:
            logging.lastResort.handle(record)     # keep the default stderr output, once

    def close(self) -> List[str]:
        self._logger.removeHandler(self)
        super().close()
        more = [f"... and {self.n_dropped} more warnings"] if self.n_dropped else []
        return self.messages + more


class WarningTee:
    """A text stream (the launcher's console) that passes everything on and keeps the lines
    that are warnings: ROS ``[WARN]``/``[ERROR]`` logs, ``warning`` lines and tracking-lost
    messages of any node. ``lines`` holds them (at most MAX_WARNINGS)."""
    PATTERN = re.compile(r"\[(WARN|ERROR|FATAL)\]|\bwarning\b|tracking lost", re.IGNORECASE)

    def __init__(self, stream):
        self.stream = stream
        self.lines: List[str] = []

    def write(self, text: str) -> int:
        for line in text.splitlines():
            if len(self.lines) < MAX_WARNINGS and self.PATTERN.search(line):
                self.lines.append(" ".join(line.split()))
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()


def keyframe_rate_text(metrics: dict) -> Optional[str]:
    """Keyframes per second of input and by cause, ``6.43 (warmup 7, threshold 42)``, from
    ``metrics.json``'s ``keyframes_per_s`` and ``keyframe_causes`` (None without them)."""
    rate, causes = metrics.get("keyframes_per_s"), metrics.get("keyframe_causes")
    if rate is None or not causes:
        return None
    return f"{rate:.2f} (" + ", ".join(f"{c} {n}" for c, n in causes.items()) + ")"
