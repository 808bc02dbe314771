"""One DDS participant for the network-range test (run inside a private network namespace).

``graph SECS``: a node named ``splat_probe_graph`` with the environment it was given (the
project's, from ros_env), alive for SECS seconds. ``outsider SECS``: a node that looks for
``splat_probe_graph`` for up to SECS seconds; prints JSON ``{"seen": bool}``.
"""
import json
import sys
import time

import rclpy


def main() -> None:
    role, secs = sys.argv[1], float(sys.argv[2])
    rclpy.init()
    node = rclpy.create_node("splat_probe_" + role)
    t0, seen = time.monotonic(), False
    while time.monotonic() - t0 < secs:
        rclpy.spin_once(node, timeout_sec=0.1)
        if role == "outsider" and "splat_probe_graph" in node.get_node_names():
            seen = True
            break
    print(json.dumps({"role": role, "seen": seen}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
