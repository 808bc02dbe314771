"""The synthetic scene: an axis-aligned textured room with furniture-like boxes, fitted
around a camera trajectory (room frame z up)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

import numpy as np
import torch

from splat_slam_synth.options import TEX_LEVELS, TEX_SIZE, SynthError
from splat_slam_synth.textures import load_texture_images, mip_levels, to_u8, procedural_texture
from splat_slam_synth.trajectories import UP_AXES, estimate_up


def _point_box_distance(P: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    d = np.maximum(np.maximum(lo - P, 0.0), P - hi)
    return np.linalg.norm(d, axis=-1)


@dataclass
class Scene:
    """Axis-aligned room + boxes in the room frame (z up), with textures and lights.

    Surface ids: room faces ``2*axis + side`` (side 1 = the face at ``room_hi``), box ``b``
    faces ``6 + 6*b + 2*axis + side``.
    """
    room_lo: np.ndarray
    room_hi: np.ndarray
    boxes_lo: np.ndarray                    # (B, 3)
    boxes_hi: np.ndarray                    # (B, 3)
    T_room_world: np.ndarray                # (4, 4): X_room = T @ X_world
    textures: List[np.ndarray]              # (TEX_SIZE, TEX_SIZE, 3) uint8 RGB
    texture_names: List[str]
    surf_tex: np.ndarray                    # (6 + 6B,) texture index
    surf_density: np.ndarray                # (6 + 6B,) texels per metre
    surf_offset: np.ndarray                 # (6 + 6B, 2) texels
    surf_tint: np.ndarray                   # (6 + 6B, 3)
    light_pos: np.ndarray                   # point light (room frame)
    light_dir: np.ndarray                   # unit vector towards the directional light
    info: Dict = field(default_factory=dict)
    _cache: Dict = field(default_factory=dict, repr=False)

    @property
    def n_boxes(self) -> int:
        return len(self.boxes_lo)

    def without_boxes(self) -> "Scene":
        """The same room (textures, lights, frame) with every box removed."""
        return Scene(self.room_lo, self.room_hi, np.zeros((0, 3)), np.zeros((0, 3)),
                     self.T_room_world, self.textures, self.texture_names, self.surf_tex[:6],
                     self.surf_density[:6], self.surf_offset[:6], self.surf_tint[:6],
                     self.light_pos, self.light_dir, dict(self.info))

    def summary(self) -> Dict:
        return {"room_size_m": [round(float(x), 3) for x in self.room_hi - self.room_lo],
                "boxes": int(self.n_boxes), "textures": list(self.texture_names), **self.info}

    # ------------------------------------------------------------- torch state
    def _torch(self, device=None) -> Dict[str, torch.Tensor]:
        dev = torch.device(device or "cpu")
        key = f"t:{dev}"
        if key in self._cache:
            return self._cache[key]
        if dev.type != "cpu":
            t = {k: v.to(dev) for k, v in self._torch("cpu").items()}
            self._cache[key] = t
            return t
        B = self.n_boxes
        nS = 6 + 6 * B
        normal = np.zeros((nS, 3), np.float32)
        uax = np.zeros(nS, np.int64)
        vax = np.zeros(nS, np.int64)
        usign = np.ones(nS, np.float32)
        vsign = np.ones(nS, np.float32)
        flo = np.zeros((nS, 3), np.float32)
        fhi = np.zeros((nS, 3), np.float32)
        ao_k = np.zeros(nS, np.float32)
        ao_r = np.ones(nS, np.float32)
        for s in range(nS):
            box = (s - 6) // 6 if s >= 6 else -1
            a, side = (s % 6) // 2, s % 2
            if box < 0:   # room faces: normals point into the room
                n = np.eye(3)[a] * (1.0 if side == 0 else -1.0)
                flo[s], fhi[s] = self.room_lo, self.room_hi
                ao_k[s], ao_r[s] = 0.35, 0.3       # soft darkening in concave corners
            else:
                n = np.eye(3)[a] * (-1.0 if side == 0 else 1.0)
                flo[s], fhi[s] = self.boxes_lo[box], self.boxes_hi[box]
                ao_k[s], ao_r[s] = 0.35, 0.008     # thin dark bevel along box edges
            normal[s] = n
            if a == 2:
                uax[s], vax[s] = 0, 1
            else:
                # u = viewer's right when facing the surface (textures not mirrored), v down
                uax[s] = 1 if a == 0 else 0
                usign[s] = n[0] if a == 0 else -n[1]
                vax[s], vsign[s] = 2, -1.0
        # texture atlas: every texture's mip levels stacked vertically in a column block,
        # each level with one wrapped border row/column so bilinear sampling tiles seamlessly
        S = TEX_SIZE
        Hb = sum((S >> l) + 1 for l in range(TEX_LEVELS))
        atlas = np.zeros((3, Hb, len(self.textures) * (S + 1)), np.float32)
        org = np.zeros((len(self.textures), TEX_LEVELS, 2), np.float32)   # (x, y) of texel 0
        for i, tx in enumerate(self.textures):
            y = 0
            for l, arr in enumerate(mip_levels(tx, TEX_LEVELS)):
                sl = arr.shape[0]
                x = i * (S + 1)
                wrapped = np.concatenate([arr, arr[:1]], 0)
                wrapped = np.concatenate([wrapped, wrapped[:, :1]], 1)
                atlas[:, y:y + sl + 1, x:x + sl + 1] = wrapped.transpose(2, 0, 1)
                org[i, l] = (x, y)
                y += sl + 1
        # baked contact shadows of the boxes standing on the floor (view-independent)
        ext = self.room_hi[:2] - self.room_lo[:2]
        res = max(0.01, float(ext.max()) / 1024)
        gx = self.room_lo[0] + (np.arange(int(math.ceil(ext[0] / res)) + 1)) * res
        gy = self.room_lo[1] + (np.arange(int(math.ceil(ext[1] / res)) + 1)) * res
        shadow = np.ones((len(gy), len(gx)), np.float32)
        for b in range(B):
            if abs(self.boxes_lo[b, 2] - self.room_lo[2]) > 1e-6:
                continue
            dx = np.maximum(np.maximum(self.boxes_lo[b, 0] - gx, gx - self.boxes_hi[b, 0]), 0)
            dy = np.maximum(np.maximum(self.boxes_lo[b, 1] - gy, gy - self.boxes_hi[b, 1]), 0)
            dist = np.sqrt(dy[:, None] ** 2 + dx[None, :] ** 2)
            shadow *= (1 - 0.45 * np.exp(-dist / 0.12)).astype(np.float32)
        # per-surface tables: one float and one int row per surface id
        tabf = np.zeros((nS, 13), np.float32)
        tabf[:, 0], tabf[:, 1] = usign, vsign
        tabf[:, 2] = self.surf_density
        tabf[:, 3:5] = self.surf_offset
        tabf[:, 5:8] = normal
        tabf[:, 8], tabf[:, 9] = ao_k, ao_r
        tabf[:, 10] = flo[np.arange(nS), uax]
        tabf[:, 11] = fhi[np.arange(nS), uax]
        tabf[:, 12] = 0.0                # (unused)
        tabv = np.stack([flo[np.arange(nS), vax], fhi[np.arange(nS), vax]], 1).astype(np.float32)
        axis = (np.arange(nS) % 6) // 2
        tabi = np.stack([uax, vax, axis, self.surf_tex.astype(np.int64)], 1)
        f32 = lambda x: torch.as_tensor(np.asarray(x, np.float32))  # noqa: E731
        t = dict(room_lo=f32(self.room_lo), room_hi=f32(self.room_hi),
                 boxes_lo=f32(self.boxes_lo.reshape(-1, 3)), boxes_hi=f32(self.boxes_hi.reshape(-1, 3)),
                 tabf=torch.cat([f32(tabf), f32(tabv), f32(self.surf_tint)], 1),
                 tabi=torch.as_tensor(tabi),
                 atlas=torch.from_numpy(atlas)[None],
                 org=f32(org.reshape(-1, 2)),
                 light_pos=f32(self.light_pos), light_dir=f32(self.light_dir),
                 floor_shadow=torch.from_numpy(shadow)[None, None],
                 floor_grid=torch.tensor([self.room_lo[0], self.room_lo[1],
                                          2.0 / (res * (len(gx) - 1)), 2.0 / (res * (len(gy) - 1))],
                                         dtype=torch.float32))
        self._cache[key] = t
        return t


def make_scene(room_lo, room_hi, boxes_lo=(), boxes_hi=(), *, seed: int = 0,
               T_room_world=None, textures: Optional[Union[str, Path]] = None,
               info: Optional[Dict] = None) -> Scene:
    """A scene from explicit geometry (room frame, z up): textures, tints and lights are
    drawn from ``seed`` (images from the ``textures`` folder when given)."""
    rng = np.random.default_rng([int(seed), 3])
    room_lo, room_hi = np.asarray(room_lo, float), np.asarray(room_hi, float)
    boxes_lo = np.asarray(boxes_lo, float).reshape(-1, 3)
    boxes_hi = np.asarray(boxes_hi, float).reshape(-1, 3)
    if np.any(room_hi - room_lo <= 0) or np.any(boxes_hi - boxes_lo <= 0):
        raise SynthError("scene boxes need lo < hi on every axis")
    S = TEX_SIZE
    B = len(boxes_lo)
    images = load_texture_images(textures, rng, S) if textures else []
    names: List[str] = []
    texs: List[np.ndarray] = []

    def add(name, arr):
        if name.startswith("image:") and name in names:
            return names.index(name)
        names.append(name)
        texs.append(arr if arr.dtype == np.uint8 else to_u8(arr))
        return len(texs) - 1

    # room: floor (z lo), ceiling (z hi), four walls
    slot = iter(range(10 ** 6))

    def proc(kind):
        return add(kind, procedural_texture(kind, seed, next(slot)))

    floor = proc(str(rng.choice(["wood", "tiles", "carpet"])))
    ceiling = proc("plaster")
    wall_kinds = ["wallpaper", "bricks", "clutter", "whiteboard", "tiles", "wallpaper"]
    rng.shuffle(wall_kinds)
    walls = []
    for i in range(4):
        if images and rng.uniform() < 0.5:
            walls.append(add(*images[int(rng.integers(len(images)))]))
        else:
            walls.append(proc(wall_kinds[i]))
    obj_kinds = ["wood", "fabric", "clutter", "granite", "tiles", "whiteboard", "carpet",
                 "plaster", "clutter", "wood"]
    obj = []
    for i in range(min(max(B, 1), 10)):
        if images and rng.uniform() < 0.6:
            obj.append(add(*images[int(rng.integers(len(images)))]))
        else:
            obj.append(proc(obj_kinds[int(rng.integers(len(obj_kinds)))]))
    nS = 6 + 6 * B
    tex = np.zeros(nS, np.int64)
    dens = np.zeros(nS)
    tint = np.ones((nS, 3))
    tex[[0, 1, 2, 3]] = walls                 # x-lo, x-hi, y-lo, y-hi walls
    tex[4], tex[5] = floor, ceiling
    dens[:4] = S / rng.uniform(1.2, 2.0, 4)    # one tile per 1.2-2 m
    dens[4], dens[5] = S / rng.uniform(1.0, 1.6), S / rng.uniform(1.5, 2.5)
    tint[:6] = rng.uniform(0.9, 1.08, (6, 3))
    for b in range(B):
        t_b = obj[int(rng.integers(len(obj)))]
        sl = slice(6 + 6 * b, 12 + 6 * b)
        tex[sl] = t_b
        dens[sl] = S / rng.uniform(0.5, 1.1)
        tint[sl] = rng.uniform(0.8, 1.15, 3)[None] * rng.uniform(0.95, 1.05, (6, 3))
    off = rng.uniform(0, S, (nS, 2))
    centre = 0.5 * (room_lo + room_hi)
    light_pos = np.array([centre[0] + rng.uniform(-0.5, 0.5), centre[1] + rng.uniform(-0.5, 0.5),
                          room_hi[2] - 0.3])
    ld = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), 1.0])
    return Scene(room_lo, room_hi, boxes_lo, boxes_hi,
                 np.eye(4) if T_room_world is None else np.asarray(T_room_world, float),
                 texs, names, tex, dens, off, tint, light_pos, ld / np.linalg.norm(ld),
                 dict(info or {}))


def _room_frame(P: np.ndarray, up, fmt) -> Tuple[np.ndarray, np.ndarray]:
    """(unit world up, 4x4 world->room transform): room z up, x along the mean horizontal
    viewing direction, origin at the mean camera position."""
    up_v = np.asarray(UP_AXES[up] if isinstance(up, str) else (up if up is not None
                      else estimate_up(P, fmt)), float)
    up_v /= np.linalg.norm(up_v)
    fwd = P[:, :3, 2] - np.outer(P[:, :3, 2] @ up_v, up_v)
    f = fwd.mean(0)
    if np.linalg.norm(f) < 0.2:
        pos_h = P[:, :3, 3] - np.outer(P[:, :3, 3] @ up_v, up_v)
        pos_h = pos_h - pos_h.mean(0)
        f = np.linalg.svd(pos_h, full_matrices=False)[2][0] if len(P) > 2 else np.zeros(3)
        if np.linalg.norm(f - (f @ up_v) * up_v) < 1e-6:
            f = np.cross(up_v, np.eye(3)[int(np.argmin(np.abs(up_v)))])
    f = f - (f @ up_v) * up_v
    xr = f / np.linalg.norm(f)
    yr = np.cross(up_v, xr)
    R_rw = np.stack([xr, yr, up_v], 0)
    origin = P[:, :3, 3].mean(0)
    T_rw = np.eye(4)
    T_rw[:3, :3] = R_rw
    T_rw[:3, 3] = -R_rw @ origin
    return up_v, T_rw


def _fit_room(rng, allp: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Room corners (room frame) around every camera position with >= 1.1 m margin."""
    lo, hi = allp.min(0), allp.max(0)
    room_lo = np.array([lo[0] - rng.uniform(1.3, 2.0), lo[1] - rng.uniform(1.3, 2.0),
                        lo[2] - rng.uniform(1.15, 1.45)])
    room_hi = np.array([hi[0] + rng.uniform(1.6, 2.4), hi[1] + rng.uniform(1.3, 2.0), 0.0])
    room_hi[2] = max(hi[2] + rng.uniform(0.9, 1.3), room_lo[2] + 2.6)
    for a in range(2):                     # at least 3.6 m across
        short = 3.6 - (room_hi[a] - room_lo[a])
        if short > 0:
            room_lo[a] -= short / 2
            room_hi[a] += short / 2
    return room_lo, room_hi


def _exit_dist(room_lo, room_hi, o, d) -> float:
    """Distance along the ray o + s d to the room's walls."""
    with np.errstate(divide="ignore"):
        inv = 1.0 / np.where(d == 0, 1e-12, d)
    return float(np.min(np.maximum((room_lo - o) * inv, (room_hi - o) * inv)))


def _box_at(rng, c, kind: str, room_lo, room_hi, blo, bhi) -> Tuple[np.ndarray, np.ndarray]:
    """A box of ``kind`` standing under the point ``c``, kept inside the room."""
    floor_z, ceil_z = room_lo[2], room_hi[2]
    if kind == "furniture":
        half = rng.uniform(0.2, 0.6, 2)
        z0, z1 = floor_z, np.clip(c[2] + rng.uniform(-0.05, 0.2), floor_z + 0.3, ceil_z - 0.3)
    elif kind == "cabinet":
        half = rng.uniform(0.2, 0.5, 2)
        z0 = floor_z
        z1 = min(floor_z + rng.uniform(0.9, 2.0), ceil_z - 0.2)
    else:
        half = rng.uniform(0.06, 0.25, 2)
        z0 = floor_z
        for bl, bh in zip(blo, bhi):       # rest on the highest box below the point
            if bl[0] <= c[0] <= bh[0] and bl[1] <= c[1] <= bh[1] and bh[2] <= c[2] + 0.1:
                z0 = max(z0, bh[2])
        z1 = z0 + rng.uniform(0.1, 0.45)
    b_lo = np.array([c[0] - half[0], c[1] - half[1], z0])
    b_hi = np.array([c[0] + half[0], c[1] + half[1], z1])
    # keep inside the room (shift against the wall, then clip)
    for a in range(2):
        if b_lo[a] < room_lo[a]:
            b_hi[a] += room_lo[a] - b_lo[a]
            b_lo[a] = room_lo[a]
        if b_hi[a] > room_hi[a]:
            b_lo[a] -= b_hi[a] - room_hi[a]
            b_hi[a] = room_hi[a]
    b_lo[:2] = np.maximum(b_lo[:2], room_lo[:2])
    b_hi[:2] = np.minimum(b_hi[:2], room_hi[:2])
    return b_lo, b_hi


def _shrink_clear(b_lo, b_hi, allp: np.ndarray, clearance: float) -> bool:
    """Shrink the box in place until it keeps ``clearance`` from every camera position;
    False when it got too small first."""
    for _ in range(8):
        if np.any(b_hi - b_lo < 0.06) or b_hi[2] <= b_lo[2] + 0.05:
            return False
        if _point_box_distance(allp, b_lo, b_hi).min() >= clearance:
            return True
        ctr = 0.5 * (b_lo + b_hi)
        b_lo[:2] = ctr[:2] - 0.8 * (ctr[:2] - b_lo[:2])
        b_hi[:2] = ctr[:2] + 0.8 * (b_hi[:2] - ctr[:2])
        b_hi[2] = b_lo[2] + 0.75 * (b_hi[2] - b_lo[2])
    return False


def _fit_context(poses, up, fmt, positions):
    """(unit world up, T_room_world, room-frame camera positions, every position the camera
    passes through (room frame), room-from-camera rotations)."""
    P = np.asarray(poses, float)
    up_v, T_rw = _room_frame(P, up, fmt)
    R_rw = T_rw[:3, :3]
    cams = P[:, :3, 3] @ R_rw.T + T_rw[:3, 3]
    allp = cams if positions is None else np.concatenate(
        [cams, np.asarray(positions, float).reshape(-1, 3) @ R_rw.T + T_rw[:3, 3]], 0)
    R_rc = np.einsum("ij,njk->nik", R_rw, P[:, :3, :3])
    return up_v, T_rw, cams, allp, R_rc


def _room_reach(rng, kind: str, tw: float) -> Optional[float]:
    """Distance along a view ray (wall at ``tw``) at which a box of ``kind`` is placed; None
    to skip the ray: cabinets stand at the wall, the rest 0.9-3.2 m away."""
    if kind == "cabinet":
        return tw - 0.05
    s = min(max(rng.uniform(0.35, 0.85) * tw, 0.9), 3.2, tw - 0.4)
    return None if s < 0.9 else s


def _overlaps(b_lo, b_hi, blo, bhi) -> bool:
    return any(np.all(b_lo < h - 1e-3) and np.all(b_hi > l + 1e-3) for l, h in zip(blo, bhi))


def _place_boxes(rng, cams, R_rc, allp, room_lo, room_hi, n: int, clearance: float,
                 blo: List[np.ndarray], bhi: List[np.ndarray], kinds: List[str], *,
                 kind_names=("furniture", "cabinet", "object"), kind_p=(0.45, 0.2, 0.35),
                 reach=_room_reach, accept=None) -> int:
    """Append up to ``n`` boxes (to ``blo``, ``bhi``, ``kinds``) around points the cameras
    look at: a random camera, a ray in its central field of view, a point ``reach`` along
    it. Every box keeps ``clearance`` from every position in ``allp``; boxes never
    interpenetrate; ``accept(lo, hi)`` (optional) can veto a box. Returns how many were
    added."""
    added = tries = 0
    while added < n and tries < 60 * max(n, 1):
        tries += 1
        i = int(rng.integers(len(cams)))
        o = cams[i]
        d = R_rc[i] @ np.array([rng.uniform(-0.45, 0.45), rng.uniform(-0.34, 0.34), 1.0])
        d /= np.linalg.norm(d)
        tw = _exit_dist(room_lo, room_hi, o, d)
        kind = str(rng.choice(list(kind_names), p=list(kind_p)))
        s = reach(rng, kind, tw)
        if s is None:
            continue
        b_lo, b_hi = _box_at(rng, o + s * d, kind, room_lo, room_hi, blo, bhi)
        if not _shrink_clear(b_lo, b_hi, allp, clearance):
            continue
        if _overlaps(b_lo, b_hi, blo, bhi):
            continue                           # no interpenetrating boxes
        if accept is not None and not accept(b_lo, b_hi):
            continue
        blo.append(b_lo)
        bhi.append(b_hi)
        kinds.append(kind)
        added += 1
    return added


def _scene_info(name: str, up_v, kinds: List[str], allp, blo, bhi) -> Dict:
    return {"name": name, "up_world": [float(x) for x in up_v],
            "box_kinds": {k: kinds.count(k) for k in sorted(set(kinds))},
            "min_camera_box_distance_m": round(float(min(
                [_point_box_distance(allp, l, h).min() for l, h in zip(blo, bhi)] or [np.inf])),
                3)}


def build_room(poses: np.ndarray, *, seed: int = 0, textures=None, up=None, fmt=None,
               positions: Optional[np.ndarray] = None, clearance: float = 0.5,
               n_boxes: Optional[int] = None) -> Scene:
    """Fit a room with furniture-like boxes around camera-to-world ``poses`` (world frame):
    the default scene (``variants.build_scene`` picks the others).

    All camera positions (``poses`` plus the optional dense ``positions``, e.g. the whole
    exposure windows) lie inside the room with >= 1.1 m margin, and every box keeps
    ``clearance`` metres from every position. Boxes are placed around points the cameras
    look at (0.9-3.2 m along central view rays), so they give parallax and occlusion.
    """
    name = "room"
    rng = np.random.default_rng([int(seed), 5])
    up_v, T_rw, cams, allp, R_rc = _fit_context(poses, up, fmt, positions)
    room_lo, room_hi = _fit_room(rng, allp)
    area = float(np.prod(room_hi[:2] - room_lo[:2]))
    target = int(np.clip(area / 2.0 + 6, 8, 32)) if n_boxes is None else int(n_boxes)
    blo: List[np.ndarray] = []
    bhi: List[np.ndarray] = []
    kinds: List[str] = []
    _place_boxes(rng, cams, R_rc, allp, room_lo, room_hi, target, clearance, blo, bhi, kinds)
    return make_scene(room_lo, room_hi, np.array(blo).reshape(-1, 3), np.array(bhi).reshape(-1, 3),
                      seed=seed, T_room_world=T_rw, textures=textures,
                      info=_scene_info(name, up_v, kinds, allp, blo, bhi))
