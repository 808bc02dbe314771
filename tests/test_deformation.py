"""Map deformation (Eq. 12): hand-computed values and rendering after pose/depth updates."""
import math

import numpy as np
import pytest
import torch

from splat_slam_ros.mapping.deformation import deform_gaussians
from splat_slam_ros.geometry import quat_to_matrix
from splat_slam_ros.mapping.mapper import Mapper
from test_mapper import K, pose_at, psnr, render_view, scene_gaussians, small_cfg


def test_equation_on_a_hand_computed_case():
    # intrinsics fx = fy = 100, cx = 32, cy = 24, image 64 x 48
    intr = (100.0, 100.0, 32.0, 24.0)
    old_pose = np.eye(4)
    old_pose[2, 3] = -1.0                     # camera at z = -1 looking along +z
    new_pose = np.eye(4)                      # rotated 90 deg about z, moved to x = 1
    new_pose[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    new_pose[0, 3] = 1.0
    D = np.zeros((48, 64), np.float32)
    D1 = np.zeros((48, 64), np.float32)
    D[29, 42], D1[29, 42] = 2.0, 2.5          # depth grows by 0.5 at pixel (u=42, v=29)
    D[24, 32] = 1.0                           # new depth missing at (32, 24)
    means = torch.tensor([[0.2, 0.1, 1.0],    # camera (0.2, 0.1, 2.0) -> pixel (42, 29)
                          [0.0, 0.0, 0.0],    # camera (0, 0, 1) -> pixel (32, 24): D' missing
                          [-5.0, 0.0, 0.0]])  # camera (-5, 0, 1) -> u = -468: outside
    quats = torch.tensor([[0.0, 0, 0, 1]] * 3)
    log_s = torch.log(torch.tensor([[0.1, 0.2, 0.3]] * 3))
    d = deform_gaussians(means, quats, log_s, old_pose, new_pose, intr, D, D1)
    # Gaussian 0: factor 1 + 0.5 / 2 = 1.25; camera point -> (0.25, 0.125, 2.5);
    # world: R' x + t' = (-0.125 + 1, 0.25, 2.5)
    assert d.nonrigid.tolist() == [True, False, False]
    assert d.factor[0].item() == pytest.approx(1.25)
    np.testing.assert_allclose(d.means[0].numpy(), [0.875, 0.25, 2.5], atol=1e-6)
    np.testing.assert_allclose(d.log_scales[0].exp().numpy(), [0.125, 0.25, 0.375], rtol=1e-6)
    # Gaussian 1 (missing new depth): rigid, camera (0, 0, 1) -> world (1, 0, 1)
    np.testing.assert_allclose(d.means[1].numpy(), [1.0, 0.0, 1.0], atol=1e-6)
    # Gaussian 2 (outside the image): rigid, camera (-5, 0, 1) -> world (1, -5, 1)
    np.testing.assert_allclose(d.means[2].numpy(), [1.0, -5.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(d.log_scales[1:].exp().numpy(), [[0.1, 0.2, 0.3]] * 2, rtol=1e-6)
    # R_i' = R' R^-1 R_i: identity -> 90 deg about z = (0, 0, sin 45, cos 45)
    h = math.sqrt(0.5)
    np.testing.assert_allclose(d.quats.numpy(), [[0, 0, h, h]] * 3, atol=1e-6)


def test_rotation_composes_with_existing_rotation():
    intr = (100.0, 100.0, 32.0, 24.0)
    old_pose = np.eye(4)
    new_pose = np.eye(4)
    new_pose[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]     # 90 deg about x
    q_i = torch.tensor([[0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)]])   # 90 deg about z
    d = deform_gaussians(torch.tensor([[0.0, 0.0, 2.0]]), q_i, torch.zeros(1, 3), old_pose,
                         new_pose, intr)
    # R_x(90) R_z(90) as a quaternion: q_x * q_z with q_x = (h, 0, 0, h), q_z = (0, 0, h, h)
    # (Hamilton product, x y z w) = (h*h, -h*h, h*h, h*h) = (0.5, -0.5, 0.5, 0.5)
    np.testing.assert_allclose(d.quats[0].numpy(), [0.5, -0.5, 0.5, 0.5], atol=1e-6)
    Rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(quat_to_matrix(d.quats[0].double()).numpy(),
                               new_pose[:3, :3] @ Rz, atol=1e-6)
    np.testing.assert_allclose(d.means[0].numpy(), [0.0, -2.0, 0.0], atol=1e-6)


@pytest.fixture(scope="module")
def mapped():
    scene = scene_gaussians()
    pose = pose_at(0.1, 0.0, 0.0, 0.05)
    img, depth = render_view(scene, pose)
    mp = Mapper(small_cfg(iters_first=60, downsample_first=2), K)
    mp.add_keyframe(0, img, pose, depth)
    return mp, img, depth, pose


def test_rigid_pose_change_with_and_without_deformation(mapped):
    mp, img, depth, pose = mapped
    state = mp.map.tensors()
    try:
        p_before = psnr(mp.render(pose)[0], img)
        assert p_before > 18
        # global BA / loop closure moves the keyframe (and the world with it) rigidly
        delta = pose_at(0.3, -0.1, 0.2, 0.25)
        new_pose = delta @ pose
        p_not_deformed = psnr(mp.render(new_pose)[0], img)
        moved = mp.apply_update(0, new_pose)
        assert moved == len(mp.map) and mp.stats()["deformations"] == 1
        np.testing.assert_allclose(mp.keyframes[0].pose, new_pose)
        p_after = psnr(mp.render(new_pose)[0], img)
        assert p_after >= p_before - 0.5, (p_before, p_after)
        assert p_not_deformed < p_before - 5, (p_before, p_not_deformed)
    finally:
        mp.map.set_rows(torch.arange(len(mp.map)), means=state["means"], quats=state["quats"],
                        log_scales=state["log_scales"])
        mp.keyframes[0].pose = pose


def test_depth_update_moves_along_rays(mapped):
    """Scale correction D' = 1.2 D at the same pose: the image stays, the depth scales."""
    mp, img, depth, pose = mapped
    state = mp.map.tensors()
    kf = mp.keyframes[0]
    old_depth, old_valid = kf.depth.clone(), kf.valid.clone()
    try:
        rgb0, d0 = mp.render(pose)
        mp.apply_update(0, pose, depth * 1.2, depth > 0)
        rgb1, d1 = mp.render(pose)
        # Gaussians move along their viewing rays and scale with the depth, so the image is
        # unchanged (up to Gaussians outside the view, kept rigid, at the border)
        assert psnr(rgb1[4:-4, 4:-4], rgb0[4:-4, 4:-4]) > 35
        m = (d0 > 0.5) & (d1 > 0.5)
        assert np.median(d1[m] / d0[m]) == pytest.approx(1.2, abs=0.02)
        assert torch.allclose(kf.depth, old_depth * 1.2)
        # another keyframe's Gaussians are untouched
        assert mp.apply_update(99, np.eye(4)) == 0
    finally:
        mp.map.set_rows(torch.arange(len(mp.map)), means=state["means"], quats=state["quats"],
                        log_scales=state["log_scales"])
        kf.pose, kf.depth, kf.valid = pose, old_depth, old_valid


def test_only_the_updated_keyframe_moves():
    scene = scene_gaussians()
    mp = Mapper(small_cfg(iters_first=5, iters_per_keyframe=2, densify_every=0,
                          prune_every=0), K)
    for i, p in enumerate([pose_at(), pose_at(0.8, 0, 0.3)]):
        img, d = render_view(scene, p)
        mp.add_keyframe(i, img, p, d, force=True)
    before = mp.map.tensors()
    new_pose = pose_at(0.8, 0.5, 0.3)
    n = mp.apply_update(1, new_pose)
    after = mp.map.tensors()
    sel = before["kf_id"] == 1
    assert n == int(sel.sum()) > 0
    assert torch.equal(after["means"][~sel], before["means"][~sel])
    shift = after["means"][sel] - before["means"][sel]
    assert torch.allclose(shift, torch.tensor([0.0, 0.5, 0.0]).expand_as(shift), atol=1e-5)
