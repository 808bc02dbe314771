"""The camera's photometric response the map is rendered through (Eq. 11's exposure).

Per mapped keyframe k an affine exposure ``kf.exposure = (log a_k, b_k)``: the rendered
colour becomes a_k C_k + b_k; the first keyframe fixes the gauge (a = 1, b = 0) and is not
optimised. With ``mapping.vignetting`` a radial falloff V = 1 + v1 r^2 + v2 r^4 shared by
all keyframes multiplies the colour first. :class:`CameraModel` holds v1, v2 and the Adam
optimiser of the exposures and the vignetting.
"""
from __future__ import annotations

from typing import Dict, Optional

import torch

from splat_slam_ros.mapping.keyframe_inputs import MappedKeyframe


class CameraModel:
    """Per-keyframe exposure (a_k, b_k of Eq. 11) and the learned vignetting (v1, v2)."""

    def __init__(self, mcfg, device):
        self.mcfg = mcfg
        self.device = device
        self.opt: Optional[torch.optim.Optimizer] = None
        self.vignette = torch.zeros(2, device=device, requires_grad=mcfg.vignetting)  # v1, v2
        self._r2: Dict[tuple, torch.Tensor] = {}        # (H, W, cx, cy) -> r^2 map

    def expose(self, rgb: torch.Tensor, kf: MappedKeyframe, intr) -> torch.Tensor:
        """The camera's response to rendered colour: a_k V C_k + b_k (Eq. 11's exposure, with
        the learned vignetting V when ``mapping.vignetting``)."""
        if self.mcfg.vignetting:
            rgb = rgb * self.vignetting(rgb.shape[0], rgb.shape[1], intr)
        return rgb * kf.exposure[0].exp() + kf.exposure[1]      # a_k C_k + b_k (Eq. 11)

    def vignetting(self, H: int, W: int, intr) -> torch.Tensor:
        """(H, W, 1) radial falloff 1 + v1 r^2 + v2 r^4 (:meth:`r2`)."""
        r2 = self.r2(H, W, intr)[..., None]
        v = self.vignette
        return (1.0 + v[0] * r2 + v[1] * r2 * r2).clamp_min(0.1)

    def r2(self, H: int, W: int, intr) -> torch.Tensor:
        """(H, W) squared distance from the principal point / half the image diagonal (the
        same at any render size), cached per size and principal point."""
        key = (H, W, *intr[2:])
        r2 = self._r2.get(key)
        if r2 is None:
            ys = torch.arange(H, dtype=torch.float32, device=self.device)[:, None]
            xs = torch.arange(W, dtype=torch.float32, device=self.device)[None, :]
            r2 = ((xs - intr[2]) ** 2 + (ys - intr[3]) ** 2) / (0.25 * (W * W + H * H))
            r2 = self._r2.setdefault(key, r2.contiguous())
        return r2

    def add_keyframe(self, kf: MappedKeyframe) -> None:
        """A mapped keyframe's exposure (Eq. 11 affine a, b) joins the optimiser, except for
        the first keyframe's, which fixes the gauge (a = 1, b = 0)."""
        if kf.index > 0:
            kf.exposure.requires_grad_(True)
            grp = {"params": [kf.exposure], "lr": self.mcfg.lr_exposure}
            if self.opt is None:                      # the vignetting needs two views too
                vig = [{"params": [self.vignette], "lr": self.mcfg.lr_vignetting}] \
                    if self.mcfg.vignetting else []
                self.opt = torch.optim.Adam([grp] + vig, lr=self.mcfg.lr_exposure)
            else:
                self.opt.add_param_group(grp)

    def drop_keyframe(self, kf: MappedKeyframe) -> None:
        """A merged keyframe's exposure leaves the optimiser."""
        if self.opt is not None:
            self.opt.param_groups = [g for g in self.opt.param_groups
                                     if g["params"][0] is not kf.exposure]
            self.opt.state.pop(kf.exposure, None)

    def zero_grad(self) -> None:
        if self.opt is not None:
            self.opt.zero_grad(set_to_none=True)

    def step(self) -> None:
        if self.opt is not None:
            self.opt.step()
