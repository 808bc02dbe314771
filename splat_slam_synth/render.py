"""Vectorised ray casting of a synthetic scene: ray/box slab intersections, trilinear
mip-mapped textures, Lambertian shading with contact shadows -> RGB + z-depth."""
from __future__ import annotations

import math
from typing import Tuple

import cv2
import numpy as np
import torch

from splat_slam_synth.options import TEX_LEVELS, TEX_SIZE
from splat_slam_synth.scene import Scene
from splat_slam_ros.types import Intrinsics


def _camera_rays(scene: Scene, K: Intrinsics, device=None) -> torch.Tensor:
    """(H, W, 3) camera-frame ray directions with z = 1 through the pixel centres."""
    key = ("rays", K.fx, K.fy, K.cx, K.cy, K.width, K.height, K.distortion_model,
           tuple(K.distortion), str(torch.device(device or "cpu")))
    if key in scene._cache:
        return scene._cache[key]
    v, u = np.mgrid[0:K.height, 0:K.width].astype(np.float64)
    if K.has_distortion:
        pts = np.stack([u, v], -1).reshape(-1, 1, 2)
        D = np.asarray(K.distortion, np.float64)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        if K.distortion_model == "equidistant":
            xy = cv2.fisheye.undistortPoints(pts, K.K, D[:4], criteria=crit)
        else:
            xy = cv2.undistortPoints(pts, K.K, D, criteria=crit)
        xy = xy.reshape(K.height, K.width, 2)
        x, y = xy[..., 0], xy[..., 1]
    else:
        x, y = (u - K.cx) / K.fx, (v - K.cy) / K.fy
    rays = torch.from_numpy(np.stack([x, y, np.ones_like(x)], -1).astype(np.float32))
    rays = rays.to(torch.device(device or "cpu"))
    scene._cache[key] = rays
    return rays


def _sample_trilinear(t, tex, lev, u, v):
    """Trilinear mip-mapped texture lookup: texture ``tex`` (per pixel) at level-0 texel
    coordinates (u, v) (texel centres at +0.5), continuous mip level ``lev``."""
    l0 = lev.floor()
    l1 = (l0 + 1).clamp(max=TEX_LEVELS - 1)
    pts = []
    for l in (l0, l1):
        scale = torch.exp2(-l)
        Sl = TEX_SIZE * scale
        x = torch.remainder(u * scale - 0.5, Sl)
        y = torch.remainder(v * scale - 0.5, Sl)
        o = t["org"][tex * TEX_LEVELS + l.to(torch.int64)]
        pts.append(torch.stack([o[:, 0] + x, o[:, 1] + y], -1))
    atlas = t["atlas"]
    Ha, Wa = atlas.shape[-2:]
    g = torch.stack(pts, 0)                                    # (2, P, 2) atlas pixels
    g = g * torch.tensor([2.0 / (Wa - 1), 2.0 / (Ha - 1)], device=g.device) - 1.0
    c = torch.nn.functional.grid_sample(atlas, g[None], mode="bilinear",
                                        padding_mode="border", align_corners=True)[0]
    w = (lev - l0)[None]
    return (c[:, 0] + (c[:, 1] - c[:, 0]) * w).T                # (P, 3) in 0..255


def render_view(scene: Scene, pose_world: np.ndarray, K: Intrinsics, device=None):
    """Core ray caster. Returns (rgb float32 (H,W,3) in [0,255+], z-depth (H,W)) torch
    tensors on ``device`` (default CPU)."""
    dev = torch.device(device or "cpu")
    t = scene._torch(dev)
    T_rc = scene.T_room_world @ np.asarray(pose_world, np.float64)
    R = torch.from_numpy(T_rc[:3, :3].astype(np.float32)).to(dev)
    o = torch.from_numpy(T_rc[:3, 3].astype(np.float32)).to(dev)
    rays = _camera_rays(scene, K, dev)
    H, W = rays.shape[:2]
    d = rays @ R.T                                       # (H, W, 3) room-frame, camera z = 1
    d = torch.where(d == 0, torch.full_like(d, 1e-12), d)
    inv = 1.0 / d
    # room interior: exit distance, the face is the axis where the ray leaves first
    tmax = torch.maximum((t["room_lo"] - o) * inv, (t["room_hi"] - o) * inv)
    depth, ax = tmax.min(-1)
    sid = 2 * ax + (d.gather(-1, ax[..., None])[..., 0] > 0).long()
    # boxes: slab test, restricted to each box's projected bounding rectangle
    Rn, on = T_rc[:3, :3], T_rc[:3, 3]
    for b in range(scene.n_boxes):
        lo_b, hi_b = scene.boxes_lo[b], scene.boxes_hi[b]
        corners = np.array([[x, y, z] for x in (lo_b[0], hi_b[0]) for y in (lo_b[1], hi_b[1])
                            for z in (lo_b[2], hi_b[2])])
        Xc = (corners - on) @ Rn
        zc = Xc[:, 2]
        if np.all(zc <= 1e-3):
            continue
        if np.any(zc <= 1e-3) or K.has_distortion:
            v0, v1, u0, u1 = 0, H, 0, W
        else:
            u = K.fx * Xc[:, 0] / zc + K.cx
            v = K.fy * Xc[:, 1] / zc + K.cy
            u0, u1 = max(int(math.floor(u.min())) - 1, 0), min(int(math.ceil(u.max())) + 2, W)
            v0, v1 = max(int(math.floor(v.min())) - 1, 0), min(int(math.ceil(v.max())) + 2, H)
            if u0 >= u1 or v0 >= v1:
                continue
        inv_s = inv[v0:v1, u0:u1]
        t1 = (t["boxes_lo"][b] - o) * inv_s
        t2 = (t["boxes_hi"][b] - o) * inv_s
        tn, axb = torch.minimum(t1, t2).max(-1)
        tf = torch.maximum(t1, t2).min(-1).values
        dep = depth[v0:v1, u0:u1]
        hit = (tn <= tf) & (tn > 1e-4) & (tn < dep)
        if not bool(hit.any()):
            continue
        side = (d[v0:v1, u0:u1].gather(-1, axb[..., None])[..., 0] < 0).long()
        depth[v0:v1, u0:u1] = torch.where(hit, tn, dep)
        sid[v0:v1, u0:u1] = torch.where(hit, 6 + 6 * b + 2 * axb + side, sid[v0:v1, u0:u1])
    # ---- shading (flattened)
    dd = d.reshape(-1, 3)
    z = depth.reshape(-1)
    s = sid.reshape(-1)
    X = o + z[:, None] * dd
    tf = t["tabf"][s]                                    # (P, 18) per-surface floats
    ti = t["tabi"][s]                                    # (P, 4) uax, vax, axis, texture
    Xu = X.gather(1, ti[:, 0:1])[:, 0]
    Xv = X.gather(1, ti[:, 1:2])[:, 0]
    dens = tf[:, 2]
    u = Xu * tf[:, 0] * dens + tf[:, 3]
    v = Xv * tf[:, 1] * dens + tf[:, 4]
    # mip level from the pixel footprint on the surface (geometric mean of its axes)
    dn = dd.norm(dim=1)
    cos = (dd.gather(1, ti[:, 2:3])[:, 0].abs() / dn).clamp_min(0.05)
    f = 0.5 * (abs(K.fx) + abs(K.fy))
    foot = z * dn * (1.0 / f) * dens / cos.sqrt()
    lev = torch.log2(foot.clamp_min(1e-6)).clamp(0, TEX_LEVELS - 1)
    albedo = _sample_trilinear(t, ti[:, 3], lev, u, v) * tf[:, 15:18]
    # Lambertian: ambient + directional ("window") + point light near the ceiling
    n = tf[:, 5:8]
    lp = t["light_pos"] - X
    ldist = lp.norm(dim=1).clamp_min(1e-3)
    point = ((n * lp).sum(1) / ldist).clamp_min(0) / (1 + (ldist / 3.0) ** 2)
    direc = (n * t["light_dir"]).sum(1).clamp_min(0)
    # ambient occlusion near face edges (room corners, box bevels)
    edge = torch.minimum(torch.minimum(Xu - tf[:, 10], tf[:, 11] - Xu),
                         torch.minimum(Xv - tf[:, 13], tf[:, 14] - Xv)).clamp_min(0)
    ao = 1 - tf[:, 8] * torch.exp(-edge / tf[:, 9])
    # contact shadows of the boxes standing on the floor (baked map)
    fl = (s == 4).nonzero()[:, 0]
    if scene.n_boxes and len(fl):
        g = t["floor_grid"]
        xy = (X[fl, :2] - g[:2]) * g[2:] - 1.0
        sh = torch.nn.functional.grid_sample(t["floor_shadow"], xy[None, None], mode="bilinear",
                                             padding_mode="border", align_corners=True)[0, 0, 0]
        ao[fl] = ao[fl] * sh
    amb = ((0.4 + 0.25 * direc) * ao)[:, None] * torch.tensor([0.97, 0.99, 1.03], device=dev)
    pnt = (0.6 * point * ao)[:, None] * torch.tensor([1.03, 0.98, 0.9], device=dev)
    rgb = albedo * (amb + pnt)
    return rgb.reshape(H, W, 3), depth


def render_frame(scene: Scene, pose: np.ndarray, intrinsics: Intrinsics,
                 as_float: bool = False, device=None) -> Tuple[np.ndarray, np.ndarray]:
    """Render one clean view. ``pose``: 4x4 camera-to-world in the trajectory's world frame.

    Returns (rgb H x W x 3 uint8 RGB — or float32 in [0, 255] with ``as_float`` —, depth
    H x W float32 z-depth in metres), numpy; ``device`` (torch) does the work."""
    with torch.no_grad():
        rgb, depth = render_view(scene, pose, intrinsics, device)
    rgb = rgb.cpu().numpy()
    if not as_float:
        rgb = np.clip(rgb + 0.5, 0, 255).astype(np.uint8)
    return rgb, depth.cpu().numpy().astype(np.float32)
