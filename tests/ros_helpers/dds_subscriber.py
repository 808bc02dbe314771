"""Subscriber side of tests/test_msgs_dds.py: receives raw CDR of every kind, checks the
contents against the deterministic payloads, prints one JSON line with the results."""
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import dds_common  # noqa: E402  (applies the ROS environment: before rclpy)
import rclpy  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402

import dds_payloads  # noqa: E402


def main():
    a = dds_common.parse_args(count=5, timeout=30.0)
    import splat_slam_nodes.convert  # noqa: F401  (import before timing: pulls torch lazily later)
    rclpy.init()
    node = rclpy.create_node("splat_dds_test_sub")
    raw = {k: [] for k in dds_common.KINDS}
    types = dds_common.topic_types()
    subs = []
    for k, (t, q) in types.items():
        subs.append(node.create_subscription(
            t, dds_common.topic_name(a.ns, k), lambda b, k=k: raw[k].append((time.monotonic(), b)),
            q, raw=True))
    t0 = time.monotonic()
    while any(len(v) < a.count for v in raw.values()) and time.monotonic() - t0 < a.timeout:
        rclpy.spin_once(node, timeout_sec=0.05)
    t_first = min((v[0][0] for v in raw.values() if v), default=t0)
    t_last = max((v[-1][0] for v in raw.values() if v), default=t0)
    res = {}
    for k, v in raw.items():
        items = []
        for _, b in v:
            m = deserialize_message(b, types[k][0])
            i = dds_payloads.index_of(k, m)
            # content checksum of the decoded fields (CDR bytes differ in alignment padding)
            items.append(dict(i=i, sha=dds_payloads.digest(m), bytes=len(b),
                              ok=bool(dds_payloads.contents_equal(k, m, i))))
        res[k] = items
    print(json.dumps(dict(event="received", received=res,
                          transfer_s=round(t_last - t_first, 3))), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
