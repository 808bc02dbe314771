"""Scene variants of the generator (``--scene``, described in ``options.SCENES``): the same
room fit around the trajectory as the default ``room`` scene, with content chosen to stress
one weakness of optical flow or depth each (little texture, texel density, periodicity,
thin structures, depth range). Boxes keep the caller's clearance from every camera
position, like the room's."""
from __future__ import annotations

from typing import Dict, List, NamedTuple, Optional, Sequence

import numpy as np

from splat_slam_synth.options import TEX_SIZE, SynthError, check_scene
from splat_slam_synth.scene import (Scene, build_room, _exit_dist, _fit_context, _fit_room, _overlaps,
                                   _place_boxes, _point_box_distance, _scene_info,
                                   make_scene)
from splat_slam_synth.textures import PERIODIC, procedural_texture

_SLOT0 = 1000          # texture slots of the variants (apart from make_scene's 0, 1, 2 ...)


class _Fit(NamedTuple):
    seed: int
    up_v: np.ndarray
    T_rw: np.ndarray
    cams: np.ndarray            # (N, 3) frame positions, room frame
    allp: np.ndarray            # (M, 3) every position the camera passes through
    R_rc: np.ndarray            # (N, 3, 3) room-from-camera rotations
    clearance: float


def _standard_boxes(rng, fit: _Fit, lo, hi, n, blo, bhi, kinds, **kw) -> None:
    _place_boxes(rng, fit.cams, fit.R_rc, fit.allp, lo, hi, n, fit.clearance, blo, bhi, kinds,
                 **kw)


def _target(lo, hi, per_m2: float, add: float, a: int, b: int, n_boxes: Optional[int]) -> int:
    if n_boxes is not None:
        return int(n_boxes)
    return int(np.clip(float(np.prod(hi[:2] - lo[:2])) * per_m2 + add, a, b))


def _procedural_scene(rng, fit: _Fit, lo, hi, blo, bhi, room_kinds: Sequence,
                      room_tile_m, box_kinds: Sequence[str], box_tile_m, tint: float,
                      info: Dict) -> Scene:
    """A scene whose surfaces all get procedural textures: ``room_kinds`` for the six room
    faces (x-lo, x-hi, y-lo, y-hi walls, floor, ceiling; an int reuses the texture of that
    earlier face), one of ``box_kinds`` per box;
    ``*_tile_m``: (low, high) tile length in metres (one per room face or one range)."""
    S = TEX_SIZE
    names: List[str] = []
    texs: List[np.ndarray] = []
    B = len(blo)
    nS = 6 + 6 * B

    def tex(kind: str) -> int:
        names.append(kind)
        texs.append(procedural_texture(kind, fit.seed, _SLOT0 + len(texs)))
        return len(texs) - 1

    surf = np.zeros(nS, np.int64)
    dens = np.zeros(nS)
    tints = np.ones((nS, 3))
    room_tile_m = np.broadcast_to(np.asarray(room_tile_m, float), (6, 2))
    for f, kind in enumerate(room_kinds):
        surf[f] = surf[kind] if isinstance(kind, int) else tex(kind)
        dens[f] = S / rng.uniform(*room_tile_m[f])
    tints[:6] = rng.uniform(1 - tint, 1 + tint, (6, 3))
    pool = [tex(str(k)) for k in rng.permutation(list(box_kinds))[:min(B, len(box_kinds))]]
    for b in range(B):
        sl = slice(6 + 6 * b, 12 + 6 * b)
        surf[sl] = pool[int(rng.integers(len(pool)))]
        dens[sl] = S / rng.uniform(*box_tile_m)
        tints[sl] = rng.uniform(1 - tint, 1 + tint, 3)[None]
    off = rng.uniform(0, S, (nS, 2))
    centre = 0.5 * (lo + hi)
    light_pos = np.array([centre[0] + rng.uniform(-0.5, 0.5), centre[1] + rng.uniform(-0.5, 0.5),
                          hi[2] - 0.3])
    ld = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), 1.0])
    return Scene(lo, hi, np.array(blo).reshape(-1, 3), np.array(bhi).reshape(-1, 3), fit.T_rw,
                 texs, names, surf, dens, off, tints, light_pos, ld / np.linalg.norm(ld), info)


def _no_textures(name: str, textures) -> None:
    if textures is not None:
        raise SynthError(f"--textures cannot be combined with --scene {name}: its surfaces "
                         "are procedural by design (use room, tiled, thin or deep)")


# ------------------------------------------------------------------ variants
def _low_texture(rng, fit: _Fit, name, textures, n_boxes) -> Scene:
    _no_textures(name, textures)
    lo, hi = _fit_room(rng, fit.allp)
    blo, bhi, kinds = [], [], []          # boxes' low / high corners and kinds
    n = int(rng.integers(0, 3)) if n_boxes is None else int(n_boxes)
    _standard_boxes(rng, fit, lo, hi, n, blo, bhi, kinds, kind_names=("furniture", "cabinet"),
                    kind_p=(0.5, 0.5))
    info = _scene_info(name, fit.up_v, kinds, fit.allp, blo, bhi)
    # one paint on the four walls, another on the floor and on the ceiling
    return _procedural_scene(rng, fit, lo, hi, blo, bhi, ["paint", 0, 0, 0, "paint", "paint"],
                             (2.0, 4.0), ["paint", "paint"], (1.5, 3.0), 0.03, info)


def _repetitive(rng, fit: _Fit, name, textures, n_boxes) -> Scene:
    _no_textures(name, textures)
    lo, hi = _fit_room(rng, fit.allp)
    blo, bhi, kinds = [], [], []          # boxes' low / high corners and kinds
    _standard_boxes(rng, fit, lo, hi, _target(lo, hi, 0.25, 3, 4, 12, n_boxes), blo, bhi, kinds)
    walls = [str(k) for k in rng.choice(PERIODIC, 4)]
    room = walls + [str(rng.choice(["checker", "brickwork", "grid"])), "grid"]
    info = _scene_info(name, fit.up_v, kinds, fit.allp, blo, bhi)
    # walls: a tile every 1-2 m = 8-32 periods of 3-25 cm; boxes: 7 of 8 textures periodic
    return _procedural_scene(rng, fit, lo, hi, blo, bhi, room, (1.0, 2.0),
                             list(PERIODIC) + ["stripes", "checker", "grid", "wood"], (0.5, 1.0),
                             0.06, info)


def _tiled(rng, fit: _Fit, name, textures, n_boxes) -> Scene:
    lo, hi = _fit_room(rng, fit.allp)
    blo, bhi, kinds = [], [], []          # boxes' low / high corners and kinds
    _standard_boxes(rng, fit, lo, hi, _target(lo, hi, 0.5, 6, 8, 32, n_boxes), blo, bhi, kinds)
    info = _scene_info(name, fit.up_v, kinds, fit.allp, blo, bhi)
    sc = make_scene(lo, hi, np.array(blo).reshape(-1, 3), np.array(bhi).reshape(-1, 3),
                    seed=fit.seed, T_room_world=fit.T_rw, textures=textures, info=info)
    # surface groups: four walls, floor, ceiling, each box; half stretched, half small tiles
    S = TEX_SIZE
    modes = ["stretched", "small", "stretched", "small"]
    rng.shuffle(modes)
    modes += ["small", "stretched"] + [str(rng.choice(["stretched", "small"]))
                                       for _ in range(len(blo))]
    dens = sc.surf_density.copy()
    for g, mode in enumerate(modes):
        sl = slice(g, g + 1) if g < 6 else slice(6 * (g - 5), 6 * (g - 4))
        # stretched: one tile per 6-12 m (43-85 texels/m, magnified and blurry at 1-3 m);
        # small: one tile every 12-30 cm, repeated many times across a surface
        dens[sl] = S / (rng.uniform(6.0, 12.0) if mode == "stretched" else rng.uniform(0.12, 0.3))
    sc.surf_density = dens
    sc.info.update(stretched_surfaces=modes.count("stretched"),
                   small_tile_surfaces=modes.count("small"))
    return sc


def _thin_parts(rng, kind: str, c, inward: np.ndarray, along: np.ndarray, floor_z: float,
                ceil_z: float) -> List[tuple]:
    """Boxes (lo, hi) of one thin structure standing at floor point ``c``: ``inward`` is the
    unit horizontal normal of the nearby wall (into the room), ``along`` the wall direction
    (both axis-aligned)."""
    def box(centre, half_along, half_in, z0, z1):
        h = np.abs(along) * half_along + np.abs(inward) * half_in
        return (np.array([centre[0] - h[0], centre[1] - h[1], z0]),
                np.array([centre[0] + h[0], centre[1] + h[1], z1]))

    if kind == "pole":                       # a 3-6 cm pole, to the ceiling or a lamp stand
        w = rng.uniform(0.015, 0.03)
        top = ceil_z if rng.uniform() < 0.5 else min(floor_z + rng.uniform(1.2, 2.2), ceil_z)
        return [box(c, w, w, floor_z, top)]
    if kind == "shelf":                      # 3-5 boards 2-3.5 cm thick between two uprights
        width, depth = rng.uniform(0.6, 1.4), rng.uniform(0.25, 0.4)
        n, th = int(rng.integers(3, 6)), rng.uniform(0.02, 0.035)
        ctr = c + inward * depth / 2
        top = min(floor_z + rng.uniform(1.2, 2.0), ceil_z - 0.1)
        parts = [box(ctr + along * s * (width / 2 - 0.01), 0.01, depth / 2, floor_z, top)
                 for s in (-1, 1)]
        for z in np.linspace(floor_z + 0.3, top - th, n):
            parts.append(box(ctr, width / 2 - 0.02, depth / 2, z, z + th))
        return parts
    # table: a 3 cm top on four 4 cm legs
    la, li = rng.uniform(0.3, 0.6), rng.uniform(0.25, 0.4)
    ctr = c + inward * li
    z_top = floor_z + rng.uniform(0.7, 0.78)
    parts = [box(ctr, la, li, z_top, z_top + 0.03)]
    for sa in (-1, 1):
        for si in (-1, 1):
            parts.append(box(ctr + along * sa * (la - 0.05) + inward * si * (li - 0.05),
                             0.02, 0.02, floor_z, z_top))
    return parts


def _thin(rng, fit: _Fit, name, textures, n_boxes) -> Scene:
    lo, hi = _fit_room(rng, fit.allp)
    blo, bhi, kinds = [], [], []          # boxes' low / high corners and kinds
    n_struct = int(np.clip(float(np.prod(hi[:2] - lo[:2])) / 3 + 4, 6, 14))
    counts = {"pole": 0, "shelf": 0, "table": 0}
    tries = 0
    while sum(counts.values()) < n_struct and tries < 60 * n_struct:
        tries += 1
        i = int(rng.integers(len(fit.cams)))
        o = fit.cams[i]
        d = fit.R_rc[i] @ np.array([rng.uniform(-0.45, 0.45), rng.uniform(-0.34, 0.34), 1.0])
        d /= np.linalg.norm(d)
        p = o + _exit_dist(lo, hi, o, d) * d
        # the wall nearest to where the view ray ends; stand 0.05-0.8 m in front of it
        gaps = np.array([p[0] - lo[0], hi[0] - p[0], p[1] - lo[1], hi[1] - p[1]])
        w = int(np.argmin(gaps))
        ax = w // 2
        inward = np.zeros(3)
        inward[ax] = 1.0 if w % 2 == 0 else -1.0
        along = np.zeros(3)
        along[1 - ax] = 1.0
        kind = str(rng.choice(["pole", "shelf", "table"], p=[0.45, 0.3, 0.25]))
        c = p.copy()
        c[ax] = (lo if w % 2 == 0 else hi)[ax] + inward[ax] * (
            0.0 if kind == "shelf" else rng.uniform(0.05, 0.8))
        c[1 - ax] = np.clip(c[1 - ax], lo[1 - ax] + 0.8, hi[1 - ax] - 0.8)
        parts = _thin_parts(rng, kind, c, inward, along, lo[2], hi[2])
        ok = all(np.all(pl >= lo - 1e-9) and np.all(ph <= hi + 1e-9) and
                 _point_box_distance(fit.allp, pl, ph).min() >= fit.clearance and
                 not _overlaps(pl, ph, blo, bhi) for pl, ph in parts)
        if not ok:
            continue
        for pl, ph in parts:
            blo.append(pl)
            bhi.append(ph)
            kinds.append(kind)
        counts[kind] += 1
    # then ordinary boxes around them (fewer than in the room)
    _standard_boxes(rng, fit, lo, hi, _target(lo, hi, 0.25, 3, 4, 16, n_boxes), blo, bhi, kinds)
    info = _scene_info(name, fit.up_v, kinds, fit.allp, blo, bhi)
    info["thin_structures"] = counts
    return make_scene(lo, hi, np.array(blo).reshape(-1, 3), np.array(bhi).reshape(-1, 3),
                      seed=fit.seed, T_room_world=fit.T_rw, textures=textures, info=info)


def _deep_reach(rng, kind: str, tw: float) -> Optional[float]:
    if kind == "cabinet":
        return tw - 0.05
    s = max(rng.uniform(0.2, 0.9) * tw, 2.5)
    return None if s > tw - 0.4 else s


def _near_reach(rng, kind: str, tw: float) -> Optional[float]:
    s = rng.uniform(0.9, 1.9)
    return None if s > tw - 0.4 else s


def _deep(rng, fit: _Fit, name, textures, n_boxes) -> Scene:
    lo, hi = _fit_room(rng, fit.allp)
    # a hall: the far wall 10-18 m beyond the furthest camera position along the room's x
    # (the mean horizontal viewing direction), at least 6 m wide and 3 m high
    far = rng.uniform(10.0, 18.0)
    hi[0] = fit.allp[:, 0].max() + far
    short = 6.0 - (hi[1] - lo[1])
    if short > 0:
        lo[1] -= short / 2
        hi[1] += short / 2
    hi[2] = max(hi[2], lo[2] + rng.uniform(3.0, 4.0))
    # cameras looking down (desk trajectories) would only see the floor 2-5 m away: lower
    # it (a balcony over a hall) so that the mean view ray also runs ``far`` metres; the
    # same for the ceiling when they look up
    fwd = fit.R_rc[:, :, 2].mean(0)
    fwd /= np.linalg.norm(fwd)
    if fwd[2] < -0.1:
        lo[2] = min(lo[2], fit.allp[:, 2].min() + far * fwd[2])
    elif fwd[2] > 0.1:
        hi[2] = max(hi[2], fit.allp[:, 2].max() + far * fwd[2])
    blo, bhi, kinds = [], [], []          # boxes' low / high corners and kinds
    # near boxes 0.5-1.5 m from the path, their tops >= 0.35 m below the mean camera height
    # so that the hall stays visible above them; then a few boxes along the hall
    top = float(fit.cams[:, 2].mean()) - 0.35

    def near_ok(b_lo, b_hi) -> bool:
        return b_hi[2] <= top and _point_box_distance(fit.allp, b_lo, b_hi).min() <= 1.5

    _standard_boxes(rng, fit, lo, hi, int(rng.integers(2, 5)), blo, bhi, kinds,
                    kind_names=("furniture", "object"), kind_p=(0.7, 0.3), reach=_near_reach,
                    accept=near_ok)
    n_near = len(blo)
    _standard_boxes(rng, fit, lo, hi, _target(lo, hi, 0.06, 2, 4, 10, n_boxes), blo, bhi, kinds,
                    reach=_deep_reach)
    info = _scene_info(name, fit.up_v, kinds, fit.allp, blo, bhi)
    info.update(near_boxes=n_near,
                far_wall_m=round(float(hi[0] - fit.cams[:, 0].max()), 3),
                floor_below_cameras_m=round(float(fit.cams[:, 2].min() - lo[2]), 3))
    return make_scene(lo, hi, np.array(blo).reshape(-1, 3), np.array(bhi).reshape(-1, 3),
                      seed=fit.seed, T_room_world=fit.T_rw, textures=textures, info=info)


_BUILDERS = {"low_texture": _low_texture, "tiled": _tiled, "repetitive": _repetitive,
             "thin": _thin, "deep": _deep}


def build_variant(name: str, poses, *, seed: int = 0, textures=None, up=None, fmt=None,
                  positions=None, clearance: float = 0.5, n_boxes: Optional[int] = None
                  ) -> Scene:
    """The scene variant ``name`` (not 'room', see :func:`build_scene`) fitted around
    ``poses``; ``n_boxes`` overrides the number of ordinary boxes."""
    if name not in _BUILDERS:
        raise SynthError(f"unknown scene variant '{name}' (one of {sorted(_BUILDERS)})")
    up_v, T_rw, cams, allp, R_rc = _fit_context(poses, up, fmt, positions)
    fit = _Fit(int(seed), up_v, T_rw, cams, allp, R_rc, float(clearance))
    # the room's own stream: the variants get the room size of the 'room' scene
    rng = np.random.default_rng([int(seed), 5])
    return _BUILDERS[name](rng, fit, name, textures, n_boxes)


def build_scene(poses: np.ndarray, *, seed: int = 0, textures=None, up=None, fmt=None,
                positions: Optional[np.ndarray] = None, clearance: float = 0.5,
                n_boxes: Optional[int] = None, scene: str = "room") -> Scene:
    """The scene ``scene`` (``options.SCENES``) fitted around camera-to-world ``poses``:
    the furnished room (:func:`scene.build_room`, the default) or one of its variants."""
    name = check_scene(scene)
    kw = dict(seed=seed, textures=textures, up=up, fmt=fmt, positions=positions,
              clearance=clearance, n_boxes=n_boxes)
    return build_room(poses, **kw) if name == "room" else build_variant(name, poses, **kw)
