"""Publisher side of tests/test_msgs_dds.py: waits for matched subscribers, publishes
``--count`` messages of every kind, waits until all are acknowledged, prints JSON lines."""
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import dds_common  # noqa: E402  (applies the ROS environment: before rclpy)
import rclpy  # noqa: E402
from rclpy.duration import Duration  # noqa: E402

import dds_payloads  # noqa: E402


def out(**kw):
    print(json.dumps(kw), flush=True)


def main():
    a = dds_common.parse_args(count=5, subs=1, match_timeout=20.0)   # subs: per topic
    # Build every message before DDS starts, so publishing is not slowed by imports.
    msgs = {k: [dds_payloads.build(k, i) for i in range(a.count)] for k in dds_common.KINDS}
    rclpy.init()
    node = rclpy.create_node("splat_dds_test_pub")
    pubs = {k: node.create_publisher(t, dds_common.topic_name(a.ns, k), q)
            for k, (t, q) in dds_common.topic_types().items()}
    t0 = time.monotonic()
    while any(p.get_subscription_count() < a.subs for p in pubs.values()):
        if time.monotonic() - t0 > a.match_timeout:
            out(event="error", what="no subscriber matched",
                counts={k: p.get_subscription_count() for k, p in pubs.items()})
            rclpy.try_shutdown()
            return 1
        time.sleep(0.01)
    out(event="matched", wait_s=round(time.monotonic() - t0, 3))
    sha = {k: [] for k in dds_common.KINDS}
    for i in range(a.count):
        for k in dds_common.KINDS:
            m = msgs[k][i]
            sha[k].append(dds_payloads.digest(m))
            pubs[k].publish(m)
    out(event="published", sha=sha)
    acked = {k: bool(p.wait_for_all_acked(Duration(seconds=15))) for k, p in pubs.items()}
    out(event="acked", acked=acked)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
