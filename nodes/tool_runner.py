"""The rclpy session of the command-line tools (bag player, splat-slam-topic): init, run,
user errors as ``error: ...`` with exit status 2, clean exit on Ctrl-C / external shutdown.
rclpy is imported when a tool runs, after it applied the project's ROS environment."""
from __future__ import annotations

import sys
from typing import Callable, List, Optional, Tuple, Type


def is_shutdown_race(e: BaseException) -> bool:
    """A SIGINT / SIGTERM's shutdown that landed between an executor's context check and its
    wait-set creation: rclpy raises RCLError (a RuntimeError) there; that is a requested stop."""
    import rclpy
    return isinstance(e, RuntimeError) and not rclpy.ok()


def usage_error(*checks: Tuple[bool, str]) -> int:
    """The first of ``(broken, message)`` that is broken printed as ``error: message``: 2;
    0 when none is."""
    for broken, message in checks:
        if broken:
            print(f"error: {message}", file=sys.stderr)
            return 2
    return 0


def run_rclpy_tool(body: Callable[[], int], user_errors: Tuple[Type[BaseException], ...],
                   rclpy_args: Optional[List[str]] = None, interrupted: int = 130) -> int:
    """``rclpy.init(rclpy_args)``, ``body()``; returns its status, 2 for ``user_errors`` and
    ``interrupted`` when stopped by SIGINT / SIGTERM; rclpy is always shut down."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    rclpy.init(args=rclpy_args)
    try:
        return body()
    except user_errors as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        return interrupted
    except RuntimeError as e:
        if is_shutdown_race(e):
            return interrupted
        raise
    finally:
        rclpy.try_shutdown()
