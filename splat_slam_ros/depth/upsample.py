"""Upsampling of BA-resolution disparity to the tracking resolution (proxy depth, step 2 of
:mod:`splat_slam_ros.depth.proxy_depth`): bilinear in disparity inside smooth BA cells, one
corner's value (the one that best explains the pixel's colour, or the nearest) elsewhere, so
that no "flying" depth appears across a discontinuity."""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import torch


def smooth_cells(disp: torch.Tensor, valid: torch.Tensor, disc: float = 0.1,
                 kappa: float = 1.5) -> torch.Tensor:
    """(h-1, w-1) flags: may the 2x2 BA cell with top-left corner (i, j) be interpolated?

    Yes when its 4 disparities are valid and either within ``1 + disc`` of each other, or
    continuous along both axes: on each of its two rows (columns) the step across the cell
    is at most ``kappa`` x the larger step of the neighbouring cells on that row (column)
    plus ``disc/4`` x the disparity. Disparity is affine in the pixel coordinates on a 3D
    plane, so steep planes (floors at grazing angles) and creases (wall corners) pass; a
    jump between two surfaces is much larger than the steps on either side and does not.
    """
    d = torch.where(valid, disp, torch.zeros_like(disp)).to(torch.float32)
    v = valid
    a, b, c, e = d[:-1, :-1], d[:-1, 1:], d[1:, :-1], d[1:, 1:]
    v4 = v[:-1, :-1] & v[:-1, 1:] & v[1:, :-1] & v[1:, 1:]
    dmax = torch.maximum(torch.maximum(a, b), torch.maximum(c, e))
    dmin = torch.minimum(torch.minimum(a, b), torch.minimum(c, e))
    close = dmax <= (1.0 + disc) * dmin
    eps = 0.25 * disc * dmin

    def continuous(dd, vv):
        # steps along the last axis (h', w-1), 0 where a side is missing / invalid
        g = torch.where(vv[..., :-1] & vv[..., 1:], (dd[..., 1:] - dd[..., :-1]).abs(),
                        torch.zeros_like(dd[..., 1:]))
        z = torch.zeros_like(g[..., :1])
        side = torch.maximum(torch.cat([z, g[..., :-1]], -1), torch.cat([g[..., 1:], z], -1))
        return g <= kappa * side                        # (h', w-1)

    cx = continuous(d, v)                               # rows: (h, w-1)
    cy = continuous(d.T, v.T).T                         # columns: (h-1, w)
    gx0, gx1 = (b - a).abs(), (e - c).abs()
    gy0, gy1 = (c - a).abs(), (e - b).abs()
    okx = (cx[:-1] | (gx0 <= eps)) & (cx[1:] | (gx1 <= eps))
    oky = (cy[:, :-1] | (gy0 <= eps)) & (cy[:, 1:] | (gy1 <= eps))
    return v4 & (close | (okx & oky))


def _cell_coords(H: int, W: int, h: int, w: int, device):
    ys = (torch.arange(H, device=device, dtype=torch.float32) + 0.5) * (h / H) - 0.5
    xs = (torch.arange(W, device=device, dtype=torch.float32) + 0.5) * (w / W) - 0.5
    y0 = ys.floor().long().clamp(0, max(h - 2, 0))
    x0 = xs.floor().long().clamp(0, max(w - 2, 0))
    return ys, xs, y0, x0


@torch.no_grad()
def corner_preference(image, h: int, w: int, sigma_color: float = 20.0,
                      sigma_space: float = 0.5) -> torch.Tensor:
    """For every pixel of ``image`` (H, W, 3), which of the 4 corners of its BA cell
    (00, 01, 10, 11 -> 0..3) explains it best: minimum of |colour - mean colour of the
    corner's BA block|^2 / sigma_color^2 + (distance to the corner in BA pixels)^2 /
    sigma_space^2. Returns (H, W) uint8. Depends on the image only: computed once per
    keyframe and reused whenever its depth is recomputed."""
    img = torch.as_tensor(np.asarray(image)).to(torch.float32)
    H, W = img.shape[:2]
    dev = img.device
    blocks = torch.nn.functional.adaptive_avg_pool2d(img.permute(2, 0, 1)[None], (h, w))[0]
    ys, xs, y0, x0 = _cell_coords(H, W, h, w, dev)
    img = img.permute(2, 0, 1)                                                  # (3, H, W)
    best = None
    for n, (cy, cx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        yk = (y0 + cy).clamp(max=h - 1)
        xk = (x0 + cx).clamp(max=w - 1)
        col = blocks.index_select(1, yk).index_select(2, xk)                    # (3, H, W)
        c = ((img - col) ** 2).sum(0) * (1.0 / sigma_color ** 2)
        c += ((ys - yk) ** 2 / sigma_space ** 2)[:, None]
        c += ((xs - xk) ** 2 / sigma_space ** 2)[None, :]
        if best is None:
            best, arg = c, torch.zeros(H, W, dtype=torch.uint8, device=dev)
        else:
            better = c < best
            best = torch.minimum(best, c)
            arg = arg.masked_fill(better, n)
    return arg


@torch.no_grad()
def upsample_disparity(disp: torch.Tensor, valid: torch.Tensor, out_hw: Tuple[int, int],
                       disc: float = 0.1, guide: Optional[torch.Tensor] = None
                       ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Disparity (h, w) + validity -> (H, W) disparity + validity, pixel-centre aligned.

    Bilinear in disparity inside BA cells that :func:`smooth_cells` accepts (the outer half
    BA pixel at the image border is extrapolated linearly from the border cell). Elsewhere
    (cells across a depth edge or touching invalid pixels) one corner value is copied:
    without ``guide`` the nearest BA pixel; with ``guide`` (:func:`corner_preference` of the
    keyframe image) the corner whose colour and position explain the pixel best - the depth
    edge then follows the image edge instead of the BA grid. The pixel is invalid when that
    corner is. No in-between ("flying") depth is ever produced across an edge.
    """
    h, w = disp.shape
    H, W = out_hw
    dev = disp.device
    d = torch.where(valid, disp, torch.zeros_like(disp)).to(torch.float32)
    vf = valid.to(torch.uint8)

    def take(a, yi, xi):                            # separable gather: rows, then columns
        return a.index_select(0, yi).index_select(1, xi)

    ys, xs, y0, x0 = _cell_coords(H, W, h, w, dev)
    yn = ys.round().long().clamp(0, h - 1)
    xn = xs.round().long().clamp(0, w - 1)
    near = take(d, yn, xn)
    near_ok = take(vf, yn, xn).bool()
    if h < 2 or w < 2:
        return torch.where(near_ok, near, torch.zeros_like(near)), near_ok
    y1, x1 = y0 + 1, x0 + 1
    ay = (ys - y0).clamp(-0.5, 1.5)[:, None]
    ax = (xs - x0).clamp(-0.5, 1.5)[None, :]
    r0, r1 = d.index_select(0, y0), d.index_select(0, y1)
    d00, d01, d10, d11 = (r0.index_select(1, x0), r0.index_select(1, x1),
                          r1.index_select(1, x0), r1.index_select(1, x1))
    smooth = take(smooth_cells(disp, valid, disc).to(torch.uint8), y0, x0).bool()
    bil = (d00 * (1 - ax) + d01 * ax) * (1 - ay) + (d10 * (1 - ax) + d11 * ax) * ay
    smooth &= bil > 0                               # extrapolation must stay in front
    if guide is not None:
        best = guide.to(dev).long()[..., None]                            # best corner
        corners = torch.stack([d00, d01, d10, d11], -1)
        near = corners.gather(-1, best)[..., 0]
        near_ok = near > 0
    out = torch.where(smooth, bil, near)
    ok = smooth | near_ok
    return torch.where(ok, out, torch.zeros_like(out)), ok
