"""The saved session of a run (``OUT/session/``), which a later run loads to localise in.

Files: ``manifest.json`` (format name and version, package version, camera, tracking and BA
image sizes, the configuration, counts, and a sha256 per file) and ``keyframes.npz`` (per
keyframe: id, frame index, timestamp, camera-to-world pose, BA-grid disparity, the
tracking-size image the flow front end prepares, and a place-recognition descriptor). The
map is the run's ``map.ply``, referenced by checksum (none in a tracking-only run). A full
run also writes ``map_state.npz``: the mapper's state (Gaussians with their bookkeeping, the
mapped keyframes' poses, exposures, images and proxy depths, the mapping window), which a
later run that extends the map restores (:func:`map_state`); the mapping camera is in the
manifest. With a loop closer the manifest also holds the loop-closure graph (``loop_graph``:
edges with their kind, accepted loop pairs, merged keyframes), which an extend run keeps.

Plain numpy / json: :func:`load_session` validates everything (presence, checksums, version,
keys and shapes) and raises :class:`SessionError` with one line naming what is wrong.
"""
from __future__ import annotations

import hashlib
import io
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from splat_slam_ros.imaging import image_at, to_gray
from splat_slam_ros.types import Intrinsics, KeyframeData

FORMAT = "splat-slam-session"
VERSION = 1
SESSION_DIR = "session"
MANIFEST = "manifest.json"
KEYFRAMES = "keyframes.npz"
MAP = "map.ply"
MAP_STATE = "map_state.npz"
LOCK = ".lock"                      # held while the manifest is merged (_merge_manifest)
META_KEY = "meta_json"              # map_state.npz: the mapper's JSON metadata as bytes
NPZ_LEVEL = 1                       # zlib level of the .npz files (_write_npz)
NPZ_CHUNK = 1 << 20                 # bytes handed to the compressor at a time (_write_npz)
# map_state.npz: kf<k>_<name> per mapped keyframe (mapping/persistence.py: keyframe_depth)
KEYFRAME_DEPTH = ("depth", "valid", "width", "weight")
DESCRIPTOR_SIZE = (16, 12)          # (w, h) of the grey thumbnail descriptor
ARRAYS = ("kf_ids", "frame_indices", "timestamps", "poses", "disparities", "images",
          "descriptors")


class SessionError(ValueError):
    """A saved session is missing, unreadable, corrupt, of another version or camera."""


@dataclass
class SessionKeyframes:
    kf_ids: np.ndarray          # (N,) int64
    frame_indices: np.ndarray   # (N,) int64
    timestamps: np.ndarray      # (N,) float64
    poses: np.ndarray           # (N, 4, 4) float64 camera-to-world
    disparities: np.ndarray     # (N, h, w) float32 BA-grid disparity
    images: np.ndarray          # (N, H, W, 3) uint8 tracking-size images
    descriptors: np.ndarray     # (N, D) float32 unit-norm descriptors

    def __len__(self) -> int:
        return int(len(self.kf_ids))


@dataclass
class Session:
    path: Path                  # the session folder
    manifest: dict
    keyframes: SessionKeyframes
    map_path: Optional[Path]    # the checked map.ply, None for a tracking-only session


def descriptor(image: np.ndarray) -> np.ndarray:
    """Global place descriptor: the grey image shrunk to 16x12, zero-mean, unit-norm
    (their dot product is the normalised cross-correlation of the thumbnails)."""
    g = to_gray(image)
    t = cv2.resize(g.astype(np.float32), DESCRIPTOR_SIZE, interpolation=cv2.INTER_AREA).ravel()
    t = t - t.mean()
    n = float(np.linalg.norm(t))
    return (t / n if n > 1e-6 else t).astype(np.float32)


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _write_npz(path: Path, arrays: dict) -> None:
    """np.savez_compressed with fixed zip entry times: the same keyframes, the same bytes
    (and checksum) in every run. Deflate level 1: the map state of a 30-keyframe run in about
    half the time of the default level 6, 4 % larger (it is written when the map is done).
    Each entry is the .npy bytes as np.save writes them (version 1.0 header), streamed from
    the array in NPZ_CHUNK pieces: neither a copy of the array (a session's images: 15 MB)
    nor its whole compressed form is held, and the zip's bytes are those of one write."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, a in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info._compresslevel = NPZ_LEVEL     # what writestr(compresslevel=) sets
            a = np.asarray(a)                   # (0-d arrays stay 0-d)
            a = a if a.flags.c_contiguous else a.copy()
            if a.dtype.hasobject:
                raise ValueError(f"{name}: object arrays are not stored")
            head = io.BytesIO()
            fmt = np.lib.format
            fmt.write_array_header_1_0(head, fmt.header_data_from_array_1_0(a))
            data = memoryview(a.reshape(-1).view(np.uint8))
            info.file_size = head.tell() + data.nbytes      # the zip64 decision of one write
            with z.open(info, "w") as dest:
                dest.write(head.getvalue())
                for i in range(0, data.nbytes, NPZ_CHUNK):
                    dest.write(data[i:i + NPZ_CHUNK])


def _merge_manifest(d: Path, part: dict) -> None:
    """Merge ``part`` into ``d/manifest.json`` under a file lock: the keyframes and the map
    state may come from two processes (the tracker and mapper nodes), in either order."""
    import fcntl
    with open(d / LOCK, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        mf = d / MANIFEST
        m = json.loads(mf.read_text()) if mf.is_file() else {}
        files = dict(m.get("files") or {}, **part.pop("files", {}))
        m.update(part, files=files, format=FORMAT, version=VERSION)
        m.setdefault("map", None)
        m.setdefault("map_state", None)
        m["map_note"] = None if m["map"] else "no map in this session (a tracking-only run)"
        tmp = mf.with_suffix(".tmp")
        tmp.write_text(json.dumps(m, indent=2, default=str))
        tmp.replace(mf)


def write_session_keyframes(out: Path, kfs: SessionKeyframes, camera: Intrinsics,
                            tracking_size: Sequence[int], ba_size: Sequence[int], config: dict,
                            package_version: str) -> Path:
    """The tracker's part of ``out/session/``: keyframes.npz and the manifest's camera,
    sizes, counts and configuration. Returns the session folder."""
    d = Path(out) / SESSION_DIR
    d.mkdir(parents=True, exist_ok=True)
    _write_npz(d / KEYFRAMES, {k: getattr(kfs, k) for k in ARRAYS})
    _merge_manifest(d, {
        "package_version": package_version, "camera": camera.to_dict(),
        "tracking_size": [int(x) for x in tracking_size], "ba_size": [int(x) for x in ba_size],
        "keyframes": len(kfs),
        "frames": [int(kfs.frame_indices.min()), int(kfs.frame_indices.max())] if len(kfs)
        else None,
        "files": {KEYFRAMES: sha256(d / KEYFRAMES)}, "config": config})
    return d


def write_map_state(out: Path, arrays: Dict[str, np.ndarray], meta: dict,
                    camera: Intrinsics) -> Path:
    """The mapper's part of ``out/session/`` (after ``out/map.ply``): map_state.npz (the
    mapper's ``arrays`` and ``meta``: mapping.persistence.mapper_arrays), the map's checksum
    and the mapping ``camera`` in the manifest."""
    d = Path(out) / SESSION_DIR
    d.mkdir(parents=True, exist_ok=True)
    arrays = dict(arrays)
    # the metadata (window visibility lists: large) inside the file, not the manifest
    arrays[META_KEY] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    _write_npz(d / MAP_STATE, arrays)
    ply = Path(out) / MAP
    _merge_manifest(d, {
        "files": {MAP_STATE: sha256(d / MAP_STATE)},
        "map": {"path": f"../{MAP}", "sha256": sha256(ply), "bytes": ply.stat().st_size}
        if ply.is_file() else None,
        "map_state": {"camera": camera.to_dict(), "gaussians": len(arrays["means"]),
                      "mapped_keyframes": len(arrays["kf_ids"])}})
    return d


def write_loop_graph(out: Path, summary: dict) -> None:
    """The loop closer's part of ``out/session/``: the loop-closure graph
    (``LoopCloser.graph_summary``: edges, loop pairs, merged keyframes) in the manifest."""
    d = Path(out) / SESSION_DIR
    d.mkdir(parents=True, exist_ok=True)
    _merge_manifest(d, {"loop_graph": summary})


def loop_graph(session: Session) -> Optional[dict]:
    """The loop-closure graph the session holds (None: a run without a loop closer)."""
    g = session.manifest.get("loop_graph")
    return g if isinstance(g, dict) else None


def write_session(out: Path, kfs: SessionKeyframes, camera: Intrinsics,
                  tracking_size: Sequence[int], ba_size: Sequence[int], config: dict,
                  package_version: str, map_state: Optional[tuple] = None,
                  loop_summary: Optional[dict] = None) -> Path:
    """Write ``out/session/`` (keyframes.npz + manifest.json, map_state.npz of ``map_state``:
    the mapper's (arrays, metadata, camera), the loop-closure graph); the map is
    ``out/map.ply`` when it exists. Returns the session folder."""
    d = write_session_keyframes(out, kfs, camera, tracking_size, ba_size, config,
                                package_version)
    if map_state is not None:
        write_map_state(out, *map_state)
    if loop_summary is not None:
        write_loop_graph(out, loop_summary)
    return d


def remove_session(out: Path) -> None:
    """Remove the session files an earlier run left in ``out`` (a new run replaces them)."""
    for name in (MANIFEST, KEYFRAMES, MAP_STATE, LOCK):
        (Path(out) / SESSION_DIR / name).unlink(missing_ok=True)


def _read_manifest(d: Path, run_dir: Path) -> dict:
    mf = d / MANIFEST
    if not d.is_dir() or not mf.is_file():
        raise SessionError(f"no saved session in {run_dir} ({mf} not found; runs of "
                           f"splat-slam-run write one)")
    try:
        m = json.loads(mf.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise SessionError(f"session file {mf} is unreadable ({type(e).__name__})") from None
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        raise SessionError(f"session file {mf} is not a {FORMAT} manifest")
    v = m.get("version")
    if v != VERSION:
        raise SessionError(f"session file {mf} has format version {v!r}; this version of "
                           f"splat-slam reads version {VERSION} only")
    for key in ("camera", "tracking_size", "ba_size", "files"):
        if key not in m:
            raise SessionError(f"session file {mf} is corrupt (no {key!r})")
    return m


def _check_file(path: Path, want: Optional[str], what: str) -> None:
    if not path.is_file():
        raise SessionError(f"session file {path} is missing ({what})")
    if not isinstance(want, str) or sha256(path) != want:
        raise SessionError(f"session file {path} does not match its sha256 in {MANIFEST} "
                           f"(corrupt or changed since the session was saved)")


def _read_keyframes(path: Path, m: dict) -> SessionKeyframes:
    try:
        with np.load(path, allow_pickle=False) as z:
            a = {k: np.asarray(z[k]) for k in ARRAYS}
    except Exception as e:          # zip / npy errors of every kind: a corrupt file
        raise SessionError(f"session file {path} is unreadable ({type(e).__name__})") from None
    n = len(a["kf_ids"])
    bh, bw = int(m["ba_size"][1]), int(m["ba_size"][0])
    th, tw = int(m["tracking_size"][1]), int(m["tracking_size"][0])
    shapes = {"frame_indices": (n,), "timestamps": (n,), "poses": (n, 4, 4),
              "disparities": (n, bh, bw), "images": (n, th, tw, 3)}
    for k, s in shapes.items():
        if a[k].shape != s:
            raise SessionError(f"session file {path} is corrupt ({k} has shape "
                               f"{a[k].shape}, expected {s})")
    if n == 0 or n != m.get("keyframes"):
        raise SessionError(f"session file {path} holds {n} keyframes, the manifest says "
                           f"{m.get('keyframes')}")
    return SessionKeyframes(**a)


def load_session(run_dir: Path) -> Session:
    """Load and validate the session saved by the run in ``run_dir`` (SessionError)."""
    run_dir = Path(run_dir)
    d = run_dir / SESSION_DIR
    m = _read_manifest(d, run_dir)
    kp = d / KEYFRAMES
    _check_file(kp, m["files"].get(KEYFRAMES) if isinstance(m["files"], dict) else None,
                "the keyframes")
    kfs = _read_keyframes(kp, m)
    map_path = None
    if m.get("map"):
        map_path = (d / str(m["map"].get("path", f"../{MAP}"))).resolve()
        _check_file(map_path, m["map"].get("sha256"), "the map")
    return Session(d, m, kfs, map_path)


def pinhole_diffs(saved: dict, now: dict) -> List[str]:
    """'name saved vs now' for each of fx, fy, cx, cy, width, height (:meth:`Intrinsics.to_dict`
    layout) that differs by more than 1e-4 relative."""
    diffs: List[str] = []
    for k in ("fx", "fy", "cx", "cy", "width", "height"):
        a, b = saved.get(k), now[k]
        if not isinstance(a, (int, float)) or abs(float(a) - float(b)) > 1e-4 * max(1.0, abs(b)):
            diffs.append(f"{k} {a} vs {b}")
    return diffs


def camera_mismatch(session: Session, camera: Intrinsics, tracking_size: Sequence[int],
                    ba_size: Sequence[int]) -> List[str]:
    """'name session vs now' for each camera value / image size that differs (empty: same)."""
    saved, now = session.manifest["camera"], camera.to_dict()
    diffs = pinhole_diffs(saved, now)
    da, db = list(saved.get("distortion") or []), now["distortion"]
    if saved.get("distortion_model") != now["distortion_model"] and (da or db) or \
            len(da) != len(db) or any(abs(float(x) - y) > 1e-6 for x, y in zip(da, db)):
        diffs.append(f"distortion {saved.get('distortion_model')} {da} vs "
                     f"{now['distortion_model']} {db}")
    for name, a, b in (("tracking size", session.manifest["tracking_size"], tracking_size),
                       ("BA grid", session.manifest["ba_size"], ba_size)):
        if [int(x) for x in a] != [int(x) for x in b]:
            diffs.append(f"{name} {a[0]}x{a[1]} vs {b[0]}x{b[1]}")
    return diffs


def check_camera(session: Session, camera: Intrinsics, tracking_size: Sequence[int],
                 ba_size: Sequence[int]) -> None:
    diffs = camera_mismatch(session, camera, tracking_size, ba_size)
    if diffs:
        raise SessionError(f"the session in {session.path.parent} was made with another camera "
                           f"(saved vs this input): {', '.join(diffs)}")


def descriptor_ranking(session_desc: np.ndarray, desc: np.ndarray) -> np.ndarray:
    """Row indices of ``session_desc`` by similarity to ``desc``, best first."""
    return np.argsort(-(session_desc @ desc), kind="stable")


def map_camera(session: Session) -> Intrinsics:
    """The mapping camera of the session's map state; SessionError when it has none (a
    tracking-only run)."""
    entry = session.manifest.get("map_state")
    if not isinstance(entry, dict) or MAP_STATE not in session.manifest["files"]:
        raise SessionError(f"the session in {session.path.parent} has no map to extend (a "
                           f"tracking-only run); --localize tracks in its keyframes without "
                           f"a map")
    try:
        return Intrinsics.from_dict(entry["camera"])
    except (KeyError, TypeError, ValueError):
        raise SessionError(f"session file {session.path / MANIFEST} is corrupt (no mapping "
                           f"camera)") from None


def map_state(session: Session) -> Tuple[Dict[str, np.ndarray], dict, Intrinsics]:
    """The mapper state a full run saved (arrays, metadata, the mapping camera), checked
    against its checksum; SessionError when the session has none (a tracking-only run) or
    the file is corrupt."""
    cam = map_camera(session)
    path = session.path / MAP_STATE
    _check_file(path, session.manifest["files"].get(MAP_STATE), "the mapper state")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: np.asarray(z[k]) for k in z.files}
        meta = json.loads(bytes(arrays.pop(META_KEY)).decode())
        missing = [k for k in ("means", "kf_ids", "kf_pose") if k not in arrays]
        missing += [f"kf{k}_{n}" for k in arrays.get("kf_ids", []) for n in
                    ("image",) + KEYFRAME_DEPTH[:3] if f"kf{k}_{n}" not in arrays]
    except Exception as e:          # zip / npy / key errors of every kind: a corrupt state
        raise SessionError(f"session file {path} is unreadable ({type(e).__name__})") from None
    if missing:
        raise SessionError(f"session file {path} is corrupt (no {missing[0]!r})")
    return arrays, meta, cam


def keyframe_data(kfs: SessionKeyframes, intrinsics: Intrinsics) -> List[KeyframeData]:
    """Session keyframes as the stages take keyframes: images resized to ``intrinsics``'
    size (a graph node gets the mapping camera, the tracker the tracking camera), BA-grid
    disparities, full confidence."""
    return [KeyframeData(kf_id=int(k), frame_index=int(kfs.frame_indices[n]),
                         timestamp=float(kfs.timestamps[n]), pose=kfs.poses[n].copy(),
                         image=image_at(kfs.images[n], intrinsics.width, intrinsics.height),
                         intrinsics=intrinsics,
                         disparity=kfs.disparities[n].astype(np.float32),
                         confidence=np.ones(kfs.disparities[n].shape, np.float32))
            for n, k in enumerate(kfs.kf_ids)]
