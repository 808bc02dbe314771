"""Procedural tileable textures (plaster, wallpaper, wood, tiles, ...) and texture images
from a folder, with their mip levels."""
from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Dict, List, Tuple

import cv2
import numpy as np

from splat_slam_synth.options import IMAGE_EXTS, TEX_SIZE, SynthError


_FREQ_CACHE: Dict = {}


def _noise(rng, S: int, fmin: float, fmax: float, beta: float = 1.0,
           aniso: Tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Periodic (tileable) band-limited noise on S x S, zero mean, unit std.
    fmin/fmax in cycles per tile; aniso stretches the spectrum (x, y)."""
    key = (S, aniso)
    if key not in _FREQ_CACHE:
        fy = np.fft.fftfreq(S)[:, None] * S * aniso[1]
        fx = np.fft.rfftfreq(S)[None, :] * S * aniso[0]
        f = np.sqrt(fx ** 2 + fy ** 2).astype(np.float32)
        _FREQ_CACHE[key] = (f, 1.0 / np.maximum(f, 1.0))
    f, inv_f = _FREQ_CACHE[key]
    amp = np.where((f >= fmin) & (f <= fmax), inv_f if beta == 1.0 else inv_f ** beta, 0.0)
    spec = rng.standard_normal((2,) + f.shape, dtype=np.float32) * amp
    spec = spec[0] + 1j * spec[1]
    n = np.fft.irfft2(spec, s=(S, S))
    return ((n - n.mean()) / (n.std() + 1e-12)).astype(np.float32)


def _fbm(rng, S):
    """Multi-scale noise: coarse mottling + mid + fine grain."""
    return 0.6 * _noise(rng, S, 1, 6) + 0.3 * _noise(rng, S, 6, 40) + 0.2 * _noise(rng, S, 40, S / 2)


def _color(rng, sat=(0.15, 0.6), val=(0.35, 0.85), hue=None) -> np.ndarray:
    h = rng.uniform(0, 1) if hue is None else hue
    s, v = rng.uniform(*sat), rng.uniform(*val)
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i],
                     dtype=np.float32)


def _draw_tiled(img: np.ndarray, fn) -> None:
    """Call fn(img, dx, dy) for the 9 periodic copies so shapes wrap across tile edges."""
    S = img.shape[0]
    for dy in (-S, 0, S):
        for dx in (-S, 0, S):
            fn(img, dx, dy)


def _shapes(rng, img: np.ndarray, n: int, kinds=("rect", "circle", "line", "text"),
            bright=(0.1, 0.95)) -> None:
    S = img.shape[0]
    for _ in range(n):
        kind = kinds[rng.integers(len(kinds))]
        col = tuple(float(c) for c in _color(rng, sat=(0.0, 0.8), val=bright))
        x, y = int(rng.integers(S)), int(rng.integers(S))
        if kind == "rect":
            w, h = int(rng.integers(S // 40, S // 5)), int(rng.integers(S // 40, S // 5))
            th = -1 if rng.uniform() < 0.7 else int(rng.integers(1, 4))
            _draw_tiled(img, lambda im, dx, dy: cv2.rectangle(
                im, (x + dx, y + dy), (x + dx + w, y + dy + h), col, th, cv2.LINE_AA))
        elif kind == "circle":
            r = int(rng.integers(S // 60, S // 10))
            th = -1 if rng.uniform() < 0.6 else int(rng.integers(1, 4))
            _draw_tiled(img, lambda im, dx, dy: cv2.circle(im, (x + dx, y + dy), r, col, th,
                                                             cv2.LINE_AA))
        elif kind == "line":
            x2, y2 = x + int(rng.integers(-S // 4, S // 4)), y + int(rng.integers(-S // 4, S // 4))
            th = int(rng.integers(1, 5))
            _draw_tiled(img, lambda im, dx, dy: cv2.line(im, (x + dx, y + dy), (x2 + dx, y2 + dy),
                                                           col, th, cv2.LINE_AA))
        else:  # "text": rows of small word blocks
            rows, lh = int(rng.integers(2, 7)), int(rng.integers(5, 10))
            width = int(rng.integers(S // 10, S // 4))
            blocks = []
            for r in range(rows):
                cx = 0
                while cx < width:
                    wl = int(rng.integers(4, 22))
                    blocks.append((cx, r * lh * 2, wl, lh))
                    cx += wl + int(rng.integers(3, 7))

            def draw(im, dx, dy):
                for bx, by, bw, bh in blocks:
                    cv2.rectangle(im, (x + dx + bx, y + dy + by),
                                  (x + dx + bx + bw, y + dy + by + bh), col, -1, cv2.LINE_AA)
            _draw_tiled(img, draw)


def tex_plaster(rng, S):
    c = _color(rng, sat=(0.02, 0.15), val=(0.72, 0.9))
    n = 0.045 * _noise(rng, S, 1, 8) + 0.03 * _noise(rng, S, 12, 64) + 0.02 * _noise(rng, S, 64, S / 2)
    return c[None, None] * (1 + n[..., None])


def tex_wallpaper(rng, S):
    c = _color(rng, sat=(0.05, 0.4), val=(0.55, 0.85))
    c2 = c * rng.uniform(0.6, 0.85)
    p = S // int(rng.choice([8, 16, 32]))
    y, x = np.mgrid[0:S, 0:S].astype(np.float32)
    kind = rng.integers(3)
    if kind == 0:
        pat = 0.5 + 0.5 * np.sin(2 * np.pi * x / p)
    elif kind == 1:
        pat = np.abs(np.sin(np.pi * x / p)) + np.abs(np.sin(np.pi * y / p))
        pat = (pat > 1.0).astype(np.float32)
    else:
        pat = ((np.hypot((x % p) - p / 2, (y % p) - p / 2) < p * 0.22)).astype(np.float32)
    pat = cv2.GaussianBlur(pat, (0, 0), 1.0)
    img = c[None, None] * (1 - pat[..., None]) + c2[None, None] * pat[..., None]
    img = img * (1 + 0.08 * _fbm(rng, S)[..., None])
    # a few posters / frames on the wall
    for _ in range(int(rng.integers(1, 4))):
        w, h = int(rng.integers(S // 6, S // 3)), int(rng.integers(S // 6, S // 3))
        x0, y0 = int(rng.integers(0, S - w)), int(rng.integers(0, S - h))
        poster = tex_clutter(rng, S)[:h, :w]
        img[y0:y0 + h, x0:x0 + w] = poster
        cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), (0.15, 0.12, 0.1), 3, cv2.LINE_AA)
    return img


def tex_wood(rng, S):
    planks = int(rng.choice([4, 8]))
    ph = S // planks
    y, x = np.mgrid[0:S, 0:S].astype(np.float32)
    warp = _noise(rng, S, 1, 12, aniso=(4.0, 0.5))
    k = int(rng.integers(20, 45))
    grain = np.sin(2 * np.pi * (k * y / S + 0.8 * warp))
    fine = _noise(rng, S, 30, S / 2, aniso=(6.0, 0.6))
    dark, light = _color(rng, sat=(0.45, 0.7), val=(0.25, 0.4), hue=rng.uniform(0.05, 0.1)), \
        _color(rng, sat=(0.35, 0.6), val=(0.55, 0.8), hue=rng.uniform(0.06, 0.11))
    t = np.clip(0.5 + 0.3 * grain + 0.15 * fine, 0, 1)[..., None]
    img = dark[None, None] * (1 - t) + light[None, None] * t
    row = (y // ph).astype(int)
    tone = rng.uniform(0.8, 1.15, planks)
    img *= tone[row][..., None]
    gap = ((y % ph) < 2).astype(np.float32)
    for r in range(planks):             # plank end joints
        jx = int(rng.integers(S))
        gap[r * ph:(r + 1) * ph, jx:jx + 2] = 1
    img *= (1 - 0.6 * cv2.GaussianBlur(gap, (0, 0), 0.7))[..., None]
    return img


def tex_tiles(rng, S):
    n = int(rng.choice([4, 8]))
    p = S // n
    y, x = np.mgrid[0:S, 0:S]
    c = _color(rng, sat=(0.05, 0.5), val=(0.45, 0.85))
    tile_tone = rng.uniform(0.85, 1.12, (n, n, 3))
    img = c[None, None] * tile_tone[y // p, x // p].astype(np.float32)
    if rng.uniform() < 0.4:   # checkerboard variant
        chk = ((y // p + x // p) % 2).astype(np.float32)[..., None]
        img = img * (1 - 0.35 * chk)
    img *= 1 + 0.06 * _fbm(rng, S)[..., None]
    mortar = (((y % p) < 3) | ((x % p) < 3)).astype(np.float32)
    mortar = cv2.GaussianBlur(mortar, (0, 0), 0.8)[..., None]
    mc = _color(rng, sat=(0.0, 0.1), val=(0.3, 0.75))
    return img * (1 - mortar) + mc[None, None] * mortar


def tex_bricks(rng, S):
    rows, cols = 16, 4
    bh, bw = S // rows, S // cols
    y, x = np.mgrid[0:S, 0:S]
    r = y // bh
    xs = (x + (r % 2) * bw // 2) % S
    c = r * cols + xs // bw
    base = _color(rng, sat=(0.35, 0.65), val=(0.35, 0.6), hue=rng.uniform(0.0, 0.08))
    tone = rng.uniform(0.75, 1.2, (rows * cols, 3)).astype(np.float32)
    img = base[None, None] * tone[c]
    img *= 1 + 0.1 * _fbm(rng, S)[..., None]
    m = (((y % bh) < 3) | ((xs % bw) < 3)).astype(np.float32)
    m = cv2.GaussianBlur(m, (0, 0), 0.8)[..., None]
    return img * (1 - m) + np.float32(0.72) * m


def tex_carpet(rng, S):
    c = _color(rng, sat=(0.2, 0.6), val=(0.3, 0.6))
    n = 0.12 * _noise(rng, S, 60, S / 2) + 0.1 * _noise(rng, S, 2, 12) + 0.06 * _noise(rng, S, 12, 60)
    img = c[None, None] * (1 + n[..., None])
    img *= 1 + 0.05 * _noise(rng, S, 20, 80)[..., None] * np.array([1, -0.5, 0.3], np.float32)
    return img


def tex_fabric(rng, S):
    y, x = np.mgrid[0:S, 0:S].astype(np.float32)
    c1, c2 = _color(rng), _color(rng)
    px, py = S / int(rng.choice([4, 8, 16])), S / int(rng.choice([4, 8, 16]))
    a = (0.5 + 0.5 * np.sin(2 * np.pi * x / px))[..., None]
    b = (0.5 + 0.5 * np.sin(2 * np.pi * y / py))[..., None]
    img = c1[None, None] * (1 - 0.5 * a) + c2[None, None] * 0.5 * b
    weave = np.sin(np.pi * x / 2.0) * np.sin(np.pi * y / 2.0)
    img *= (1 + 0.06 * weave[..., None] + 0.06 * _fbm(rng, S)[..., None])
    return img


def tex_clutter(rng, S):
    img = np.ascontiguousarray(
        np.repeat((0.55 + 0.12 * _fbm(rng, S))[..., None], 3, 2) * _color(rng, sat=(0, 0.3),
                                                                          val=(0.7, 1.0)))
    _shapes(rng, img, int(rng.integers(40, 110)))
    return img


def tex_granite(rng, S):
    c = [_color(rng, sat=(0.0, 0.3), val=v) for v in ((0.15, 0.35), (0.45, 0.65), (0.75, 0.95))]
    n1, n2 = _noise(rng, S, 20, S / 2), _noise(rng, S, 4, 30)
    img = np.where((n1 > 1.0)[..., None], c[0], np.where((n1 < -1.0)[..., None], c[2], c[1]))
    return img.astype(np.float32) * (1 + 0.1 * n2[..., None])


def tex_whiteboard(rng, S):
    img = np.ones((S, S, 3), np.float32) * _color(rng, sat=(0, 0.05), val=(0.82, 0.95))
    img *= 1 + 0.03 * _fbm(rng, S)[..., None]   # smudges: a realistic low-texture surface
    img = np.ascontiguousarray(img)
    for _ in range(int(rng.integers(16, 32))):  # handwriting-like strokes
        col = tuple(float(c) for c in _color(rng, sat=(0.5, 0.9), val=(0.15, 0.5)))
        p = rng.uniform(0, S, 2)
        pts = [p.copy()]
        ang = rng.uniform(0, 2 * np.pi)
        for _ in range(int(rng.integers(10, 40))):
            ang += rng.normal(0, 0.8)
            p = p + 8 * np.array([math.cos(ang), math.sin(ang)])
            pts.append(p.copy())
        arr = np.array(pts, np.int32)
        _draw_tiled(img, lambda im, dx, dy: cv2.polylines(im, [arr + (dx, dy)], False, col, 2,
                                                             cv2.LINE_AA))
    return img


# ---- textures of the scene variants (--scene low_texture / repetitive)
def tex_paint(rng, S):
    """Plain matt paint: one colour with very faint large-scale mottling (~1 %)."""
    c = _color(rng, sat=(0.02, 0.2), val=(0.6, 0.85))
    n = 0.008 * _noise(rng, S, 1, 4) + 0.004 * _noise(rng, S, 4, 16)
    return c[None, None] * (1 + n[..., None])


def _two_tone(rng, pat: np.ndarray, S: int) -> np.ndarray:
    """Blend two contrasting colours by the pattern ``pat`` in [0, 1], faint grime on top."""
    c1 = _color(rng, sat=(0.0, 0.5), val=(0.7, 0.92))
    c2 = c1 * rng.uniform(0.25, 0.45)
    img = c1[None, None] * (1 - pat[..., None]) + c2[None, None] * pat[..., None]
    return img * (1 + 0.015 * _fbm(rng, S)[..., None])


def tex_checker(rng, S):
    """A regular checkerboard of 8 or 16 squares per tile side."""
    p = S // int(rng.choice([8, 16]))
    y, x = np.mgrid[0:S, 0:S]
    pat = cv2.GaussianBlur(((y // p + x // p) % 2).astype(np.float32), (0, 0), 0.8)
    return _two_tone(rng, pat, S)


def tex_stripes(rng, S):
    """Sharp regular stripes (8, 16 or 32 per tile), vertical or horizontal."""
    p = S // int(rng.choice([8, 16, 32]))
    y, x = np.mgrid[0:S, 0:S]
    coord = x if rng.uniform() < 0.5 else y
    pat = cv2.GaussianBlur(((coord % p) < p // 2).astype(np.float32), (0, 0), 0.8)
    return _two_tone(rng, pat, S)


def tex_grid(rng, S):
    """Dark grid lines (8 or 16 cells per tile side) on a plain background."""
    p = S // int(rng.choice([8, 16]))
    w = max(2, p // int(rng.integers(5, 9)))
    y, x = np.mgrid[0:S, 0:S]
    pat = cv2.GaussianBlur((((y % p) < w) | ((x % p) < w)).astype(np.float32), (0, 0), 0.8)
    return _two_tone(rng, pat, S)


def tex_brickwork(rng, S):
    """Identical bricks in running bond (16 rows x 4 per tile): no per-brick tone change."""
    bh, bw = S // 16, S // 4
    y, x = np.mgrid[0:S, 0:S]
    xs = (x + ((y // bh) % 2) * (bw // 2)) % S
    pat = cv2.GaussianBlur((((y % bh) < 4) | ((xs % bw) < 4)).astype(np.float32), (0, 0), 0.8)
    base = _color(rng, sat=(0.4, 0.65), val=(0.4, 0.6), hue=rng.uniform(0.0, 0.08))
    img = base[None, None] * (1 - pat[..., None]) + np.float32(0.8) * pat[..., None]
    return img * (1 + 0.015 * _fbm(rng, S)[..., None])


PROCEDURAL = {"plaster": tex_plaster, "wallpaper": tex_wallpaper, "wood": tex_wood,
              "tiles": tex_tiles, "bricks": tex_bricks, "carpet": tex_carpet,
              "fabric": tex_fabric, "clutter": tex_clutter, "granite": tex_granite,
              "whiteboard": tex_whiteboard, "paint": tex_paint, "checker": tex_checker,
              "stripes": tex_stripes, "grid": tex_grid, "brickwork": tex_brickwork}
PERIODIC = ("checker", "stripes", "grid", "brickwork")   # strictly periodic kinds


def to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=48)
def procedural_texture(kind: str, seed: int, slot: int) -> np.ndarray:
    """A TEX_SIZE^2 tileable uint8 RGB texture of ``kind`` (see PROCEDURAL), deterministic in
    (seed, slot); cached (read-only) so scenes re-built with one seed share textures."""
    arr = to_u8(PROCEDURAL[kind](np.random.default_rng([int(seed), 31, int(slot)]), TEX_SIZE))
    arr.setflags(write=False)
    return arr


def load_texture_images(folder, rng, S: int, max_images: int = 24) -> List[Tuple[str, np.ndarray]]:
    d = Path(folder)
    if not d.is_dir():
        raise SynthError(f"--textures folder not found: {d}")
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in IMAGE_EXTS and p.is_file())
    if not files:
        raise SynthError(f"--textures folder {d} holds no .png/.jpg images")
    if len(files) > max_images:
        files = [files[i] for i in sorted(rng.choice(len(files), max_images, replace=False))]
    out = []
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise SynthError(f"cannot read texture image {p}")
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        h, w = img.shape[:2]
        side = int(min(h, w) * rng.uniform(0.6, 1.0))
        y0, x0 = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
        crop = cv2.resize(img[y0:y0 + side, x0:x0 + side], (S, S), interpolation=cv2.INTER_AREA)
        out.append((f"image:{p.name}", crop))
    return out


def mip_levels(tex: np.ndarray, levels: int) -> List[np.ndarray]:
    out = [tex]
    for _ in range(levels - 1):
        s = out[-1].shape[0] // 2
        out.append(cv2.resize(out[-1], (s, s), interpolation=cv2.INTER_AREA))
    return out
