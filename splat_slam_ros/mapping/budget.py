"""How many optimisation steps the mapper spends per keyframe and on the final refinement.

Two kinds of budget (docs/mapping.md "Budgets"):

- **Steps** (offline: lockstep bag replay, ``splat-slam-run``; the default). A keyframe gets
  ``iters_first`` / ``iters_per_keyframe`` steps, shrunk to ``stream_pace_steps`` x the stream
  seconds since the last mapped keyframe (fast motion, many keyframes: fewer steps each); the
  final refinement ``final_refine_per_keyframe`` x keyframes, at most ``final_refine_iters``.
  The counts depend on the input and the configuration only, so a replay gives the same map
  whatever the load or the machine's speed.
- **Time** (``mapping.time_budget``: live input, where the camera sets the pace; the launcher
  turns it on for realtime input). The step caps above stay, and wall-clock caps come on top:
  ``budget_s_first`` / ``budget_s_per_keyframe`` shrunk to ``stream_pace`` x the stream time,
  ``keep_up`` x the stream time, ``final_refine_s``, ``final_deadline_s`` (after the input
  ended). Steps a wall-clock cap cuts are counted
  (``Mapper.skipped_iters``, per keyframe in the history) so a user sees what the load cost.
"""
from __future__ import annotations

import math
from typing import Dict, Iterable, NamedTuple, Optional

from splat_slam_ros.config import MappingConfig

MIN_DEADLINE_S = 1e-3   # a deadline already past still leaves the refinement's first step


class Budget(NamedTuple):
    steps: int          # at most this many optimisation steps
    wall_s: float       # and, when > 0, stop before the next step would end past this
    min_steps: int      # steps run even past the wall-clock cap


def keyframe_budget(m: MappingConfig, first: bool, stream_dt: Optional[float]) -> Budget:
    """The budget of one mapped keyframe; ``stream_dt``: stream seconds since the last mapped
    keyframe (None for the first, or when the stamps do not advance)."""
    steps = int(m.iters_first if first else m.iters_per_keyframe)
    paced = not first and stream_dt is not None and stream_dt > 0
    if paced and m.stream_pace_steps > 0:           # the step form of the stream pace
        steps = min(steps, max(int(m.min_iters_per_keyframe),
                               math.ceil(m.stream_pace_steps * stream_dt)))
    wall = 0.0
    if m.time_budget:
        wall = float(m.budget_s_first if first else m.budget_s_per_keyframe)
        if paced and m.stream_pace > 0 and wall > 0:
            wall = min(wall, m.stream_pace * stream_dt)
        if paced and m.keep_up > 0:
            wall = min(wall, m.keep_up * stream_dt) if wall > 0 else m.keep_up * stream_dt
    return Budget(steps, float(wall), int(m.min_iters_per_keyframe))


def final_refine_budget(m: MappingConfig, n_keyframes: int,
                        since_input_s: float = 0.0) -> Budget:
    """The final refinement (supplementary "Final Refinement"): ``final_refine_iters`` (the
    paper's beta), or ``final_refine_per_keyframe`` x keyframes when that is fewer (a short
    clip does not pay 2000 steps); with ``time_budget``, ``final_refine_s`` caps it, and
    ``final_deadline_s`` ends it that long after the input ended (``since_input_s`` ago:
    keyframes still queued then use up the refinement's time; one step at least)."""
    steps = int(m.final_refine_iters)
    if m.final_refine_per_keyframe > 0:
        steps = min(steps, int(m.final_refine_per_keyframe) * int(n_keyframes))
    wall = float(m.final_refine_s) if m.time_budget else 0.0
    if m.time_budget and m.final_deadline_s > 0:
        left = max(MIN_DEADLINE_S, float(m.final_deadline_s) - max(0.0, float(since_input_s)))
        wall = min(wall, left) if wall > 0 else left
    return Budget(steps, wall, 0)


def steps_summary(history: Iterable[dict]) -> Dict[str, float]:
    """Steps run per mapped keyframe over a mapper's history (mean, min, max) and the steps
    a wall-clock cap cut (``skipped``): what the load cost a live run; 0 offline."""
    rows = [h for h in history if h.get("mapped")]
    steps = [int(h.get("steps", 0)) for h in rows]
    if not steps:
        return {"mean": 0.0, "min": 0, "max": 0, "skipped": 0}
    return {"mean": round(sum(steps) / len(steps), 2), "min": min(steps), "max": max(steps),
            "skipped": sum(int(h.get("steps_skipped", 0)) for h in rows)}
