"""Learned flow front end: the DROID-SLAM network as a :class:`FlowPredictor` (paper Sec. 3.1).

``tracking.flow_model: /path/droid.pth`` selects it (the tracker and the loop
closer build their predictor with ``make_flow_predictor``). The checkpoint is
the public DROID-SLAM state dict: keys as saved from ``nn.DataParallel``
(``module.`` prefix, stripped here), the original parameter names and shapes;
the flow/confidence heads stored with more than two output channels are cut to
the first two, as the reference loader does. Any missing, unexpected or
mis-shaped key is a :class:`FlowModelError` naming the first such key.

Incremental use, as the tracker calls it:

* ``prepare(image)`` runs the feature and context encoders once per image and
  keeps ``fmap`` / ``net`` / ``inp`` (float16 to halve the memory of the
  tracker's keyframe store; computed in float32).
* ``predict_pair(a, b, init_ij, init_ji)`` builds one all-pairs correlation
  volume for the pair (the b -> a volume is its transpose), pools both pyramids
  and runs :func:`iterate_edges` on the two edges i -> j and j -> i; ``init_*``
  (BA-grid flows induced by the current estimate) start the correspondences,
  as the reference initialises a new edge with the reprojection.

Outputs match what BA consumes from DIS: flow (h, w, 2) float32 in BA pixels
(BA grid = 1/8 of the tracking image, so ``tracking.ba_downsample`` must be 8)
and weight (h, w, 2) in [0, 1].
"""
from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional, Tuple

import numpy as np
import torch
import torch.nn.functional as F

from splat_slam_ros.config import ConfigError
from splat_slam_ros.tracking.droid_net import (STRIDE, CorrPyramid, DroidNet, coords_grid,
                                               iterate_edges)

log = logging.getLogger(__name__)

# heads the public checkpoint stores with extra output channels (only the first two are used)
_SLICED_HEADS = ("update.weight.2.weight", "update.weight.2.bias",
                 "update.delta.2.weight", "update.delta.2.bias")


class FlowModelError(ConfigError):
    """A missing, unreadable or mis-keyed flow-model checkpoint, or an unusable setting."""


# --------------------------------------------------------------------------- loading
def _read_state_dict(path: Path) -> Dict[str, torch.Tensor]:
    if not path.is_file():
        raise FlowModelError(f"tracking.flow_model: checkpoint not found: {path}")
    try:
        obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:      # noqa: BLE001  any failure to unpickle a user file is a user error
        # (torch raises RuntimeError, UnpicklingError, IndexError, EOFError... on junk)
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise FlowModelError(f"tracking.flow_model: {path} is not a readable torch "
                             f"checkpoint ({first})") from None
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict) or not obj:
        raise FlowModelError(f"tracking.flow_model: {path} does not hold a state dict "
                             f"(found {type(obj).__name__})")
    bad = [k for k, v in obj.items() if not isinstance(k, str) or not torch.is_tensor(v)]
    if bad:
        raise FlowModelError(f"tracking.flow_model: {path}: entry {bad[0]!r} is not a tensor")
    return obj


def convert_state_dict(raw: Dict[str, torch.Tensor], model: torch.nn.Module,
                       source: str = "checkpoint") -> "OrderedDict[str, torch.Tensor]":
    """Public-layout state dict -> ``model``'s: strip ``module.``, cut the heads to two
    channels, and check every key and shape (FlowModelError naming the first bad key)."""
    sd = OrderedDict()
    for k, v in raw.items():
        sd[k[len("module."):] if k.startswith("module.") else k] = v
    for k in _SLICED_HEADS:
        if k in sd and sd[k].ndim >= 1 and sd[k].shape[0] > 2:
            sd[k] = sd[k][:2]
    want = model.state_dict()
    missing = [k for k in want if k not in sd]
    extra = [k for k in sd if k not in want]
    if missing:
        also = f", has unexpected '{extra[0]}'" if extra else ""
        raise FlowModelError(f"tracking.flow_model: {source} lacks the key '{missing[0]}'"
                             f"{also} ({len(missing)} missing; not a DROID-SLAM checkpoint?)")
    if extra:
        raise FlowModelError(f"tracking.flow_model: {source} has an unexpected key "
                             f"'{extra[0]}' (not a DROID-SLAM checkpoint?)")
    for k, v in want.items():
        if tuple(sd[k].shape) != tuple(v.shape):
            raise FlowModelError(f"tracking.flow_model: {source} key '{k}' has shape "
                                 f"{tuple(sd[k].shape)}, expected {tuple(v.shape)}")
    return sd


def load_droid_net(path, device="cpu") -> DroidNet:
    """Build :class:`DroidNet` from a checkpoint in the public layout (eval mode, on ``device``)."""
    p = Path(path).expanduser()
    raw = _read_state_dict(p)
    net = DroidNet()
    sd = convert_state_dict(raw, net, source=str(p))
    net.load_state_dict({k: v.float() for k, v in sd.items()})
    for v in net.state_dict().values():
        if not torch.isfinite(v).all():
            raise FlowModelError(f"tracking.flow_model: {p} holds non-finite weights")
    return net.to(device).eval()


def resolve_flow_device(name: str) -> torch.device:
    """``tracking.flow_device``: auto | cpu | cuda[:n]."""
    name = (name or "auto").strip()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise FlowModelError(f"tracking.flow_device={name} but CUDA is not available")
    if name != "cpu" and not name.startswith("cuda"):
        raise FlowModelError(f"tracking.flow_device={name!r}: use auto, cpu or cuda")
    try:
        return torch.device(name)
    except RuntimeError:
        raise FlowModelError(f"tracking.flow_device={name!r} is not a torch device") from None


# --------------------------------------------------------------------------- predictor
@dataclass
class DroidFeatures:
    """What :meth:`DroidFlowPredictor.prepare` keeps per image (1/8 resolution, float16)."""
    fmap: torch.Tensor        # (128, h, w) correlation features
    net: torch.Tensor         # (128, h, w) initial GRU state (tanh)
    inp: torch.Tensor         # (128, h, w) GRU context input (relu)


class DroidFlowPredictor:
    """DROID-SLAM flow + confidence for the tracker and the loop closer (see module docstring)."""

    ba_downsample = STRIDE

    def __init__(self, net: DroidNet, device="cpu", iters: int = 4, ba_downsample: int = 8):
        if ba_downsample != STRIDE:
            raise FlowModelError(f"tracking.flow_model needs tracking.ba_downsample={STRIDE} "
                                 f"(the network works at 1/{STRIDE}), got {ba_downsample}")
        if iters < 1:
            raise FlowModelError(f"tracking.flow_model_iters must be >= 1, got {iters}")
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.iters = int(iters)

    @classmethod
    def from_checkpoint(cls, path, device="auto", iters: int = 4,
                        ba_downsample: int = 8) -> "DroidFlowPredictor":
        dev = resolve_flow_device(device) if isinstance(device, str) else torch.device(device)
        pred = cls(load_droid_net(path, dev), dev, iters, ba_downsample)
        log.info("DROID-SLAM flow network loaded from %s on %s (%d GRU iterations)",
                 path, dev, iters)
        return pred

    # -------------------------------------------------------------- prepare
    def prepare(self, image) -> DroidFeatures:
        """Tracking-resolution uint8 RGB (H x W x 3, H and W multiples of 8) -> features."""
        img = torch.as_tensor(np.ascontiguousarray(image))
        if img.ndim == 2:
            img = img[..., None].expand(-1, -1, 3)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != torch.uint8:
            raise FlowModelError(f"flow model input must be H x W x 3 uint8, got "
                                 f"{tuple(img.shape)} {img.dtype}")
        H, W = img.shape[:2]
        if H % STRIDE or W % STRIDE or H < 8 * STRIDE or W < 8 * STRIDE:
            raise FlowModelError(f"the DROID flow model needs a tracking image of at least "
                                 f"{8 * STRIDE}x{8 * STRIDE} with sides divisible by {STRIDE}, "
                                 f"got {W}x{H}")
        with torch.no_grad():
            fmap, net, inp = self.net.features(img[None].to(self.device))
        return DroidFeatures(fmap[0].half(), net[0].half(), inp[0].half())

    def _as_features(self, x) -> DroidFeatures:
        return x if isinstance(x, DroidFeatures) else self.prepare(x)

    # -------------------------------------------------------------- predict
    def _start(self, init: Optional[torch.Tensor], h: int, w: int) -> torch.Tensor:
        c0 = coords_grid(h, w, self.device)
        if init is None:
            return c0
        init = torch.as_tensor(init, dtype=torch.float32, device=self.device)
        if tuple(init.shape) != (h, w, 2):
            raise FlowModelError(f"initial flow has shape {tuple(init.shape)}, expected "
                                 f"{(h, w, 2)}")
        return c0 + torch.nan_to_num(init, nan=0.0, posinf=0.0, neginf=0.0)

    def _invert(self, flow: torch.Tensor, iters: int = 3) -> torch.Tensor:
        """Approximate inverse of a smooth flow field: g(y) = -f(y + g(y))."""
        h, w = flow.shape[:2]
        c0 = coords_grid(h, w, flow.device)
        src = flow.permute(2, 0, 1)[None]
        g = -flow
        for _ in range(iters):
            p = c0 + g
            grid = torch.stack([2 * p[..., 0] / max(w - 1, 1) - 1,
                                2 * p[..., 1] / max(h - 1, 1) - 1], -1)
            g = -F.grid_sample(src, grid[None], mode="bilinear", padding_mode="border",
                               align_corners=True)[0].permute(1, 2, 0)
        return g

    def predict_pair(self, img_i, img_j, init_ij: Optional[torch.Tensor] = None,
                     init_ji: Optional[torch.Tensor] = None):
        """(f_ij, w_ij, f_ji, w_ji) at the BA grid; ``init_*`` (h, w, 2) BA-pixel flows
        expected from the current estimate start the iteration (``init_ji`` defaults to
        the inverse of ``init_ij``)."""
        A, B = self._as_features(img_i), self._as_features(img_j)
        _, h, w = A.fmap.shape
        if tuple(B.fmap.shape) != tuple(A.fmap.shape):
            raise FlowModelError(f"images of different sizes: {tuple(A.fmap.shape[1:])} vs "
                                 f"{tuple(B.fmap.shape[1:])} (BA grid)")
        with torch.no_grad():
            c_ij = self._start(init_ij, h, w)
            if init_ji is None and init_ij is not None:
                c_ji = coords_grid(h, w, self.device) + self._invert(c_ij - coords_grid(
                    h, w, self.device))
            else:
                c_ji = self._start(init_ji, h, w)
            corr = CorrPyramid.pair(A.fmap.float(), B.fmap.float())   # edges i->j, j->i
            net = torch.stack([A.net, B.net]).float()
            inp = torch.stack([A.inp, B.inp]).float()
            ii = torch.tensor([0, 1], device=self.device)
            res = iterate_edges(self.net.update, corr, net, inp, torch.stack([c_ij, c_ji]),
                                ii, self.iters)
            flow = (res.target - coords_grid(h, w, self.device)[None]).float()
            weight = res.weight.float().clamp(0.0, 1.0)
        return flow[0], weight[0], flow[1], weight[1]

    def predict(self, img_i, img_j) -> Tuple[torch.Tensor, torch.Tensor]:
        f_ij, w_ij, _, _ = self.predict_pair(img_i, img_j)
        return f_ij, w_ij


def make_droid_predictor(tcfg) -> DroidFlowPredictor:
    """The learned predictor from a TrackingConfig with ``flow_model`` set."""
    return DroidFlowPredictor.from_checkpoint(
        tcfg.flow_model, device=tcfg.flow_device, iters=tcfg.flow_model_iters,
        ba_downsample=tcfg.ba_downsample)
