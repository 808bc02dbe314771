"""Camera realism applied to rendered RGB: auto-exposure drift, vignetting, shot/read noise,
JPEG (motion blur is done by the sequence renderer from sub-exposures)."""
from __future__ import annotations

from typing import Tuple

import cv2
import numpy as np

from splat_slam_synth.options import RealismOptions
from splat_slam_ros.types import Intrinsics


def _smooth_signal(rng, n_terms: int = 3) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    periods = rng.uniform(3.0, 14.0, n_terms)
    phases = rng.uniform(0, 2 * np.pi, n_terms)
    amps = rng.uniform(0.5, 1.0, n_terms)
    return periods, phases, amps / amps.sum()


def _eval_signal(sig, t: float) -> float:
    periods, phases, amps = sig
    return float(np.sum(amps * np.sin(2 * np.pi * t / periods + phases)))


class CameraEffects:
    """Per-frame photometric camera model applied to a float render in [0, 255]."""

    def __init__(self, opts: RealismOptions, K: Intrinsics, seed: int):
        self.opts, self.seed = opts, int(seed)
        rng = np.random.default_rng([self.seed, 17])
        self.gain_sig, self.off_sig = _smooth_signal(rng), _smooth_signal(rng)
        v, u = np.mgrid[0:K.height, 0:K.width].astype(np.float32)
        r2 = (u - K.cx) ** 2 + (v - K.cy) ** 2
        r2max = max((x - K.cx) ** 2 + (y - K.cy) ** 2 for x in (0, K.width - 1)
                    for y in (0, K.height - 1))
        self.vig = (1.0 - opts.vignetting * r2 / r2max).astype(np.float32)[..., None]

    def gain_offset(self, t_rel: float) -> Tuple[float, float]:
        A = self.opts.auto_exposure
        if A <= 0:
            return 1.0, 0.0
        return 1.0 + A * _eval_signal(self.gain_sig, t_rel), 0.25 * A * 255.0 * _eval_signal(
            self.off_sig, t_rel)

    def __call__(self, img: np.ndarray, index: int, t_rel: float) -> np.ndarray:
        o = self.opts
        x = img
        if o.vignetting > 0:
            x = x * self.vig
        if o.auto_exposure > 0:
            g, b = self.gain_offset(t_rel)
            x = x * g + b
        if o.noise > 0:
            rng = np.random.default_rng([self.seed, 23, int(index)])
            # read noise std = noise/2; shot noise variance grows linearly with intensity
            var = (0.25 * o.noise ** 2) + (0.75 * o.noise ** 2 / 127.5) * np.clip(x, 0, 255)
            x = x + rng.standard_normal(x.shape, dtype=np.float32) * np.sqrt(var)
        out = np.clip(x + 0.5, 0, 255).astype(np.uint8)
        if o.jpeg > 0:
            ok, enc = cv2.imencode(".jpg", cv2.cvtColor(out, cv2.COLOR_RGB2BGR),
                                   [int(cv2.IMWRITE_JPEG_QUALITY), int(o.jpeg)])
            out = cv2.cvtColor(cv2.imdecode(enc, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        return out
