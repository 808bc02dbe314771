"""Publisher for the splat-slam-topic test in tests/test_msgs_dds.py: a small rgb8 Image at --rate Hz on
/NS/image and one Keyframe (RELIABLE + TRANSIENT_LOCAL) on /NS/keyframes, for --duration s."""
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import dds_common  # noqa: E402  (applies the ROS environment: before rclpy)
import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402
from splat_slam_msgs.msg import Keyframe  # noqa: E402

from splat_slam_nodes import convert, qos  # noqa: E402


def main():
    a = dds_common.parse_args(rate=20.0, duration=15.0)
    import dds_payloads
    kf = convert.keyframe_to_msg(dds_payloads.keyframe(3))
    img = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    rclpy.init()
    node = rclpy.create_node("splat_topic_test_pub")
    pk = node.create_publisher(Keyframe, f"/{a.ns}/keyframes", qos.keyframe_qos())
    pi = node.create_publisher(Image, f"/{a.ns}/image", qos.image_qos())
    pk.publish(kf)
    print("ready", flush=True)
    t0 = time.monotonic()
    i = 0
    while time.monotonic() - t0 < a.duration and rclpy.ok():   # SIGTERM shuts rclpy down
        try:
            pi.publish(convert.image_to_msg(img, stamp=time.time(), frame_id=str(i)))
        except Exception:                  # context shut down by a signal meanwhile
            break
        i += 1
        nxt = t0 + i / a.rate
        time.sleep(max(0.0, nxt - time.monotonic()))
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
