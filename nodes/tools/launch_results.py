"""The end of a finished graph run (splat-slam-launch): metrics.json (frames, pose latency,
per-node CPU / RSS / restarts, the evaluation against the bag's ground truth), the summary
lines, the report and the exit status (:func:`finish`). ``L`` is the
:class:`~splat_slam_nodes.tools.launch.Launcher` whose run ended."""
from __future__ import annotations

import sys
from typing import Dict, Optional


def node_stats(L) -> Dict[str, dict]:
    out = {}
    for n, c in L.children.items():
        out[n] = {"cpu_s": round(c.cpu_s(), 2), "peak_rss_mb": round(c.peak_rss / 2**20, 1),
                  "restarts": c.restarts}
        dropped = [d["dropped_inputs"] for d in L.events
                   if d.get("node") == n and isinstance(d.get("dropped_inputs"), int)]
        if dropped:                       # malformed messages it dropped (latest event)
            out[n]["dropped_inputs"] = dropped[-1]
    return out


def write_metrics(L, end_wall: float) -> dict:
    from splat_slam_ros.pipeline import _write_json, frame_counts
    eos = L.has_event("player", "end_of_stream") or {}
    mapper = (L.has_event("mapper", "saved") or {}).get("metrics", {})
    trk = L.has_event("tracker", "saved") or {}
    frames = int(eos.get("frames", trk.get("frames", 0)) or 0)
    wall = end_wall - (L.t_play or L.t0)
    m = {"mode": "graph", "dataset": (L.bag.info.get("name") if L.bag else "live"),
         "player_mode": L.args.mode}
    m.update(mapper)
    m["frames"] = frames
    m.update(frame_counts(trk.get("frames"), trk.get("dropped"), trk.get("posed"),
                          trk.get("skipped"), trk.get("lost")))
    m["pose_latency_ms"] = trk.get("latency_ms") or {}
    lag = map_lag(trk.get("keyframe_arrival"),
                  (L.has_event("mapper", "saved") or {}).get("keyframe_mapped"))
    if lag:
        m["map_lag_s"] = lag
    if L.t_eos is not None and L.t_mapped is not None:
        m["map_done_after_stream_s"] = round(L.t_mapped - L.t_eos, 3)
    m["keyframes"] = trk.get("keyframes", 0)
    m.update({k: trk[k] for k in ("keyframes_per_s", "keyframe_causes") if k in trk})
    m["wall_s"] = round(wall, 3)
    m["wall_total_s"] = round(end_wall - L.t0, 3)
    m["fps"] = round(frames / max(wall, 1e-9), 3)
    m["nodes"] = node_stats(L)
    m["peak_rss_mb_sum"] = round(sum(v["peak_rss_mb"] for v in m["nodes"].values()), 1)
    if L.bag is None:
        m["evaluation_skipped"] = "live input: no ground truth"
    else:
        evaluate(L, m)
    if L.with_mapping and m.get("gaussians"):
        from splat_slam_ros.evaluation.run import evaluate_lpips
        evaluate_lpips(L.out_dir, L.cfg, m)      # lpips (null without a backbone)
    _write_json(L.out_dir / "metrics.json", m)
    return m


def map_lag(arrival, mapped) -> dict:
    """Map lag (s) per keyframe: its frame's arrival at the tracker -> its Gaussians in the
    map (the mapper mapped it), p50 / p95 / max over the keyframes both nodes reported
    (``frames``: how many); {} when there are none (a run without mapping)."""
    from ..camera_input import spread
    if not isinstance(arrival, dict) or not isinstance(mapped, dict):
        return {}
    lags = [float(mapped[k]) - float(arrival[k]) for k in arrival if k in mapped]
    out = spread(lags, 3)
    if out:
        out["keyframes"] = out.pop("frames")
    return out


def evaluate(L, m: dict) -> None:
    """ATE and depth L1 against the bag's ground truth into ``m``. A bag without ground
    truth poses: ``evaluation_skipped`` says so; any failure of the evaluation itself:
    ``evaluation_error`` (the launcher then exits 1), what it computed before stays."""
    try:
        from splat_slam_ros.io.bagio import BagDataset
        from splat_slam_ros.evaluation.run import evaluate_map_depth, evaluate_trajectories
        from splat_slam_ros.types import Intrinsics
        K = Intrinsics.from_yaml(L.intrinsics_file) if L.intrinsics_file else None
        ds = BagDataset(L.args.bag, topics={"image": L.bag_topics["image"]}, intrinsics=K)
        if ds.gt_trajectory() is None:
            m["evaluation_skipped"] = "no ground truth in the bag"
            return
        evaluate_trajectories(ds, L.out_dir, m)
        evaluate_map_depth(ds, L.out_dir, L.cfg, m)     # depth L1 vs the bag's
    except Exception as e:
        m["evaluation_error"] = f"{type(e).__name__}: {e}"


def no_map_reason(runs_mapper: bool, m: dict) -> Optional[str]:
    """A run whose own mapper node reported no map although the tracker made keyframes (the
    mapper finalised without mapping one: its "saved" event has no map metrics): an error,
    never a success without a map."""
    if not runs_mapper or not m.get("keyframes") or "gaussians" in m:
        return None
    return (f"the mapper wrote no map although the tracker made {m['keyframes']} keyframes "
            "(it finalised without mapping any: see the mapper's lines above)")


def finish(L, end_wall: float) -> int:
    """After a complete run: metrics.json, summary, report. The exit status: 0; 3 when
    there is no result (no keyframe or an empty map); 1 when the evaluation (or the LPIPS
    a configured backbone asked for) failed."""
    from splat_slam_ros.pipeline import _write_json, no_result_reason
    from splat_slam_ros.report.build import write_report
    L.mark_finished()
    m = write_metrics(L, end_wall)
    L.stop_children()
    m["nodes"] = node_stats(L)
    m["warnings"] = getattr(L.out, "lines", [])
    rc = 0
    from .launch_map import finish as session_finish
    reason = session_finish(L.session, L.out_dir, m, L.has_event("tracker", "saved"),
                            L.has_event("loop_closure", "finalized"))  # --load-map
    if reason is None and not (L.session or {}).get("localize"):
        reason = no_result_reason(L.cfg, m)  # never a success without keyframes or map
    if reason is None:
        reason = no_map_reason("mapper" in L.local_nodes, m)
    if reason:
        m["error"] = reason
        rc = 3
    elif m.get("evaluation_error") or m.get("lpips_error"):
        rc = 1                                 # an evaluation that was asked for failed
    _write_json(L.out_dir / "metrics.json", m)
    summary(L, m)
    L.say(f"report: {write_report(L.out_dir, L.cfg)[0]}")
    if reason:
        print(f"error: {reason}", file=sys.stderr)
    if m.get("evaluation_error"):
        print(f"error: the evaluation failed: {m['evaluation_error']} (metrics.json has "
              "what it computed)", file=sys.stderr)
    return rc


def summary(L, m: dict) -> None:
    from splat_slam_ros.pipeline import SUMMARY_METRICS, keyframe_line
    L.say(f"frames {m['frames']}  keyframes {m['keyframes']}  wall {m['wall_s']:.1f} s  "
          f"{m['fps']:.2f} frames/s")
    kf_line = keyframe_line(m)
    if kf_line:
        L.say(kf_line)
    L.say(f"frames posed {m['frames_posed']} (tracked {m['frames_tracked']}, skipped "
          f"{m['frames_skipped']}, lost {m['frames_lost']}), dropped "
          f"{m['frames_dropped']}")
    lat = m.get("pose_latency_ms") or {}
    if lat:
        L.say(f"pose latency p50 {lat['p50']:.0f} ms, p95 {lat['p95']:.0f} ms, "
              f"max {lat['max']:.0f} ms")
    lag = m.get("map_lag_s") or {}
    if lag:
        L.say(f"map lag (keyframe's frame arrived -> mapped) p50 {lag['p50']:.1f} s, p95 "
              f"{lag['p95']:.1f} s, max {lag['max']:.1f} s over {lag['keyframes']} keyframes")
    for k in SUMMARY_METRICS:
        if isinstance(m.get(k), (int, float)):
            L.say(f"{k} {m[k]:.4f}")
    L.say("per node: " + ", ".join(f"{n} cpu {v['cpu_s']:.1f} s rss {v['peak_rss_mb']:.0f} MB"
                                   + (f" restarts {v['restarts']}" if v["restarts"] else "")
                                   + (f" dropped {v['dropped_inputs']} malformed input(s)"
                                      if v.get("dropped_inputs") else "")
                                   for n, v in m["nodes"].items()))
    if m.get("evaluation_skipped"):
        L.say(f"no evaluation: {m['evaluation_skipped']}")
    L.say(f"outputs in {L.out_dir}")
