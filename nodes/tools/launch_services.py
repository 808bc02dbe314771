"""The launcher's services: a whole map saved or loaded across the graph's processes.

``/splat/save_map`` (SaveMap) writes into ``directory`` (relative to ``--out``, checked like
the mapper's save: nodes/service_guard.py) what a later run loads with ``--load-map``: the
tracker node its trajectories and the keyframes' part of ``session/``, the mapper node
``map.ply``, ``renders/``, its metrics and ``session/map_state.npz``. Each node answers with a
``map_saved`` graph event; the service answers once all did (or one failed, or
:data:`REPLY_TIMEOUT_S` passed).

``/splat/load_map`` (LoadMap) loads the session an earlier run saved in ``directory``
(relative to ``--out``), localize-only or extend, as ``--load-map`` does at start; the
session is checked first. It is taken only before the tracker has tracked a frame (a
robot starts the graph, then chooses the map): the tracker node decides (``map_loaded``
event), and on its yes the loop-closure and mapper nodes load the session's keyframes and
map (extend) and answer too.

Requests and answers are graph events carrying a ``request`` id. The services run on a node
and thread of their own, so the launcher's loop keeps receiving events (and supervising the
nodes) while a request waits.
"""
from __future__ import annotations

import itertools
import json
import time
from typing import Dict, List

from .. import service_guard as G
from ..node_common import SERVICES

REPLY_TIMEOUT_S = 300.0     # a save of a large map takes seconds; a node that died never answers


class LaunchServices:
    """The services on a node of their own, spun by a thread of their own: a request waits
    for the nodes' answers, which the launcher's main loop receives (:meth:`on_event`)."""

    def __init__(self, launcher):
        import threading

        from rclpy.executors import SingleThreadedExecutor
        from splat_slam_msgs.srv import LoadMap, SaveMap
        self.L = launcher
        self.node = n = launcher.rclpy.create_node("launch_services", enable_rosout=False)
        n.create_service(SaveMap, SERVICES["graph_save_map"], self.save)
        n.create_service(LoadMap, SERVICES["graph_load_map"], self.load)
        self.waiting: Dict[str, dict] = {}
        self.lock = threading.Lock()
        self.ids = itertools.count(1)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(n)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, name="launch_services", daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        """Spin in short steps until :meth:`close` (never shut the executor down under a
        running wait: the process would abort in rclpy's C++ layer)."""
        while not self.stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception:               # rclpy shut down under it: the launcher stops
                return

    def close(self) -> None:
        """Stop the thread, then the executor and the node (before rclpy shuts down)."""
        self.stop.set()
        with self.lock:                     # a request still waiting answers "no answer"
            for w in self.waiting.values():
                w["done"].set()
        self.thread.join(timeout=10.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()

    def on_event(self, d: dict) -> None:
        """An answer (``map_saved`` / ``map_loaded``) of a node to a pending request (the
        launcher's thread)."""
        if d.get("event") not in ("map_saved", "map_loaded"):
            return
        with self.lock:
            w = self.waiting.get(str(d.get("request")))
            if w is None:
                return
            w["replies"][str(d.get("node"))] = d
            if not d.get("ok") or w["need"] <= set(w["replies"]):
                w["done"].set()

    def _ask(self, event: str, need: List[str], **fields) -> List[dict]:
        """Publish ``event`` to the nodes and wait for the answers of ``need`` (fewer when
        one refused); a node that did not answer in time gets {"ok": False, ...}."""
        import threading
        rid = f"{id(self)}-{next(self.ids)}"
        w = {"need": set(need), "replies": {}, "done": threading.Event()}
        with self.lock:
            self.waiting[rid] = w
        d = {"node": "launch", "event": event, "t": time.time(), "request": rid, **fields}
        self.L.ev_pub.publish(self.L.String(data=json.dumps(d)))
        w["done"].wait(REPLY_TIMEOUT_S)
        with self.lock:
            del self.waiting[rid]
            replies = dict(w["replies"])
        out = [replies[n] for n in need if n in replies]
        if all(r.get("ok") for r in out):
            out += [{"node": n, "ok": False, "message": f"the {n} node did not answer within "
                     f"{REPLY_TIMEOUT_S:g} s"} for n in need if n not in replies]
        return out

    def _stages(self, loop: bool, mapper: bool) -> List[str]:
        """The running stages that answer a request: the tracker always."""
        L = self.L
        return ["tracker"] + (["loop_closure"] if loop and L.with_loop else []) + \
            (["mapper"] if mapper and L.with_mapping else [])

    @staticmethod
    def _answer(resp, replies: List[dict], done: str):
        bad = [r for r in replies if not r.get("ok")]
        resp.success = not bad
        resp.message = "; ".join(f"{r['node']}: {r.get('message')}" for r in bad) if bad \
            else done
        return resp

    def save(self, req, resp):
        L = self.L
        try:
            if L.session is not None and L.session["localize"]:
                raise G.ServiceInputError("localize-only: the loaded map is read-only (it is in "
                                          f"{L.session['run']})")
            d = G.save_dir(req.directory, L.out_dir)
        except G.ServiceInputError as e:
            resp.success, resp.message = False, str(e)
            return resp
        L.say(f"saving the map into {d}")
        replies = self._ask("save_map", self._stages(True, True), directory=str(d))
        return self._answer(resp, replies, f"saved into {d}: " + ", ".join(
            f for r in replies for f in r.get("files", [])) + " (splat-slam-launch / "
            "splat-slam-run --load-map loads it)")

    def load(self, req, resp):
        from .launch_map import LoadMapError, load_info
        L = self.L
        try:
            if L.session is not None:
                raise G.ServiceInputError(f"a map is loaded already ({L.session['run']})")
            run = G.save_dir(req.directory, L.out_dir)
            info = load_info(run, bool(req.localize), L.cfg, L.overrides)
        except (G.ServiceInputError, LoadMapError) as e:
            resp.success, resp.message = False, str(e)
            return resp
        extend = not info["localize"]
        replies = self._ask("load_map", self._stages(extend, extend), run=info["run"],
                                  localize=info["localize"], mapping=info["mapping"])
        if all(r.get("ok") for r in replies):
            L.session = info
            L.say(f"{'localizing' if info['localize'] else 'extending the map'} in the session "
                  f"of {info['run']} ({info['keyframes']} keyframes)")
        return self._answer(resp, replies, f"loaded the session of {run} "
                            f"({info['keyframes']} keyframes, "
                            f"{'localize-only' if info['localize'] else 'extend'}): the "
                            f"tracker relocalises in it from the next frame")
