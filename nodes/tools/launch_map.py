"""Maps across sessions in the graph: ``splat-slam-launch ... --load-map RUN [--localize]``.

The session the run in ``RUN`` saved (``RUN/session/``: a ``splat-slam-run`` or a
``splat-slam-launch`` run, both write one) is checked before any node starts: a missing or
corrupt session, or (without ``--localize``) one without a map state, is a usage error
(exit 2). The nodes get ``node.load_map``:

- ``--localize``: only the tracker runs (the map is read-only); it relocalises each frame in
  the session's keyframes and publishes poses in the loaded map's frame
  (:class:`splat_slam_ros.localize.LocalizeRole`). Outputs: trajectory_full.txt (the posed
  frames), a byte-identical copy of the loaded map.ply, metrics.json ``localize``.
- without it (extend): the tracker continues the session (ExtendTracker), the loop closer
  holds the loaded keyframes fixed, the mapper starts from the loaded map; outputs as a full
  run, with a session of the extended map; metrics.json ``extend``.

Either way the camera must be the session's (the tracker node stops with exit 2 naming the
differing values), the tracker publishes a ``relocalised`` graph event and ``map -> odom``
carries the relocalisation (nodes/tf_frames.py). A run in which no frame was relocalised
ends with exit 3 and removes the outputs its nodes wrote (never a map or trajectory in
another frame); metrics.json says why.
"""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Dict, List, Optional


class LoadMapError(ValueError):
    """A --load-map / --localize usage error or an unusable session (exit 2)."""


def check_args(args) -> None:
    if args.localize and not args.load_map:
        raise LoadMapError("--localize needs --load-map RUN (the run whose saved map to "
                           "localize in)")
    if not args.load_map:
        return
    if not args.out:
        raise LoadMapError("--load-map needs --out (where the outputs go)")
    if Path(args.load_map).resolve() == Path(args.out).resolve():
        raise LoadMapError("--load-map and --out are the same directory: the new run would "
                           "overwrite the map it loads; choose another --out")
    if args.tracking_only and not args.localize:
        raise LoadMapError("--tracking-only cannot extend a map (--load-map without --localize "
                           "grows the map); use --localize to track in it")
    if args.resume:
        raise LoadMapError("--resume is not available with --load-map: start the run again "
                           "(--fresh discards the state of the one that did not finish)")


def load_info(run: Path, localize: bool, cfg, overrides: Dict[str, object]) -> dict:
    """The session in ``run`` checked (LoadMapError); for an extend run the mapping settings
    of :data:`splat_slam_ros.extend.EXTEND_MAPPING` applied to ``cfg`` and ``overrides``
    where neither sets them. The launcher's description of the loaded session."""
    from splat_slam_ros.io.session import SessionError, load_session, map_state
    run = Path(run).resolve()
    try:
        session = load_session(run)
        if not localize:
            map_state(session)          # the map to extend: present and intact
    except SessionError as e:
        raise LoadMapError(str(e)) from None
    notes: List[str] = []
    mapping: Dict[str, object] = {}
    if not localize:
        from splat_slam_ros.extend import extend_config
        notes = extend_config(cfg, overrides)
        for note in notes:              # "mapping.KEY VALUE"
            full = note.split(" ", 1)[0]
            key = full.split(".", 1)[1]
            mapping[key] = overrides[full] = getattr(cfg.mapping, key)
    st = session.manifest.get("map_state") or {}
    return {"run": str(run), "localize": bool(localize), "notes": notes, "mapping": mapping,
            "keyframes": len(session.keyframes), "map": session.map_path,
            "loaded": {"keyframes": len(session.keyframes),
                       "mapped_keyframes": st.get("mapped_keyframes"),
                       "gaussians": st.get("gaussians")}}


def plan(args, cfg, overrides: Dict[str, object], out_dir: Optional[Path]) -> Optional[dict]:
    """Check the options and the session (LoadMapError); remove what an earlier run left in
    ``out_dir`` that this one would not replace. :func:`load_info`, or None."""
    from splat_slam_ros.io.session import remove_session
    check_args(args)
    if out_dir is None:
        return None
    remove_session(out_dir)             # an earlier run's session must not outlive its outputs
    if not args.load_map:
        return None
    info = load_info(Path(args.load_map), bool(args.localize), cfg, overrides)
    if args.localize:                   # outputs an earlier run left that this one does not write
        for name in ("trajectory_keyframes.txt", "map.ply", "map_mesh.ply"):
            (out_dir / name).unlink(missing_ok=True)
    return info


def node_params(info: Optional[dict], name: str) -> Dict[str, object]:
    """The ``node.*`` parameters of node ``name`` for the loaded session."""
    if info is None or name not in ("tracker", "loop_closure", "mapper"):
        return {}
    p: Dict[str, object] = {"node.load_map": info["run"]}
    if name == "tracker":
        p["node.localize"] = info["localize"]
    return p


def finish(info: Optional[dict], out_dir: Path, m: dict, tracker_saved: Optional[dict],
           loop_final: Optional[dict]) -> Optional[str]:
    """metrics.json's ``localize`` / ``extend`` part from the tracker's ``saved`` event
    (``session``) and the loop closer's ``finalized`` (loop edges); copies the loaded map in
    localize runs. Returns the error of a run that never relocalised (its outputs removed),
    else None."""
    if info is None:
        return None
    s = (tracker_saved or {}).get("session") or {}
    lc = loop_final or {}
    part = dict(s, session=info["run"], loaded=info["loaded"])
    if info["localize"]:
        m["localize"] = part
        if info["map"] is not None and s.get("relocalised_frame") is not None:
            shutil.copyfile(info["map"], out_dir / "map.ply")    # the map, never re-optimised
    else:
        mp = m.get("map") if isinstance(m.get("map"), dict) else {}
        part.update(gaussians=mp.get("gaussians"), mapped_keyframes=mp.get("keyframes"),
                    loop_edges=lc.get("loop_edges"),
                    loop_edges_to_loaded=lc.get("loop_edges_to_loaded"))
        m["extend"] = part
    if s.get("relocalised_frame") is not None:
        return None
    from splat_slam_ros.extend import never_relocalised
    from splat_slam_ros.io.session import remove_session
    for name in ("trajectory_full.txt", "trajectory_keyframes.txt", "map.ply", "map_mesh.ply"):
        (out_dir / name).unlink(missing_ok=True)
    shutil.rmtree(out_dir / "renders", ignore_errors=True)
    remove_session(out_dir)
    return never_relocalised(int(m.get("frames_received") or 0), info["keyframes"])
