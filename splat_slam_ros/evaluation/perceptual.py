"""LPIPS-style perceptual distance with a user-supplied backbone file (no downloads):
loading and caching the backbone and its per-layer channel weights, the distance."""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Dict, List, Optional

import torch

from splat_slam_ros.evaluation.inputs import MetricError, image_pair


_LPIPS_CACHE: Dict[tuple, tuple] = {}
_WEIGHT_NAME = re.compile(r"(?:^|\.)(?:lpips_w(\d+)|lin(\d+)(?:\.model\.1)?\.weight)$")


def _weights_from_named(named) -> Optional[List[torch.Tensor]]:
    """Per-layer channel weights from names ``lpips_w<i>`` or ``lin<i>[.model.1].weight``."""
    found = {}
    for name, v in named:
        m = _WEIGHT_NAME.search(name)
        if m and torch.is_tensor(v):
            found[int(m.group(1) or m.group(2))] = v.detach().float().reshape(-1)
    if not found:
        return None
    if sorted(found) != list(range(len(found))):
        raise MetricError(f"LPIPS layer weights are not numbered 0..n-1: {sorted(found)}")
    return [found[i] for i in range(len(found))]


def _load_weights(path: Path) -> List[torch.Tensor]:
    if not path.is_file():
        raise MetricError(f"LPIPS weights file not found: {path}")
    try:
        obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any load failure is a user-file problem
        raise MetricError(f"cannot read LPIPS weights file {path}: "
                          f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}") from None
    if isinstance(obj, (list, tuple)) and all(torch.is_tensor(v) for v in obj):
        return [v.detach().float().reshape(-1) for v in obj]
    if isinstance(obj, dict):
        w = _weights_from_named(obj.items())
        if w is not None:
            return w
    raise MetricError(f"LPIPS weights file {path} must hold a list of per-layer tensors or a "
                      "state dict with keys 'lin<i>.model.1.weight' / 'lpips_w<i>'")


def _load_backbone(p: Path) -> torch.nn.Module:
    """TorchScript file (torch.jit.save), else a torch.export program (torch.export.save)."""
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)   # torch.jit is deprecated in 2.x
        try:
            return torch.jit.load(str(p), map_location="cpu")
        except Exception as e:  # noqa: BLE001 - any failure means "not TorchScript"
            jit_err = type(e).__name__
        try:
            return torch.export.load(str(p)).module()
        except Exception:  # noqa: BLE001
            pass
    raise MetricError(f"LPIPS backbone {p} is not a loadable TorchScript file ({jit_err}) nor "
                      "a torch.export program; save it with torch.jit.save or torch.export.save")


def _load_lpips(model, weights_path, device) -> tuple:
    if isinstance(model, torch.nn.Module):
        key = (id(model), str(weights_path), str(device))
    else:
        p = Path(os.fspath(model))
        if not p.is_file():
            raise MetricError(f"LPIPS backbone file not found: {p}")
        key = (str(p.resolve()), p.stat().st_mtime_ns, str(weights_path), str(device))
    if key in _LPIPS_CACHE:
        return _LPIPS_CACHE[key]
    if not isinstance(model, torch.nn.Module):
        net = _load_backbone(p)
    else:
        net = model
    try:
        net = net.eval()
    except NotImplementedError:          # torch.export modules have no train/eval switch
        pass
    if torch.device(device) != torch.device("cpu"):
        try:
            net = net.to(device)
        except Exception as e:  # noqa: BLE001
            raise MetricError(f"cannot move the LPIPS backbone to {device}: "
                              f"{type(e).__name__}") from None
    if weights_path is not None:
        weights = _load_weights(Path(os.fspath(weights_path)))
    else:
        weights = _weights_from_named(list(net.named_buffers()) + list(net.named_parameters()))
    entry = (net, None if weights is None else [w.to(device) for w in weights])
    _LPIPS_CACHE.clear()                 # keep one model in memory
    _LPIPS_CACHE[key] = entry
    return entry


def lpips(img, ref, model_path, weights_path=None, layer_reduce: str = "sum") -> float:
    """LPIPS-style perceptual distance with a user-supplied backbone (no downloads).

    ``model_path``: a TorchScript file (``torch.jit.save``; a ``torch.export.save`` program
    also loads) or an ``nn.Module`` whose
    forward maps a (B, 3, H, W) batch in [-1, 1] to a list/tuple of feature maps
    (B, C_l, H_l, W_l) (a single tensor counts as one layer); any input normalisation
    belongs inside the module. Per-layer channel weights ``w_l`` come from
    ``weights_path`` (a ``torch.save``d list of tensors, or a state dict with keys
    ``lin<i>.model.1.weight`` like the official LPIPS files, or ``lpips_w<i>``), else
    from buffers/parameters named that way inside the module, else all ones.
    Distance (the LPIPS formula): for each layer, unit-normalise features over channels,
    take ``sum_c w_c (f1 - f2)^2`` averaged over space; then sum over layers
    (``layer_reduce='mean'`` averages instead). Identical images give 0.
    """
    if layer_reduce not in ("sum", "mean"):
        raise MetricError(f"layer_reduce must be 'sum' or 'mean', got {layer_reduce!r}")
    a, b = image_pair(img, ref)
    if a.shape[-1] == 1:
        a, b = a.expand(-1, -1, 3), b.expand(-1, -1, 3)
    device = a.device
    net, weights = _load_lpips(model_path, weights_path, device)
    x = torch.stack([a, b]).permute(0, 3, 1, 2).float() * 2 - 1
    try:
        with torch.no_grad():
            feats = net(x)
    except Exception as e:  # noqa: BLE001
        msg = str(e).strip().splitlines()
        raise MetricError(f"LPIPS backbone failed on a {tuple(x.shape)} batch: "
                          f"{type(e).__name__}{': ' + msg[-1][:200] if msg else ''}") from None
    if torch.is_tensor(feats):
        feats = [feats]
    if (not isinstance(feats, (list, tuple)) or not feats
            or not all(torch.is_tensor(f) and f.ndim == 4 and f.shape[0] == 2 for f in feats)):
        raise MetricError("LPIPS backbone must return a tensor or a list/tuple of (B, C, H, W) "
                          "feature maps")
    if weights is not None and len(weights) != len(feats):
        raise MetricError(f"LPIPS weights have {len(weights)} layers but the backbone returns "
                          f"{len(feats)} feature maps")
    dists = []
    for li, f in enumerate(feats):
        f = f.double()
        f = f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)     # unit-normalise channels
        d2 = (f[0] - f[1]).pow(2)                                  # (C, H, W)
        if weights is not None:
            w = weights[li].double()
            if w.numel() != d2.shape[0]:
                raise MetricError(f"LPIPS layer {li}: {w.numel()} weights for "
                                  f"{d2.shape[0]} channels")
            d2 = d2 * w[:, None, None]
        dists.append(d2.sum(0).mean())
    d = torch.stack(dists)
    return float(d.sum() if layer_reduce == "sum" else d.mean())


def check_lpips(model_path, weights_path=None) -> None:
    """Load an LPIPS backbone file (and weights file) as :func:`lpips` does, then drop it:
    MetricError at once when a file is missing or is no backbone / weights file (before a
    run whose LPIPS would fail at its end)."""
    try:
        _load_lpips(model_path, weights_path or None, "cpu")
    finally:
        release_lpips()


def release_lpips() -> None:
    """Free the backbone :func:`lpips` keeps loaded between calls."""
    _LPIPS_CACHE.clear()
