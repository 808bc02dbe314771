"""A stage node's side of the launcher's map services (/splat/save_map, /splat/load_map,
nodes/tools/launch_services.py): which graph events are the launcher's requests for this
process, and the node's answer (a ``map_saved`` / ``map_loaded`` graph event carrying the
request's id).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, List


def _newer(d: dict, started: float) -> bool:
    """Sent after ``started`` (not an old event that TRANSIENT_LOCAL delivers again to a node
    started after it); a malformed time is never newer."""
    try:
        return float(d.get("t", 0.0)) >= started
    except (TypeError, ValueError):
        return False


def load_request(d: dict, started: float) -> bool:
    """A launcher's request event for this process."""
    return d.get("node") == "launch" and isinstance(d.get("request"), str) and \
        _newer(d, started)


def loaded_by_tracker(d: dict, started: float) -> bool:
    """The tracker's yes to a /splat/load_map request that extends the map: the loop-closure
    and mapper nodes load the session then."""
    return (d.get("event") == "map_loaded" and d.get("node") == "tracker" and
            d.get("ok") is True and d.get("localize") is False and
            isinstance(d.get("run"), str) and _newer(d, started))


def reply(node, event: str, d: dict, ok: bool, message: str, **fields) -> None:
    """A node's answer to the launcher's request ``d`` (graph event ``event``)."""
    node.publish_event(event, request=d.get("request"), ok=bool(ok), message=message, **fields)


def answer_save(node, d: dict, write: Callable[[Path], List[str]]) -> None:
    """A node's part of the launcher's save request ``d``: ``write(directory)`` (the
    request's directory, which must lie inside node.output_dir) returns the files it wrote.
    A failure (a disk error) is the answer (``map_saved`` not ok); the node goes on."""
    from . import service_guard as G
    try:
        out = G.inside(d.get("directory"), node.output_dir)
        out.mkdir(parents=True, exist_ok=True)
        files = write(out)
    except Exception as e:
        return reply(node, "map_saved", d, False, f"{type(e).__name__}: {e}")
    reply(node, "map_saved", d, True, "saved", files=files)
