"""Crash-safe, incremental persistence of a node's keyframes and map (no ROS needed).

Layout of one store directory (one per node, e.g. ``OUT/state/mapper``)::

    manifest.json          the committed state: record name -> file, plus node metadata
    r_<name>.<n>.npz       immutable array records (written once, never modified)

Every write goes to a temporary file in the same directory, is flushed and fsync'ed and
then renamed over its final name (``os.replace`` is atomic on POSIX). Records are
immutable; changing a record writes a new file with a new counter and then commits a new
manifest that points to it. A crash at any moment therefore leaves either the old or the
new manifest, both pointing to complete files; files not referenced by the committed
manifest (and stray temporaries) are removed at the next commit / open.

:class:`KeyframeStore` adds keyframe helpers on top: per keyframe an ``image`` record
(written once), a ``state`` record (pose, disparity, confidence, mono depth; rewritten on
updates) and a ``depth`` record (proxy depth + source mask). The mapper stores its state
here as arrays (mapping/persistence.py).
"""
from __future__ import annotations

import json
import os
import re
import threading
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np

from splat_slam_ros.types import Intrinsics, KeyframeData

MANIFEST = "manifest.json"
_REC = re.compile(r"^r_(?P<name>.+)\.(?P<n>\d+)\.npz$")


class StoreError(RuntimeError):
    """A store directory is unusable (unreadable manifest, missing record)."""


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(str(d), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes, fsync: bool = True) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same folder + rename)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    os.replace(tmp, path)
    if fsync:
        _fsync_dir(path.parent)


def atomic_save_npz(path: Path, fsync: bool = True, **arrays) -> None:
    """``np.savez`` (uncompressed) to ``path`` atomically."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        if fsync:
            os.fsync(f.fileno())
    os.replace(tmp, path)


class RecordStore:
    """Immutable npz records + an atomically replaced JSON manifest (see module doc)."""

    def __init__(self, directory, fsync: bool = True):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.fsync = fsync
        self._lock = threading.RLock()
        self._records: Dict[str, str] = {}
        self.meta: Dict[str, Any] = {}
        self._counter = 0
        self._load()
        self._gc()

    # ------------------------------------------------------------ manifest
    def _load(self) -> None:
        p = self.dir / MANIFEST
        if p.is_file():
            try:
                m = json.loads(p.read_text())
                self._records = dict(m.get("records", {}))
                self.meta = dict(m.get("meta", {}))
                self._counter = int(m.get("counter", 0))
            except (ValueError, TypeError) as e:
                raise StoreError(f"store manifest {p} is unreadable: {e}") from None
        for f in self.dir.iterdir():               # never reuse a counter on disk
            mm = _REC.match(f.name)
            if mm:
                self._counter = max(self._counter, int(mm.group("n")) + 1)

    @property
    def exists(self) -> bool:
        """True when something was committed before (a restarted node resumes)."""
        return bool(self._records) or bool(self.meta)

    def names(self) -> List[str]:
        with self._lock:
            return sorted(self._records)

    def has(self, name: str) -> bool:
        return name in self._records

    # ------------------------------------------------------------ records
    def stage(self, name: str, **arrays) -> str:
        """Write a new immutable record file for ``name`` (not yet committed)."""
        if not re.match(r"^[A-Za-z0-9_\-]+$", name):
            raise ValueError(f"record names use letters, digits, _ and - only: {name!r}")
        with self._lock:
            fname = f"r_{name}.{self._counter}.npz"
            self._counter += 1
        atomic_save_npz(self.dir / fname, fsync=self.fsync, **arrays)
        return fname

    def commit(self, staged: Optional[Dict[str, Optional[str]]] = None,
               meta: Optional[Dict[str, Any]] = None) -> None:
        """Atomically switch to a manifest with ``staged`` records (name -> file from
        :meth:`stage`, or None to delete) and ``meta`` merged in; then remove old files."""
        with self._lock:
            recs = dict(self._records)
            for k, v in (staged or {}).items():
                if v is None:
                    recs.pop(k, None)
                else:
                    recs[k] = v
            new_meta = dict(self.meta)
            new_meta.update(meta or {})
            body = json.dumps({"records": recs, "meta": new_meta, "counter": self._counter},
                              default=_json_default).encode()
            atomic_write_bytes(self.dir / MANIFEST, body, fsync=self.fsync)
            old = set(self._records.values()) - set(recs.values())
            self._records, self.meta = recs, new_meta
        for f in old:
            try:
                (self.dir / f).unlink()
            except OSError:
                pass

    def put(self, name: str, meta: Optional[Dict[str, Any]] = None, **arrays) -> None:
        """Stage + commit one record."""
        self.commit({name: self.stage(name, **arrays)}, meta)

    def get(self, name: str) -> Dict[str, np.ndarray]:
        with self._lock:
            f = self._records.get(name)
        if f is None:
            raise KeyError(name)
        try:
            with np.load(self.dir / f, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise StoreError(f"store record {self.dir / f} is unreadable: {e}") from None

    def delete(self, *names: str) -> None:
        self.commit({n: None for n in names})

    def clear(self) -> None:
        """Forget everything (e.g. a map reset)."""
        with self._lock:
            self.commit({n: None for n in self._records}, None)
            self.meta = {}
            self.commit({}, {})

    def _gc(self) -> None:
        keep = set(self._records.values()) | {MANIFEST}
        for f in self.dir.iterdir():
            if f.name in keep or not f.is_file():
                continue
            if _REC.match(f.name) or f.name.endswith(".tmp"):
                try:
                    f.unlink()
                except OSError:
                    pass


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (set, tuple)):
        return list(o)
    return str(o)


# ====================================================================== keyframes
def _intr_array(k: Intrinsics) -> np.ndarray:
    return np.array([k.fx, k.fy, k.cx, k.cy, k.width, k.height], np.float64)


class KeyframeStore(RecordStore):
    """Keyframes (image, pose, disparity, confidence, mono depth, proxy depth) + free state."""

    def put_keyframe(self, kf: KeyframeData, with_image: bool = True,
                     meta: Optional[Dict[str, Any]] = None) -> None:
        """Persist a new keyframe (image record written once, state record)."""
        staged = {}
        k = int(kf.kf_id)
        if with_image and not self.has(f"kf{k}_image"):
            intr = kf.intrinsics
            staged[f"kf{k}_image"] = self.stage(
                f"kf{k}_image", image=np.asarray(kf.image, np.uint8), intrinsics=_intr_array(intr),
                distortion=np.asarray(intr.distortion, np.float64),
                meta=np.array([kf.frame_index, kf.timestamp], np.float64))
        staged[f"kf{k}_state"] = self._stage_state(k, kf.frame_index, kf.timestamp, kf.pose,
                                                   kf.disparity, kf.confidence, kf.mono_depth,
                                                   kf.intrinsics)
        self.commit(staged, meta)

    def _stage_state(self, k, frame_index, timestamp, pose, disparity, confidence, mono, intr):
        arrays = dict(pose=np.asarray(pose, np.float64),
                      disparity=np.asarray(disparity, np.float32),
                      confidence=np.asarray(confidence, np.float32),
                      meta=np.array([frame_index, timestamp], np.float64),
                      intrinsics=_intr_array(intr),
                      distortion=np.asarray(intr.distortion, np.float64))
        if mono is not None:
            arrays["mono_depth"] = np.asarray(mono, np.float32)
        return self.stage(f"kf{k}_state", **arrays)

    def update_keyframe(self, kf_id: int, pose=None, disparity=None,
                        meta: Optional[Dict[str, Any]] = None, commit: bool = True):
        """New pose and/or disparity of a stored keyframe. Returns the staged dict (when
        ``commit`` is False, pass several to :meth:`commit` at once)."""
        k = int(kf_id)
        if not self.has(f"kf{k}_state"):
            return {}
        st = self.get(f"kf{k}_state")
        if pose is not None:
            st["pose"] = np.asarray(pose, np.float64)
        if disparity is not None:
            st["disparity"] = np.asarray(disparity, np.float32)
        staged = {f"kf{k}_state": self.stage(f"kf{k}_state", **st)}
        if commit:
            self.commit(staged, meta)
        return staged

    def put_proxy_depth(self, kf_id: int, depth, source, pose, update_seq: int = 0,
                        commit: bool = True, meta: Optional[Dict[str, Any]] = None):
        k = int(kf_id)
        staged = {f"kf{k}_depth": self.stage(
            f"kf{k}_depth", depth=np.asarray(depth, np.float32),
            source=np.asarray(source, np.uint8), pose=np.asarray(pose, np.float64),
            update_seq=np.array(int(update_seq), np.int64))}
        if commit:
            self.commit(staged, meta)
        return staged

    def proxy_depth(self, kf_id: int) -> Optional[Dict[str, np.ndarray]]:
        n = f"kf{int(kf_id)}_depth"
        return self.get(n) if self.has(n) else None

    def keyframe_ids(self) -> List[int]:
        ids = []
        for n in self.names():
            m = re.match(r"^kf(\d+)_state$", n)
            if m:
                ids.append(int(m.group(1)))
        return sorted(ids)

    def keyframe(self, kf_id: int) -> KeyframeData:
        k = int(kf_id)
        st = self.get(f"kf{k}_state")
        img = None
        if self.has(f"kf{k}_image"):
            img = self.get(f"kf{k}_image")["image"]
        ia = st["intrinsics"]
        intr = Intrinsics(float(ia[0]), float(ia[1]), float(ia[2]), float(ia[3]), int(ia[4]),
                          int(ia[5]), "plumb_bob", [float(x) for x in st["distortion"]])
        if img is None:
            img = np.zeros((intr.height, intr.width, 3), np.uint8)
        return KeyframeData(kf_id=k, frame_index=int(st["meta"][0]), timestamp=float(st["meta"][1]),
                            pose=st["pose"], image=img, intrinsics=intr,
                            disparity=st["disparity"], confidence=st["confidence"],
                            mono_depth=st.get("mono_depth"))

    def keyframes(self) -> List[KeyframeData]:
        return [self.keyframe(k) for k in self.keyframe_ids()]

