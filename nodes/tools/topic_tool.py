"""splat-slam-topic: small topic tools (list / echo / hz) for the pip-only ROS 2 install,
where the ``ros2`` CLI is not available. Uses the project's DDS environment (ros_env), so it
sees the nodes of ``splat-slam-launch`` on the same ROS_DOMAIN_ID.

  splat-slam-topic list [-v]                       topics (with -v: type, publishers, subscribers)
  splat-slam-topic echo TOPIC [--once] [--max-bytes N]   compact message summaries
  splat-slam-topic hz TOPIC [--window N]           receive rate (and bandwidth)
"""
from __future__ import annotations

import argparse
import array
import math
import sys
import time
from collections import deque
from typing import List, Optional

import numpy as np

from splat_slam_ros.ros_env import RosEnvError, apply_ros_environment

from ..tool_runner import run_rclpy_tool
from .msg_types import UnknownMessageType, message_class


class TopicToolError(Exception):
    """A user-facing error: printed as ``error: ...``, exit status 2."""


# ------------------------------------------------------------------ helpers
def _import_type(type_name: str):
    """'pkg/msg/Name' -> the Python message class."""
    try:
        return message_class(type_name)
    except UnknownMessageType as e:
        raise TopicToolError(str(e)) from None


def _full_name(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic


def _wait_for_topic(node, topic: str, timeout: float):
    """Wait until ``topic`` has a publisher; return its message type name."""
    import rclpy
    t0 = time.monotonic()
    while True:
        types = dict(node.get_topic_names_and_types())
        if topic in types and node.count_publishers(topic) > 0:
            tn = types[topic]
            if len(tn) > 1:
                print(f"warning: {topic} has several types {tn}; using {tn[0]}", file=sys.stderr)
            return tn[0]
        if time.monotonic() - t0 > timeout:
            raise TopicToolError(f"no publisher of {topic} appeared within {timeout:g} s "
                                 "(check the name with 'splat-slam-topic list' and ROS_DOMAIN_ID)")
        rclpy.spin_once(node, timeout_sec=0.05)


def _fmt_num(x) -> str:
    if isinstance(x, float):
        return f"{x:.6g}"
    return str(x)


def _summarise_array(a: np.ndarray, typename: str, max_bytes: int) -> str:
    n = a.size
    if a.nbytes <= max_bytes:
        return "[" + ", ".join(_fmt_num(v) for v in a.tolist()) + "]"
    s = f"{typename}[{n}] ({_fmt_size(a.nbytes)})"
    if n and a.dtype.kind in "fiub":
        af = a.astype(np.float64, copy=False)
        fin = np.isfinite(af)
        if fin.any():
            v = af[fin]
            s += f" min={_fmt_num(float(v.min()))} max={_fmt_num(float(v.max()))} mean={_fmt_num(float(v.mean()))}"
        if not fin.all():
            s += f" non-finite={int((~fin).sum())}"
    return s


_ARRAY_NAMES = {"b": "int8", "B": "uint8", "h": "int16", "H": "uint16", "i": "int32", "I": "uint32",
                "l": "int64", "L": "uint64", "q": "int64", "Q": "uint64", "f": "float32",
                "d": "float64"}


def _fmt_size(n: int) -> str:
    for unit, f in (("MB", 1e6), ("kB", 1e3)):
        if n >= f:
            return f"{n / f:.2f} {unit}"
    return f"{n} B"


def summarise(msg, max_bytes: int = 64, indent: int = 0) -> List[str]:
    """Compact, YAML-like lines for any ROS message; long arrays are summarised."""
    pad = "  " * indent
    lines: List[str] = []
    fields = msg.get_fields_and_field_types()
    for name, ftype in fields.items():
        v = getattr(msg, name)
        if ftype == "builtin_interfaces/Time" or ftype == "builtin_interfaces/Duration":
            lines.append(f"{pad}{name}: {v.sec}.{v.nanosec:09d}")
        elif hasattr(v, "get_fields_and_field_types"):
            sub = summarise(v, max_bytes, indent + 1)
            flat = ", ".join(s.strip() for s in sub)
            if len(flat) <= 100 and all(":" in s and not s.rstrip().endswith(":") for s in sub):
                lines.append(f"{pad}{name}: {{{flat}}}")
            else:
                lines.append(f"{pad}{name}:")
                lines.extend(sub)
        elif isinstance(v, array.array):
            lines.append(f"{pad}{name}: " + _summarise_array(
                np.frombuffer(v, dtype=v.typecode) if len(v) else np.zeros(0),
                _ARRAY_NAMES.get(v.typecode, v.typecode), max_bytes))
        elif isinstance(v, np.ndarray):
            lines.append(f"{pad}{name}: " + _summarise_array(v, str(v.dtype), max_bytes))
        elif isinstance(v, (bytes, bytearray)):
            lines.append(f"{pad}{name}: " + _summarise_array(
                np.frombuffer(bytes(v), np.uint8), "uint8", max_bytes))
        elif isinstance(v, (list, tuple)):
            if v and hasattr(v[0], "get_fields_and_field_types"):
                lines.append(f"{pad}{name}: {type(v[0]).__name__}[{len(v)}]"
                             + (", first:" if v else ""))
                lines.extend(summarise(v[0], max_bytes, indent + 1))
            elif len(v) <= 8:
                lines.append(f"{pad}{name}: [" + ", ".join(repr(x) if isinstance(x, str)
                                                           else _fmt_num(x) for x in v) + "]")
            else:
                try:
                    lines.append(f"{pad}{name}: " + _summarise_array(np.asarray(v), ftype, 0))
                except (TypeError, ValueError):
                    lines.append(f"{pad}{name}: {ftype}[{len(v)}]")
        elif isinstance(v, str):
            s = v if len(v) <= 80 else v[:77] + "..."
            lines.append(f"{pad}{name}: {s!r}")
        else:
            lines.append(f"{pad}{name}: {_fmt_num(v)}")
    return lines


# ------------------------------------------------------------------ commands
def _node(rclpy, name: str):
    return rclpy.create_node(f"{name}_{int(time.time() * 1000) % 100000}",
                             enable_rosout=False, start_parameter_services=False)


def _open_topic(args, node_name: str):
    """(rclpy, node, full topic name, type name, message class) once ``args.topic`` has a
    publisher (rclpy is imported here: after main() applied the ROS environment)."""
    import rclpy
    topic = _full_name(args.topic)
    node = _node(rclpy, node_name)
    type_name = _wait_for_topic(node, topic, args.timeout)
    return rclpy, node, topic, type_name, _import_type(type_name)


def cmd_list(args) -> int:
    import rclpy
    node = _node(rclpy, "splat_topic_list")
    t0 = time.monotonic()
    while time.monotonic() - t0 < args.wait:     # let discovery finish (~0.55 s with the profile)
        rclpy.spin_once(node, timeout_sec=0.05)
    for name, types in sorted(node.get_topic_names_and_types()):
        if args.verbose:
            print(f"{name}  [{', '.join(types)}]  publishers={node.count_publishers(name)} "
                  f"subscribers={node.count_subscribers(name)}")
        else:
            print(name)
    sys.stdout.flush()
    return 0


def cmd_echo(args) -> int:
    from rclpy.serialization import deserialize_message

    from splat_slam_nodes.qos import matching_subscription_qos
    rclpy, node, topic, type_name, cls = _open_topic(args, "splat_topic_echo")
    got = []

    def cb(raw: bytes):
        got.append(raw)
        m = deserialize_message(raw, cls)
        print(f"--- {topic}  {type_name}  ({_fmt_size(len(raw))})  #{len(got)}")
        print("\n".join(summarise(m, args.max_bytes)), flush=True)

    node.create_subscription(cls, topic, cb, matching_subscription_qos(node, topic), raw=True)
    limit = 1 if args.once else args.count
    t0 = time.monotonic()
    while limit <= 0 or len(got) < limit:
        rclpy.spin_once(node, timeout_sec=0.1)
        if args.once and not got and time.monotonic() - t0 > args.timeout:
            print(f"error: no message on {topic} within {args.timeout:g} s", file=sys.stderr)
            return 1
    return 0


def cmd_hz(args) -> int:
    from splat_slam_nodes.qos import matching_subscription_qos
    rclpy, node, topic, type_name, cls = _open_topic(args, "splat_topic_hz")
    stamps: deque = deque(maxlen=args.window + 1)
    sizes: deque = deque(maxlen=args.window)
    total = [0]

    def cb(raw: bytes):                          # raw: measure transport, not deserialisation
        stamps.append(time.monotonic())
        sizes.append(len(raw))
        total[0] += 1

    node.create_subscription(cls, topic, cb, matching_subscription_qos(node, topic, depth=100),
                             raw=True)
    t0 = time.monotonic()
    next_report = t0 + args.period
    while args.duration <= 0 or time.monotonic() - t0 < args.duration:
        rclpy.spin_once(node, timeout_sec=0.02)
        now = time.monotonic()
        if now >= next_report:
            next_report = now + args.period
            print(_hz_line(stamps, sizes), flush=True)
    if next_report - time.monotonic() < args.period - 0.2:     # final report at --duration
        print(_hz_line(stamps, sizes), flush=True)
    if total[0] == 0:
        print(f"error: no message on {topic} within {args.duration:g} s", file=sys.stderr)
        return 1
    return 0


def _hz_line(stamps, sizes) -> str:
    if len(stamps) < 2:
        return "no new messages" if not stamps else "waiting for a second message"
    t = np.array(stamps)
    dt = np.diff(t)
    rate = 1.0 / dt.mean() if dt.mean() > 0 else math.inf
    bw = sum(sizes) / max(t[-1] - t[0], 1e-9)
    return (f"average rate: {rate:.3f} Hz  min: {dt.min():.4f} s  max: {dt.max():.4f} s  "
            f"std dev: {dt.std():.4f} s  window: {len(dt)}  bandwidth: {_fmt_size(bw)}/s")


# ------------------------------------------------------------------ CLI
def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="splat-slam-topic",
        description="List, echo and measure ROS 2 topics of splat_slam_ros (the ros2 CLI is not "
                    "on PyPI). Uses the project's Fast DDS profile and ROS_DOMAIN_ID from the "
                    "environment, like every splat_slam_ros process.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  splat-slam-topic list -v\n"
               "  splat-slam-topic echo /splat/keyframes --once\n"
               "  splat-slam-topic hz /camera/image_raw --window 50")
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("list", help="print the topics seen on this ROS_DOMAIN_ID")
    p.add_argument("-v", "--verbose", action="store_true", help="also type, publisher/subscriber counts")
    p.add_argument("--wait", type=float, default=1.0, help="discovery time before printing (s, default 1)")
    p = sub.add_parser("echo", help="print compact summaries of a topic's messages "
                                    "(long arrays as type[n] min/max/mean)")
    p.add_argument("topic")
    p.add_argument("--once", action="store_true", help="print one message and exit")
    p.add_argument("--count", type=int, default=0, help="exit after N messages (0 = run until Ctrl-C)")
    p.add_argument("--max-bytes", type=int, default=64,
                   help="arrays up to this many bytes are printed in full, longer ones summarised "
                        "(default 64)")
    p.add_argument("--timeout", type=float, default=5.0,
                   help="seconds to wait for a publisher (and, with --once, for a message)")
    p = sub.add_parser("hz", help="print the receive rate of a topic (and its bandwidth)")
    p.add_argument("topic")
    p.add_argument("--window", type=int, default=100, help="messages the statistics use (default 100)")
    p.add_argument("--period", type=float, default=1.0, help="seconds between reports (default 1)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after S seconds (0 = until Ctrl-C)")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for a publisher")
    return ap


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "window", 2) < 1:
        print("error: --window must be >= 1", file=sys.stderr)
        return 2
    try:
        apply_ros_environment()                   # before rclpy is imported / initialised
    except RosEnvError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    cmd = {"list": cmd_list, "echo": cmd_echo, "hz": cmd_hz}[args.cmd]
    return run_rclpy_tool(lambda: cmd(args), (TopicToolError,), interrupted=0)


if __name__ == "__main__":
    sys.exit(main())
