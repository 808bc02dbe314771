"""The node worker: one thread that runs a node's core work in arrival order, and the
newest-per-keyframe queue of live input (:class:`NewestWaiting`). Re-exported by
``node_common``."""
from __future__ import annotations

import queue
import threading
import traceback
from typing import Any, Callable, Dict, Optional, Tuple

from splat_slam_ros.config import ConfigError


class NewestWaiting:
    """Messages waiting on a worker, the newest one per key: a message whose key already
    waits replaces the waiting one when it is newer (``order``: a revision) and is not queued
    again; the job queued for the first takes whichever is newest when it runs. The caller
    holds a lock around both calls (the executor offers, the worker takes)."""

    def __init__(self):
        self.items: Dict[int, Tuple[int, Any]] = {}

    def offer(self, key: int, msg: Any, order: int) -> bool:
        """Keep ``msg`` for ``key``; True when nothing waited for ``key`` (queue a job)."""
        old = self.items.get(key)
        if old is None or order > old[0]:
            self.items[key] = (order, msg)
        return old is None

    def take(self, key: int) -> Any:
        return self.items.pop(key)[1]

    def __iter__(self):
        return iter(list(self.items))

    def __len__(self) -> int:
        return len(self.items)


class Worker:
    """One thread that runs the node's core work in arrival order (callbacks only enqueue),
    so receiving never stalls behind a long mapping / BA step. ``lock`` serialises core
    access with service callbacks. ``idle`` (optional: ``(wanted, work)`` callables) is work
    done in short pieces while nothing is queued (the mapper's background steps on live
    input); queued work always goes first."""

    def __init__(self, owner: "SplatNode"):  # noqa: F821 (node_common.SplatNode)
        self.owner = owner
        self.q: "queue.Queue" = queue.Queue()
        self.lock = threading.RLock()
        self.thread = threading.Thread(target=self._run, name=f"{owner.name}-worker", daemon=True)
        self._stop = threading.Event()
        self.fatal_rc = 0
        self.busy = False
        self.dropped = 0                 # malformed inputs dropped (graph events -> metrics)
        self._drop_lock = threading.Lock()
        self.idle: Optional[Tuple[Callable[[], bool], Callable[[], None]]] = None

    def _take(self):
        """The next queued job; while none is queued and ``idle`` wants to work, a piece of it."""
        if self.idle is not None:
            try:
                return self.q.get_nowait()
            except queue.Empty:
                wanted, work = self.idle
                if wanted():
                    return (work, (), {}, False)
        return self.q.get()

    def start(self) -> None:
        if not self.thread.is_alive():
            self.thread.start()

    def stop(self) -> None:
        self._stop.set()
        self.q.put(None)
        if self.thread.is_alive() and threading.current_thread() is not self.thread:
            self.thread.join(timeout=5)

    def submit(self, fn: Callable, *args, **kw) -> None:
        self.q.put((fn, args, kw, False))

    def submit_final(self, fn: Callable, *args, **kw) -> None:
        """A job of the node's finalisation: an error in it stops the node (exit status 1),
        since nothing would save the run's results after it and the launcher would wait."""
        self.q.put((fn, args, kw, True))

    def pending(self) -> int:
        return self.q.qsize()

    def count_drop(self) -> None:
        with self._drop_lock:
            self.dropped += 1

    def _fatal(self, rc: int, text: str) -> None:
        """Stop the node: exit status ``rc`` once spin returns."""
        import rclpy
        self.fatal_rc = rc
        self.owner.log.fatal(text)
        rclpy.try_shutdown()

    def _run(self) -> None:
        import rclpy
        while not self._stop.is_set():
            item = self._take()
            if item is None:
                break
            fn, args, kw, final = item
            self.busy = True
            try:
                with self.lock:
                    fn(*args, **kw)
            except SystemExit as e:          # a core stage cannot go on: stop the node
                self._fatal(int(e.code or 1), f"stopping: exit status {int(e.code or 1)}")
                break
            except ConfigError as e:         # the stage cannot run so configured: stop the node
                self._fatal(2, f"configuration error: {e}")
                break
            except ValueError as e:          # one malformed input (ConversionError, MapError...)
                if not rclpy.ok():
                    break
                self.count_drop()
                self.owner.warn_throttled(f"work:{type(e).__name__}",
                                          f"dropped input ({getattr(fn, '__name__', 'task')}): "
                                          f"{type(e).__name__}: {e}")
            except Exception as e:
                if not rclpy.ok():
                    break
                self.owner.log.error(f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=6)}")
                if final:                    # the node's results would never be saved
                    self._fatal(1, f"finalisation failed ({type(e).__name__}: {e}): stopping")
                    break
            finally:
                self.busy = False
