"""Figures and image tiles of the run report (matplotlib Agg, deterministic output).

Every figure has a fixed size and DPI and is saved without a ``Software`` tag or date, so
the same run directory always gives the same PNG bytes (the report is rebuilt identically).
"""
from __future__ import annotations

import io
from typing import Dict, List, Optional, Sequence

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

DPI = 100
PNG_META = {"Software": None}
ERROR_RANGE = 0.25          # colour error shown from 0 to this (mean |RGB| in [0, 1])
EMPTY_GREY = 48             # pixels without depth


# ------------------------------------------------------------------ image tiles
def _colormap(values: torch.Tensor, name: str) -> np.ndarray:
    """(H, W) values in [0, 1] -> (H, W, 3) uint8 RGB through a matplotlib colour map."""
    lut = torch.from_numpy((matplotlib.colormaps[name](np.linspace(0, 1, 256))[:, :3] * 255
                            + 0.5).astype(np.uint8))
    idx = (values.clamp(0, 1) * 255 + 0.5).long()
    return lut.to(values.device)[idx].cpu().numpy()


def depth_range(*depths: torch.Tensor) -> tuple:
    """2nd-98th percentile of the positive depths of the first map that has any."""
    for d in depths:
        v = d[d > 0]
        if v.numel() >= 2:
            q = torch.quantile(v.double()[:: max(1, v.numel() // 100000)],
                               torch.tensor([0.02, 0.98], dtype=torch.float64))
            lo, hi = float(q[0]), float(q[1])
            return lo, max(hi, lo + 1e-6)
    return 0.0, 1.0


def colour_depth(depth: torch.Tensor, lo: float, hi: float) -> np.ndarray:
    """Depth (H, W) -> turbo colours in [lo, hi] (near blue, far red); no depth = grey."""
    rgb = _colormap((depth.double() - lo) / (hi - lo), "turbo")
    rgb[(depth <= 0).cpu().numpy()] = EMPTY_GREY
    return rgb


def colour_error(render: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per-pixel mean absolute colour error, 0..ERROR_RANGE on the magma colour map."""
    a = torch.from_numpy(np.ascontiguousarray(render)).double() / 255.0
    b = torch.from_numpy(np.ascontiguousarray(ref)).double() / 255.0
    return _colormap((a - b).abs().mean(-1) / ERROR_RANGE, "magma")


def png_bytes(rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def jpeg_bytes(rgb: np.ndarray, quality: int = 88) -> bytes:
    """Photographic tiles of the keyframe grid (a fifth of the PNG size, deterministic)."""
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def thumbnail(rgb: np.ndarray, max_width: int) -> np.ndarray:
    h, w = rgb.shape[:2]
    if w <= max_width:
        return rgb
    return cv2.resize(rgb, (max_width, max(1, round(h * max_width / w))),
                      interpolation=cv2.INTER_AREA)


def fig_png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata=PNG_META)
    plt.close(fig)
    return buf.getvalue()


def _note(ax, text: str, title: str = "") -> None:
    """An empty panel saying why (``text``), under ``title``."""
    if title:
        ax.set_title(title, fontsize=9)
    ax.text(0.5, 0.5, text, ha="center", va="center", fontsize=9, wrap=True,
            transform=ax.transAxes, color="0.35")
    ax.set_xticks([])
    ax.set_yticks([])


# ------------------------------------------------------------------ panels
def plane_axes(P: np.ndarray) -> tuple:
    """The two position axes with the largest spread (the top view of the path)."""
    order = np.argsort(-np.ptp(P, axis=0), kind="stable")
    return tuple(sorted(int(i) for i in order[:2]))


def draw_trajectory(ax, est: Optional[np.ndarray], gt: Optional[np.ndarray],
                    kf: Optional[np.ndarray], title: str) -> None:
    """Top view: ground truth (black), aligned estimate (red), keyframes (dots)."""
    ref = gt if gt is not None else est
    if ref is None or len(ref) == 0:
        _note(ax, "no trajectory")
        return
    i, j = plane_axes(ref)
    if gt is not None:
        ax.plot(gt[:, i], gt[:, j], "k-", lw=1.2, label="ground truth")
    if est is not None and len(est):
        ax.plot(est[:, i], est[:, j], "-", color="tab:red", lw=1.0,
                label="estimate" + (" (Sim(3) aligned)" if gt is not None else ""))
    if kf is not None and len(kf):
        ax.plot(kf[:, i], kf[:, j], ".", color="tab:blue", ms=4, label="keyframes")
    ax.plot(ref[0, i], ref[0, j], "go", ms=5, label="start")
    ax.set_xlabel("xyz"[i] + (" [m]" if gt is not None else " [map units]"))
    ax.set_ylabel("xyz"[j] + (" [m]" if gt is not None else " [map units]"))
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    ax.set_title(title, fontsize=9)


def draw_error(ax, t: Optional[np.ndarray], err: Optional[np.ndarray], rmse: Optional[float],
               missing: str) -> None:
    if t is None or err is None or len(err) == 0:
        _note(ax, missing, "trajectory error over time")
        return
    ax.plot(t - t[0], err, "-", color="tab:purple", lw=1.0)
    if rmse is not None:
        ax.axhline(rmse, color="k", ls="--", lw=0.8, label=f"rmse {rmse:.2f} cm")
        ax.legend(fontsize=7)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("ATE [cm]")
    ax.grid(alpha=0.3)
    ax.set_title("trajectory error over time (per frame)", fontsize=9)


def draw_map_size(ax, history: Sequence[dict], missing: str) -> None:
    if not history:
        _note(ax, missing, "map size")
        return
    stamps = [h.get("timestamp") for h in history]
    if all(isinstance(t, (int, float)) for t in stamps):
        x = np.array(stamps, dtype=np.float64) - float(stamps[0])
        xlabel = "keyframe time [s] (each keyframe offered to the mapper)"
    else:
        x = np.arange(1, len(history) + 1, dtype=np.float64)
        xlabel = "keyframes offered to the mapper"
    g = np.array([h["gaussians"] for h in history], dtype=np.float64)
    k = np.array([h["keyframes"] for h in history], dtype=np.float64)
    ax.plot(x, g, ".-", color="tab:green", lw=1.2, ms=3, label="Gaussians")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("Gaussians", color="tab:green")
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.step(x, k, where="post", color="tab:blue", lw=1.0, label="mapped keyframes")
    ax2.set_ylabel("mapped keyframes", color="tab:blue")
    ax.set_title("map size over the run", fontsize=9)


def draw_timings(ax, stages: Dict[str, float], unit: str, missing: str) -> None:
    if not stages:
        _note(ax, missing, "time per stage")
        return
    names = list(stages)
    vals = np.array([stages[n] for n in names], dtype=np.float64)
    y = np.arange(len(names))
    ax.barh(y, vals, color="tab:orange")
    ax.set_yticks(y)
    ax.set_yticklabels(names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel(unit)
    for yi, v in zip(y, vals):
        ax.text(v, yi, f" {v:.1f}", va="center", fontsize=7)
    ax.grid(alpha=0.3, axis="x")
    ax.set_title("time per stage", fontsize=9)


def draw_keyframe_metrics(ax, kfs: Sequence[dict], missing: str) -> None:
    if not kfs:
        _note(ax, missing, "keyframe quality")
        return
    x = [k["kf_id"] for k in kfs]
    ax.plot(x, [k["psnr"] for k in kfs], "o-", color="tab:red", ms=3, lw=0.8, label="PSNR")
    ax.set_xlabel("keyframe id")
    ax.set_ylabel("PSNR [dB]", color="tab:red")
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.plot(x, [k["ssim"] for k in kfs], "s--", color="tab:blue", ms=3, lw=0.8)
    ax2.set_ylabel("SSIM", color="tab:blue")
    ax.set_title("keyframe quality (rendered vs input)", fontsize=9)


def draw_tiles(ax, tiles: Optional[List[np.ndarray]], labels: Sequence[str], title: str,
               missing: str) -> None:
    """A 2-row mosaic of equally sized RGB tiles."""
    if not tiles:
        _note(ax, missing, "keyframe")
        return
    h, w = tiles[0].shape[:2]
    cols = (len(tiles) + 1) // 2
    canvas = np.full((2 * h, cols * w, 3), 255, np.uint8)
    for n, t in enumerate(tiles):
        r, c = divmod(n, cols)
        canvas[r * h:(r + 1) * h, c * w:(c + 1) * w] = t
    ax.imshow(canvas, interpolation="nearest")
    for n, lab in enumerate(labels):
        r, c = divmod(n, cols)
        ax.text(c * w + 3, r * h + 3, lab, fontsize=6, va="top", color="white",
                bbox={"facecolor": "black", "alpha": 0.6, "pad": 1, "lw": 0})
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=9)


def new_figure(w: float, h: float, rows: int = 1, cols: int = 1):
    fig, ax = plt.subplots(rows, cols, figsize=(w, h), dpi=DPI)
    return fig, ax
