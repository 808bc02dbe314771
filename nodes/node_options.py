"""The graph nodes' own ROS parameters (``node.*``), beside the config keys every node declares.

ROS-free, so that ``splat-slam-launch --set node.KEY=VALUE`` is checked before any node starts:
the key must belong to a node the launch starts, the value must have the option's type, and
the options that a launcher flag sets are refused with that flag's name. The nodes declare
exactly these (``SplatNode(name, NODE_OPTIONS[name])``); every node also has ``output_dir``
and ``state_dir``.
"""
from __future__ import annotations

from typing import Any, Dict, Iterable

COMMON_OPTIONS: Dict[str, Any] = {"output_dir": "", "state_dir": ""}

NODE_OPTIONS: Dict[str, Dict[str, Any]] = {
    "tracker": {"input_qos": "sensor", "max_queue": 1, "max_backlog": 60,
                "camera_info_timeout": 2.0, "intrinsics_file": "", "loop_closure": True,
                "mapping": True, "path_every": 10, "load_map": "", "localize": False},
    "depth": {"loop_closure": True, "mapping": True},
    "loop_closure": {"loop_closure": True, "mapping": True, "load_map": ""},
    "mapper": {"loop_closure": True, "mapping": True, "snapshot_every": 1, "points_every": 1,
               "render_width": 0, "render_height": 0, "allow_reset": False,
               "max_render_pixels": 0, "load_map": ""},
    "rerun": {"rrd": "", "connect": "", "loop_closure": True, "mapping": True,
              "image_every": 5, "jpeg_quality": 85},
}

# options the launcher sets from its own arguments
LAUNCHER_FLAGS = {"output_dir": "--out", "state_dir": "--out", "loop_closure": "--no-loop-closure",
                  "mapping": "--tracking-only", "load_map": "--load-map",
                  "localize": "--localize", "intrinsics_file": "--camera-info",
                  "rrd": "--rerun", "connect": "--rerun-connect", "allow_reset": "--allow-reset"}

# the values an option takes besides its type
CHOICES = {"input_qos": ("sensor", "reliable")}


class NodeOptionError(ValueError):
    pass


def _typed(key: str, value, default):
    """``value`` as the type of ``default`` (an int is a float too), or NodeOptionError."""
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, str)
    if not ok:
        raise NodeOptionError(f"node.{key} takes a {type(default).__name__} (default "
                              f"{default!r}), got {value!r}")
    if key in CHOICES and value not in CHOICES[key]:
        raise NodeOptionError(f"node.{key} is one of {', '.join(CHOICES[key])}, got {value!r}")
    if isinstance(value, (int, float)) and not isinstance(value, bool) and value < 0:
        raise NodeOptionError(f"node.{key} must not be negative, got {value!r}")
    return value


def node_overrides(overrides: Dict[str, Any], nodes: Iterable[str]) -> Dict[str, Dict[str, Any]]:
    """The ``node.*`` items of ``--set`` (config keys are skipped) -> {node: {"node.KEY": value}}
    for the started ``nodes``. NodeOptionError names what is wrong: an unknown option, one of
    a node this launch does not start, one a launcher flag sets, a value of the wrong type."""
    per_node: Dict[str, Dict[str, Any]] = {n: {} for n in nodes}
    for k, v in overrides.items():
        if not k.startswith("node."):
            continue
        key = k[len("node."):]
        if key in LAUNCHER_FLAGS:
            raise NodeOptionError(f"{k} is set by splat-slam-launch {LAUNCHER_FLAGS[key]}; "
                                  "use that option")
        owners = [n for n, opts in NODE_OPTIONS.items() if key in opts]
        if not owners:
            known = sorted({o for opts in NODE_OPTIONS.values() for o in opts} -
                           set(LAUNCHER_FLAGS))
            raise NodeOptionError(f"unknown node option {k} (the nodes' options: "
                                  + ", ".join(f"node.{o}" for o in known) + ")")
        started = [n for n in owners if n in per_node]
        if not started:
            raise NodeOptionError(f"{k} is an option of the {' and '.join(owners)} node, which "
                                  "this launch does not start")
        for n in started:
            per_node[n][k] = _typed(key, v, NODE_OPTIONS[n][key])
    return per_node


def ros_value(v) -> str:
    """A parameter value as a ``-p KEY:=VALUE`` argument's VALUE (ROS YAML)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(ros_value(x) for x in v) + "]"
    if isinstance(v, str):
        return v if v else "''"
    return str(v)


def ros_param(key: str, value) -> list:
    """``["-p", "KEY:=VALUE"]``: one parameter on a node's ``--ros-args`` command line."""
    return ["-p", f"{key}:={ros_value(value)}"]
