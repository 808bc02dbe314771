"""Pure-torch rasterizer: the ground truth the C++ kernel is tested against.

Same rules as the kernel (``csrc/raster.cpp``), written as plainly as possible and
differentiated by autograd:

* Gaussians are sorted front to back by float32 depth, ties broken by index;
* Gaussian ``i`` touches pixel ``x`` only inside its footprint (``Projected.ranges``);
* ``alpha_i = min(0.99, o_i exp(max(-12, -0.5 d^T Sigma'^-1 d)))`` (paper Eq. 9),
  ignored when ``< 1/255``;
* a pixel stops at the first Gaussian that would bring its transmittance below 1e-4
  (that Gaussian and all later ones are ignored);
* ``C = sum c_i alpha_i T_i + T_N bg``, ``D = sum z_i alpha_i T_i``, ``A = 1 - T_N``
  (paper Eq. 8);
* visible: ``alpha_i T_i > 0`` at some pixel with ``T_i >= 0.5`` (supplementary, covisibility).

The image is cut into tiles only to bound memory (the result does not depend on the tile
size); each chunk of tiles is evaluated densely against the Gaussians overlapping it.
"""
from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
POWER_MIN = -12.0
VISIBLE_T = 0.5


def _tile_pairs(ranges: torch.Tensor, depths: torch.Tensor, tile: int, tiles_x: int):
    """(tile id, gaussian id) pairs sorted by tile, then depth (float32), then index."""
    dev = ranges.device
    valid = ranges[:, 0] <= ranges[:, 1]
    gid = torch.nonzero(valid).squeeze(1)
    r = ranges[gid].long()
    tx0, tx1 = r[:, 0] // tile, r[:, 1] // tile
    ty0, ty1 = r[:, 2] // tile, r[:, 3] // tile
    ntx, nty = tx1 - tx0 + 1, ty1 - ty0 + 1
    cnt = ntx * nty
    total = int(cnt.sum())
    rep = torch.repeat_interleave(torch.arange(len(gid), device=dev), cnt)
    start = torch.cumsum(cnt, 0) - cnt
    local = torch.arange(total, device=dev) - start[rep]
    tile_id = (ty0[rep] + local // ntx[rep]) * tiles_x + tx0[rep] + local % ntx[rep]
    # depth rank: stable sort of float32 depths (ties -> lower index first), as the kernel
    order = torch.sort(depths.detach().float()[gid], stable=True).indices
    rank = torch.empty_like(order)
    rank[order] = torch.arange(len(gid), device=dev)
    key = tile_id * max(len(gid), 1) + rank[rep]
    perm = torch.argsort(key)
    return tile_id[perm], gid[rep[perm]]


def _render_chunk(px, py, pix_valid, idx, slot_valid, means2d, conics, colors, opacities,
                  depths, ranges):
    """Dense evaluation of B tiles x K Gaussians x P pixels. Returns per-pixel sums."""
    g_m = means2d[idx]                                   # (B, K, 2)
    g_q = conics[idx]                                    # (B, K, 3)
    g_r = ranges[idx]                                    # (B, K, 4)
    dx = px[:, None, :] - g_m[..., 0:1]                  # (B, K, P)
    dy = py[:, None, :] - g_m[..., 1:2]
    power = -0.5 * (g_q[..., 0:1] * dx * dx + g_q[..., 2:3] * dy * dy) - g_q[..., 1:2] * dx * dy
    alpha = (opacities[idx][..., None] * torch.exp(power.clamp(min=POWER_MIN))).clamp(max=ALPHA_MAX)
    inside = ((px[:, None, :] >= g_r[..., 0:1]) & (px[:, None, :] <= g_r[..., 1:2])
              & (py[:, None, :] >= g_r[..., 2:3]) & (py[:, None, :] <= g_r[..., 3:4]))
    keep = inside & (alpha >= ALPHA_MIN) & slot_valid[..., None] & pix_valid[:, None, :]
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    # early termination: drop the first Gaussian that takes T below T_MIN and all after it
    t_incl = torch.cumprod(1 - alpha, dim=1)
    alpha = torch.where(t_incl >= T_MIN, alpha, torch.zeros_like(alpha))
    t_incl = torch.cumprod(1 - alpha, dim=1)
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], 1)
    w = alpha * t_excl                                   # (B, K, P)
    rgb = torch.einsum("bkp,bkc->bpc", w, colors[idx])
    depth = (w * depths[idx][..., None]).sum(1)
    t_final = t_incl[:, -1]
    vis = ((w > 0) & (t_excl >= VISIBLE_T)).any(-1)      # (B, K)
    return rgb, depth, t_final, vis


def rasterize_reference(means2d, conics, colors, opacities, depths, ranges, width: int,
                        height: int, background: torch.Tensor, tile_size: int = 16,
                        max_elems: int = 1 << 22, checkpoint_above: int = 1 << 25):
    """Rasterize projected Gaussians. Returns (rgb (H,W,3), depth, alpha, visible (N,)).

    ``max_elems`` bounds each chunk (tiles x Gaussians x pixels); when autograd is recording
    and the whole image needs more than ``checkpoint_above`` elements, chunks are
    checkpointed (recomputed in backward) so memory stays bounded.
    """
    dev, dtype = means2d.device, means2d.dtype
    n = means2d.shape[0]
    ts = int(tile_size)
    tiles_x, tiles_y = (width + ts - 1) // ts, (height + ts - 1) // ts
    n_tiles = tiles_x * tiles_y
    P = ts * ts
    rgb = background.to(dtype).expand(n_tiles, P, 3).clone()
    depth = torch.zeros(n_tiles, P, dtype=dtype, device=dev)
    t_final = torch.ones(n_tiles, P, dtype=dtype, device=dev)
    visible = torch.zeros(n, dtype=torch.bool, device=dev)

    tile_id, gid = _tile_pairs(ranges, depths, ts, tiles_x)
    if len(gid):
        counts = torch.bincount(tile_id, minlength=n_tiles)
        starts = torch.cumsum(counts, 0) - counts
        occupied = torch.nonzero(counts).squeeze(1)
        # chunks of tiles with similar list lengths (sorted by count) to limit padding
        occupied = occupied[torch.argsort(counts[occupied], descending=True)]
        loc = torch.arange(P, device=dev)
        lx, ly = (loc % ts).to(dtype), (loc // ts).to(dtype)
        needs_grad = torch.is_grad_enabled() and any(
            t.requires_grad for t in (means2d, conics, colors, opacities, depths))
        use_ckpt = needs_grad and int(counts.sum()) * P > checkpoint_above
        i = 0
        while i < len(occupied):
            k_max = int(counts[occupied[i]])
            b = max(1, max_elems // (k_max * P))
            tiles = occupied[i:i + b]
            i += b
            kk = torch.arange(k_max, device=dev)
            slot_valid = kk[None, :] < counts[tiles][:, None]
            idx = gid[(starts[tiles][:, None] + kk[None, :]).clamp(max=len(gid) - 1)]
            idx = torch.where(slot_valid, idx, torch.zeros_like(idx))
            px = (tiles % tiles_x)[:, None].to(dtype) * ts + lx[None]
            py = (tiles // tiles_x)[:, None].to(dtype) * ts + ly[None]
            pix_valid = (px < width) & (py < height)
            args = (px, py, pix_valid, idx, slot_valid, means2d, conics, colors, opacities,
                    depths, ranges.to(dtype))
            if use_ckpt:
                c_rgb, c_d, c_t, c_vis = checkpoint(_render_chunk, *args, use_reentrant=False)
            else:
                c_rgb, c_d, c_t, c_vis = _render_chunk(*args)
            bg = background.to(dtype)
            rgb = rgb.index_copy(0, tiles, c_rgb + c_t[..., None] * bg)
            depth = depth.index_copy(0, tiles, c_d)
            t_final = t_final.index_copy(0, tiles, c_t)
            visible[idx[c_vis & slot_valid]] = True

    def untile(x):
        x = x.reshape(tiles_y, tiles_x, ts, ts, *x.shape[2:]).transpose(1, 2)
        return x.reshape(tiles_y * ts, tiles_x * ts, *x.shape[4:])[:height, :width]

    return untile(rgb), untile(depth), 1 - untile(t_final), visible
