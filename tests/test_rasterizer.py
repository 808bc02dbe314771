"""Rasterizer: C++ kernels == pure-torch reference (values and gradients), semantics, build.

Error metric: norm-based relative error ``||a - b|| / ||b||`` over a whole tensor (image or
gradient), with ``b`` the float64 pure-torch reference (torch projection + reference
compositing) and ``a`` the C++ backend (the C++ projection in the inputs' float64, then the
float32 compositing kernel). Per-element relative errors are meaningless where values are
near zero; the norm metric bounds the overall float32 round-off (measured ~1e-6) and still
catches any systematic mistake (a wrong term moves it to >1e-2).
"""
from __future__ import annotations

import os
import platform
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from splat_slam_ros.mapping.rasterizer import (RasterizerInputError, RasterOutput, rasterize,
                                               visible_gaussians)
from splat_slam_ros import native
from splat_slam_ros.mapping.rasterizer import kernel as rkernel
from splat_slam_ros.mapping.rasterizer.projection import project_gaussians

W, H = 61, 45  # not multiples of the tile size: partial edge tiles
TOL = 1e-4
REPO = Path(__file__).resolve().parents[1]


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach().double(), b.detach().double()
    return float((a - b).norm() / b.norm().clamp_min(1e-30))


@pytest.fixture(scope="module")
def ext():
    return rkernel.load_extension()     # the C++ kernel must build (ninja + a C++ compiler)


def camera(width=W, height=H):
    fx, fy = 0.9 * width, 0.85 * width
    cx, cy = width / 2 - 0.3, height / 2 + 0.2
    # a generic world-to-camera transform (rotation + translation), not the identity
    from splat_slam_ros.geometry import se3_exp
    T_cw = se3_exp(torch.tensor([0.1, -0.05, 0.2, 0.05, -0.08, 0.03], dtype=torch.float64))
    return T_cw, (fx, fy, cx, cy)


def make_scene(n=200, seed=0, edge_cases=True, width=W, height=H):
    """Random Gaussians in front of the camera + the edge cases of the task."""
    g = torch.Generator().manual_seed(seed)
    T_cw, (fx, fy, cx, cy) = camera(width, height)
    T_wc = torch.linalg.inv(T_cw)
    d = torch.float64
    z = 1 + 4 * torch.rand(n, generator=g, dtype=d)
    u = torch.rand(n, generator=g, dtype=d) * width * 1.2 - 0.1 * width
    v = torch.rand(n, generator=g, dtype=d) * height * 1.2 - 0.1 * height
    pc = torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1)
    quats = torch.randn(n, 4, generator=g, dtype=d)
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=d) * 0.5 - 3.0)
    opac = 0.05 + 0.9 * torch.rand(n, generator=g, dtype=d)
    cols = torch.rand(n, 3, generator=g, dtype=d)
    if edge_cases:
        k = 0
        pc[k] = torch.tensor([0.1, 0.0, -2.0], dtype=d); k += 1            # behind the camera
        pc[k] = torch.tensor([0.0, 0.1, 0.005], dtype=d); k += 1           # closer than near
        pc[k] = torch.tensor([-50.0, 0.0, 2.0], dtype=d); k += 1           # far off-screen
        pc[k] = torch.tensor([0.0, 20.0, 3.0], dtype=d); k += 1            # off-screen (below)
        pc[k] = torch.tensor([0.05, -0.02, 6.0], dtype=d)                  # huge, behind most
        scales[k] = torch.tensor([4.0, 3.0, 0.5], dtype=d); opac[k] = 0.9; k += 1
        pc[k] = torch.tensor([0.0, 0.0, 1.5], dtype=d)                     # huge, in front
        scales[k] = torch.tensor([2.0, 1.5, 0.3], dtype=d); opac[k] = 0.3; k += 1
        for _ in range(10):                                                # tiny (sub-pixel)
            scales[k] = 1e-4; k += 1
        for _ in range(5):                                                 # zero opacity
            opac[k] = 0.0; k += 1
        # coincident depths: groups sharing exactly the same camera z, overlapping in image
        base = pc[k].clone()
        for j in range(6):
            pc[k] = base + torch.tensor([0.01 * j, 0.005 * j, 0.0], dtype=d)
            scales[k] = 0.05; opac[k] = 0.6; k += 1
    means = pc @ T_wc[:3, :3].T + T_wc[:3, 3]
    return means, quats, scales, opac, cols, T_cw, (fx, fy, cx, cy)


def render(scene, backend, requires_grad=False, background=(0.1, 0.2, 0.3), tile_size=16,
           width=W, height=H):
    means, quats, scales, opac, cols, viewmat, intr = scene
    params = [t.detach().clone().requires_grad_(requires_grad)
              for t in (means, quats, scales, opac, cols)]
    bg = torch.tensor(background, dtype=torch.float64)
    out = rasterize(*params, viewmat, intr, width, height, backend=backend, background=bg,
                    tile_size=tile_size)
    return out, params


def upstream(seed=1, width=W, height=H):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(height, width, 3, generator=g, dtype=torch.float64),
            torch.randn(height, width, generator=g, dtype=torch.float64),
            torch.randn(height, width, generator=g, dtype=torch.float64))


def grads_of(scene, backend, seed=1, **kw):
    out, params = render(scene, backend, requires_grad=True, **kw)
    gr, gd, ga = upstream(seed)
    ((out.rgb * gr).sum() + (out.depth * gd).sum() + (out.alpha * ga).sum()).backward()
    return out, [p.grad for p in params]


# ---------------------------------------------------------------- forward / backward
@pytest.mark.parametrize("seed", [0, 1])
def test_forward_matches_reference(ext, seed):
    scene = make_scene(seed=seed)
    a, _ = render(scene, "cpp")
    b, _ = render(scene, "torch")
    assert isinstance(a, RasterOutput)
    assert a.rgb.shape == (H, W, 3) and a.depth.shape == (H, W) and a.alpha.shape == (H, W)
    assert rel(a.rgb, b.rgb) < TOL
    assert rel(a.depth, b.depth) < TOL
    assert rel(a.alpha, b.alpha) < TOL
    assert torch.equal(a.visible, b.visible)
    assert torch.equal(a.radii, b.radii)
    # the scene is not trivial: many Gaussians seen, image mostly covered, depth in range
    assert 50 < int(a.visible.sum()) < 200
    assert float(a.alpha.mean()) > 0.5
    # edge cases: behind / too close / off-screen are culled (radius 0, invisible)
    assert a.radii[:4].tolist() == [0, 0, 0, 0]
    assert not a.visible[:4].any()
    assert (a.radii[4:6] > W).all()                         # huge ones cover the image
    assert not a.visible[16:21].any()                       # zero opacity never composited


@pytest.mark.parametrize("seed", [0, 1])
def test_gradients_match_reference(ext, seed):
    scene = make_scene(seed=seed)
    _, ga = grads_of(scene, "cpp", seed=seed + 10)
    _, gb = grads_of(scene, "torch", seed=seed + 10)
    for name, x, y in zip(("means", "quats", "scales", "opacities", "colors"), ga, gb):
        assert y.norm() > 0, name
        assert rel(x, y) < TOL, (name, rel(x, y))
    # culled Gaussians get exactly zero gradient
    for x in ga:
        assert x[:4].abs().max() == 0


def test_gradients_each_output_separately(ext):
    """rgb-only, depth-only and alpha-only losses (each backward term on its own)."""
    scene = make_scene(seed=3)
    for which in range(3):
        res = []
        for backend in ("cpp", "torch"):
            out, params = render(scene, backend, requires_grad=True)
            y = (out.rgb, out.depth, out.alpha)[which]
            (y * upstream(which)[which]).sum().backward()
            res.append([torch.zeros_like(p) if p.grad is None else p.grad for p in params])
        for x, y in zip(*res):
            if y.abs().max() == 0:   # e.g. colours do not affect alpha
                assert x.abs().max() == 0
            else:
                assert rel(x, y) < TOL


def test_background_gradient(ext):
    scene = make_scene(seed=9)
    means, quats, scales, opac, cols, viewmat, intr = scene
    res = []
    for backend in ("cpp", "torch"):
        bg = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64, requires_grad=True)
        out = rasterize(means, quats, scales, opac, cols, viewmat, intr, W, H, backend=backend,
                        background=bg)
        (out.rgb * upstream(2)[0]).sum().backward()
        res.append(bg.grad)
    assert res[1].abs().max() > 0 and rel(res[0], res[1]) < TOL


def test_reference_gradcheck():
    """The reference (and the projection) against finite differences, tiny scene."""
    scene = make_scene(n=5, seed=4, edge_cases=False, width=12, height=10)
    means, quats, scales, opac, cols, viewmat, intr = scene
    scales = scales * 6  # a few pixels wide on a 12x10 image
    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opac, cols))
    bg = torch.tensor([0.2, 0.1, 0.4], dtype=torch.float64)
    w_rgb, w_d, w_a = (torch.randn(10, 12, 3, dtype=torch.float64),
                       torch.randn(10, 12, dtype=torch.float64),
                       torch.randn(10, 12, dtype=torch.float64))

    def f(m, q, s, o, c):
        out = rasterize(m, q, s, o, c, viewmat, intr, 12, 10, backend="torch", background=bg,
                        tile_size=8)
        return (out.rgb * w_rgb).sum() + (out.depth * w_d).sum() + (out.alpha * w_a).sum()

    assert float(f(*inputs).detach()) != 0
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_tile_size_does_not_change_the_result(ext):
    scene = make_scene(seed=5)
    outs = [render(scene, "cpp", tile_size=ts)[0] for ts in (8, 16, 32)]
    for o in outs[1:]:
        assert torch.allclose(o.rgb, outs[0].rgb, atol=1e-6)
        assert torch.equal(o.visible, outs[0].visible)
    ref = render(scene, "torch", tile_size=32)[0]
    assert rel(outs[0].rgb, ref.rgb) < TOL


def test_backward_is_deterministic(ext):
    scene = make_scene(seed=6)
    torch.manual_seed(0)
    _, g1 = grads_of(scene, "cpp")
    _, g2 = grads_of(scene, "cpp")
    for x, y in zip(g1, g2):
        assert torch.equal(x, y)


# ---------------------------------------------------------------- projection
def _project_both(scene, dtype, low_pass=0.3, seed=5):
    """C++ and torch projections of ``scene`` in ``dtype`` (``low_pass`` px^2 on the 2D
    covariances), and the gradients w.r.t. means, quats and scales of a random linear
    function of (means2d, conics, depths)."""
    means, quats, scales, _o, _c, viewmat, (fx, fy, cx, cy) = scene
    quats = quats.clone()
    quats[6] *= 1e-10                       # norm below the normalisation's epsilon
    g = torch.Generator().manual_seed(seed)
    n = means.shape[0]
    up = [torch.randn(n, k, generator=g, dtype=dtype) for k in (2, 3)] + \
        [torch.randn(n, generator=g, dtype=dtype)]
    res = []
    for proj in ("cpp", "torch"):
        p = [t.detach().to(dtype).clone().requires_grad_(True) for t in (means, quats, scales)]
        vm = viewmat.to(dtype)
        if proj == "cpp":
            m2d, con, dep, rng, rad, val = rkernel.ProjectCpp.apply(
                *p, vm.contiguous(), fx, fy, cx, cy, W, H, 0.01, low_pass)
        else:
            o = project_gaussians(*p, vm, fx, fy, cx, cy, W, H, 0.01, low_pass)
            m2d, con, dep, rng, rad, val = (o.means2d, o.conics, o.depths, o.ranges, o.radii,
                                            o.valid)
        ((m2d * up[0]).sum() + (con * up[1]).sum() + (dep * up[2]).sum()).backward()
        res.append(((m2d, con, dep, rng, rad, val), [t.grad for t in p]))
    return res


@pytest.mark.parametrize("dtype,low_pass", [(torch.float64, 0.3), (torch.float32, 0.3),
                                            (torch.float64, 0.075)])
def test_cpp_projection_matches_torch(ext, dtype, low_pass):
    """The C++ projection (forward and hand-written backward) against projection.py: culled
    (behind, too close, off-screen), FOV-clamped, huge, tiny, near-zero quaternions; the
    default low-pass filter and a lattice render's."""
    scene = make_scene(seed=4)
    (fa, ga), (fb, gb) = _project_both(scene, dtype, low_pass)
    tol = 1e-10 if dtype == torch.float64 else 2e-5
    for name, x, y in zip(("means2d", "conics", "depths"), fa[:3], fb[:3]):
        assert x.dtype == dtype and rel(x, y) < tol, (name, rel(x, y))
    assert fa[3].dtype == torch.int32 and fa[4].dtype == torch.int32 and fa[5].dtype == torch.bool
    if dtype == torch.float64:
        for x, y in zip(fa[3:], fb[3:]):
            assert torch.equal(x, y)
    else:     # float32 round-off may move a footprint edge by a pixel, never the culling
        assert torch.equal(fa[5], fb[5])
        assert (fa[3] - fb[3]).abs().max() <= 1 and (fa[4] - fb[4]).abs().max() <= 1
    assert fa[5][:4].tolist() == [False] * 4 and int(fa[5].sum()) > 100
    gtol = 1e-9 if dtype == torch.float64 else 1e-4
    for name, x, y in zip(("means", "quats", "scales"), ga, gb):
        assert y.norm() > 0 and torch.isfinite(x).all(), name
        assert rel(x, y) < gtol, (name, rel(x, y))


def test_projection_binding_refuses_mismatched_gradients(ext):
    means, quats, scales, _o, _c, viewmat, (fx, fy, cx, cy) = make_scene(n=30, edge_cases=False)
    n = means.shape[0]
    args = (means, quats.contiguous(), scales, viewmat.contiguous(), fx, fy, cx, cy, W, H, 0.01,
            0.3)
    zeros = lambda *s: torch.zeros(*s, dtype=torch.float64)  # noqa: E731
    d = ext.project_backward(*args, zeros(n, 2), zeros(n, 3), zeros(n))
    assert [tuple(t.shape) for t in d] == [(n, 3), (n, 4), (n, 3)]
    assert all(t.abs().max() == 0 for t in d)          # zero upstream: exact zeros
    with pytest.raises(RuntimeError, match="projection gradients"):
        ext.project_backward(*args, zeros(n, 2), zeros(n, 2), zeros(n))


def test_viewmat_gradient_goes_through_the_torch_projection(ext):
    """The C++ projection gives no viewmat gradient: a viewmat that needs one is projected by
    projection.py, so the cpp backend still returns the reference's gradient."""
    means, quats, scales, opac, cols, viewmat, intr = make_scene(seed=2)
    grads = []
    for backend in ("cpp", "torch"):
        vm = viewmat.clone().requires_grad_(True)
        out = rasterize(means, quats, scales, opac, cols, vm, intr, W, H, backend=backend)
        (out.rgb.sum() + out.depth.sum()).backward()
        grads.append(vm.grad)
    assert grads[1].norm() > 0 and rel(grads[0], grads[1]) < TOL


def test_float32_inputs_and_auto_backend(ext):
    scene = make_scene(seed=7)
    s32 = tuple(t.float() if torch.is_tensor(t) else t for t in scene)
    a, params = render(s32, "auto", requires_grad=True)
    assert a.rgb.dtype == torch.float32
    a.rgb.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in params)
    b, _ = render(scene, "torch")
    assert rel(a.rgb, b.rgb) < 1e-4


def test_empty_and_fully_culled_scenes(ext):
    bg = (0.3, 0.5, 0.7)
    for n in (0, 3):
        means = torch.zeros(n, 3, dtype=torch.float64)
        means[:, 2] = -1.0  # all behind the camera
        scene = (means, torch.tensor([[0, 0, 0, 1.0]] * n, dtype=torch.float64).reshape(n, 4),
                 torch.full((n, 3), 0.1, dtype=torch.float64), torch.full((n,), 0.5, dtype=torch.float64),
                 torch.rand(n, 3, dtype=torch.float64), torch.eye(4, dtype=torch.float64),
                 (50.0, 50.0, 32.0, 24.0))
        for backend in ("cpp", "torch"):
            out, _ = render(scene, backend, background=bg)
            assert torch.allclose(out.rgb, torch.tensor(bg, dtype=out.rgb.dtype).expand(H, W, 3))
            assert out.alpha.abs().max() == 0 and out.depth.abs().max() == 0
            assert out.visible.shape == (n,) and not out.visible.any()


# ---------------------------------------------------------------- semantics
def _two_gaussians(front_opacity):
    d = torch.float64
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]], dtype=d)
    quats = torch.tensor([[0, 0, 0, 1.0], [0, 0, 0, 1.0]], dtype=d)
    scales = torch.tensor([[0.5, 0.5, 0.05], [0.05, 0.05, 0.05]], dtype=d)  # big front, small back
    opac = torch.tensor([front_opacity, 0.9], dtype=d)
    cols = torch.tensor([[1.0, 0, 0], [0, 1.0, 0]], dtype=d)
    return means, quats, scales, opac, cols, torch.eye(4, dtype=d), (40.0, 40.0, 31.5, 23.5)


@pytest.mark.parametrize("backend", ["cpp", "torch"])
def test_visibility_follows_transmittance(ext, backend):
    # an opaque Gaussian in front hides the small one completely: T < 0.5 behind it
    out, _ = render(_two_gaussians(0.99), backend)
    assert out.visible.tolist() == [True, False]
    assert (out.radii > 0).all()  # both are still in the frustum and rasterized
    # a faint Gaussian in front (T stays >= 0.5): both visible
    out, _ = render(_two_gaussians(0.3), backend)
    assert out.visible.tolist() == [True, True]
    # depth is the alpha-blended centre depth: between 2 and 3 at the image centre
    c = out.depth[24, 32] / out.alpha[24, 32]
    assert 2.0 < float(c) < 3.0


@pytest.mark.parametrize("tile_size", [8, 16, 32])
@pytest.mark.parametrize("seed,n", [(0, 200), (3, 2000)])
def test_visible_sets_without_the_render_are_the_renders(ext, seed, n, tile_size):
    # visible_gaussians stops each pixel once T < 0.5 instead of compositing it to the end:
    # the same flags as the render's, bit for bit; 2000 Gaussians in a 61x45 view hide most
    # of each other, so a pass that flagged whatever it reached would differ
    scene = make_scene(n=n, seed=seed)
    means, quats, scales, opac, cols, viewmat, intr = scene
    out, _ = render(scene, "cpp", tile_size=tile_size)
    vis = visible_gaussians(means, quats, scales, opac, viewmat, intr, W, H, backend="cpp",
                            tile_size=tile_size)
    assert vis.dtype == torch.bool and vis.shape == (n,)
    assert torch.equal(vis, out.visible)
    in_view = int((out.radii > 0).sum())
    assert 0 < int(vis.sum()) < (in_view if n < 1000 else in_view // 2)
    ref, _ = render(scene, "torch", tile_size=tile_size)         # other backends: the render's
    assert torch.equal(visible_gaussians(means, quats, scales, opac, viewmat, intr, W, H,
                                         backend="torch", tile_size=tile_size), ref.visible)


def test_visible_sets_of_the_two_gaussian_scene(ext):
    for opacity, expected in ((0.99, [True, False]), (0.3, [True, True])):
        means, quats, scales, opac, _, viewmat, intr = _two_gaussians(opacity)
        assert visible_gaussians(means, quats, scales, opac, viewmat, intr, W, H,
                                 backend="cpp").tolist() == expected


def test_input_errors():
    scene = make_scene(n=10, edge_cases=False)
    means, quats, scales, opac, cols, viewmat, intr = scene
    with pytest.raises(RasterizerInputError, match="quats"):
        rasterize(means, quats[:, :3], scales, opac, cols, viewmat, intr, W, H)
    with pytest.raises(RasterizerInputError, match="backend"):
        rasterize(means, quats, scales, opac, cols, viewmat, intr, W, H, backend="opengl")
    with pytest.raises(RasterizerInputError, match="tile_size"):
        rasterize(means, quats, scales, opac, cols, viewmat, intr, W, H, tile_size=12)


# ---------------------------------------------------------------- build and cache
def _run_py(code: str, env_extra: dict, timeout=300):
    env = dict(os.environ, **env_extra)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_kernel_cache_second_load_is_fast(ext):
    d = native.cache_dir()
    so = next(d.glob("*.so"))
    mtime = so.stat().st_mtime_ns
    code = """
        import time
        from splat_slam_ros.mapping.rasterizer import kernel
        t = time.perf_counter(); kernel.load_extension(); print(time.perf_counter() - t)
    """
    r = _run_py(code, {})
    assert r.returncode == 0, r.stderr
    assert float(r.stdout.strip().splitlines()[-1]) < 2.0   # an import, not a build (~1 min)
    assert so.stat().st_mtime_ns == mtime                   # nothing rebuilt


def test_build_failure_is_a_clear_error(tmp_path):
    code = """
        import warnings, torch
        from splat_slam_ros.mapping.rasterizer import kernel, rasterize, RasterizerBuildError
        try:
            kernel.load_extension()
        except RasterizerBuildError as e:
            print("ERR", e)
        try:
            rasterize(torch.zeros(1, 3), torch.tensor([[0, 0, 0, 1.0]]), torch.ones(1, 3),
                      torch.ones(1), torch.ones(1, 3), torch.eye(4), (10, 10, 5, 5), 8, 8,
                      backend="cpp")
        except RasterizerBuildError as e:
            print("CPP", e)
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            for _ in range(2):
                out = rasterize(torch.zeros(1, 3), torch.tensor([[0, 0, 0, 1.0]]), torch.ones(1, 3),
                                torch.ones(1), torch.ones(1, 3), torch.eye(4), (10, 10, 5, 5), 8, 8)
            print("WARN", len(w), str(w[0].message) if w else "")
        print("SHAPE", tuple(out.rgb.shape))
    """
    r = _run_py(code, {"CXX": "/nonexistent/g++", "SPLAT_SLAM_EXT_DIR": str(tmp_path)})
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "ERR no C++ compiler found" in out and "apt-get install g++" in out
    assert "CPP no C++ compiler found" in out
    assert "WARN 1" in out and "falling back" in out      # warned once, then the torch path
    assert "SHAPE (8, 8, 3)" in out


def test_compile_error_is_reported(tmp_path):
    code = """
        from splat_slam_ros.mapping.rasterizer import kernel
        try:
            kernel.load_extension()
        except kernel.RasterizerBuildError as e:
            print("ERR", e)
    """
    r = _run_py(code, {"SPLAT_SLAM_CXXFLAGS": "-fno-such-flag", "SPLAT_SLAM_EXT_DIR": str(tmp_path)})
    assert r.returncode == 0, r.stderr
    assert "ERR building the C++ kernels failed" in r.stdout
    assert "-fno-such-flag" in r.stdout          # the compiler's own diagnostic is shown


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64") or
                    not torch.backends.cpu.get_cpu_capability().startswith("AVX"),
                    reason="the default build here already is the non-AVX one")
def test_kernel_built_without_avx_matches_reference(tmp_path):
    """The kernels' 4-lane path (SSE or NEON registers: what a CPU without AVX builds), built
    here with AVX turned off: renders, gradients, visible sets and the fused view loss against
    the torch reference, as the default build is tested above."""
    code = """
        import sys, torch
        sys.path.insert(0, "tests")
        from test_rasterizer import grads_of, make_scene, rel, render
        from splat_slam_ros.mapping.rasterizer import kernel
        kernel.load_extension()
        for seed in (0, 1):
            scene = make_scene(seed=seed)
            (a, ga), (b, gb) = grads_of(scene, "cpp", seed=seed), grads_of(scene, "torch", seed=seed)
            print("FWD", max(rel(a.rgb, b.rgb), rel(a.depth, b.depth), rel(a.alpha, b.alpha)),
                  bool(torch.equal(a.visible, b.visible)))
            print("BWD", max(rel(x, y) for x, y in zip(ga, gb)))
        for ts in (8, 32):
            o = render(make_scene(seed=5), "cpp", tile_size=ts)[0]
            print("TILE", rel(o.rgb, render(make_scene(seed=5), "torch")[0].rgb))
        from test_rasterizer import test_visible_sets_without_the_render_are_the_renders as vt
        vt(None, 3, 2000, 16)                                  # asserts inside
        print("VISIBLE ok")
        from test_rasterizer import test_fused_view_loss_matches_the_torch_loss as loss_test
        for vignetting, weights, n in ((True, "mask", 1), (False, "float", 2)):
            loss_test(None, vignetting, weights, n)      # asserts inside
            print("LOSS ok")
    """
    r = _run_py(code, {"SPLAT_SLAM_CXXFLAGS": "-mno-avx -mno-avx2 -mno-fma",
                       "SPLAT_SLAM_EXT_DIR": str(tmp_path)})
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.split("\n")
    fwd = [ln.split() for ln in lines if ln.startswith("FWD")]
    bwd = [float(ln.split()[1]) for ln in lines if ln.startswith("BWD")]
    tile = [float(ln.split()[1]) for ln in lines if ln.startswith("TILE")]
    assert len(fwd) == 2 and len(bwd) == 2 and len(tile) == 2, r.stdout
    assert all(float(f[1]) < TOL and f[2] == "True" for f in fwd), fwd
    assert max(bwd) < TOL and max(tile) < TOL, (bwd, tile)
    assert r.stdout.count("LOSS ok") == 2 and "VISIBLE ok" in r.stdout, r.stdout
    assert "-mno-avx" in next(tmp_path.glob("*/build.ninja")).read_text()


# ---------------------------------------------------------------- gsplat (CUDA only)
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gsplat_backend_matches_reference():
    gsplat = pytest.importorskip("gsplat")  # noqa: F841
    scene = make_scene(seed=8, edge_cases=False)
    cuda = tuple(t.float().cuda() if torch.is_tensor(t) else t for t in scene)
    a, _ = render(cuda, "gsplat")
    b, _ = render(cuda, "torch")
    assert rel(a.rgb.cpu(), b.rgb.cpu()) < 1e-2
    assert rel(a.depth.cpu(), b.depth.cpu()) < 1e-2


# ------------------------------------------------------------------ view loss
@pytest.mark.parametrize("vignetting", [True, False])
@pytest.mark.parametrize("weights", ["mask", "float"])
@pytest.mark.parametrize("n", [1, 2])
def test_fused_view_loss_matches_the_torch_loss(ext, vignetting, weights, n):
    """``optimise.fused_view_loss`` (C++, one pass each way) == ``optimise.view_loss`` (torch):
    value and gradients w.r.t. the render, the exposure and the vignetting; full views and
    lattice (strided) targets, bool masks and float weights, with and without vignetting."""
    import numpy as np
    from types import SimpleNamespace

    from splat_slam_ros.config import MappingConfig
    from splat_slam_ros.mapping.camera_model import CameraModel
    from splat_slam_ros.mapping.keyframe_inputs import MappedKeyframe, lattice_view
    from splat_slam_ros.mapping.optimise import fused_view_loss, lattice, view_loss

    g = torch.Generator().manual_seed(3 + n)
    cam = CameraModel(MappingConfig(vignetting=vignetting), "cpu")
    with torch.no_grad():                  # a falloff that is clamped at the far corners
        cam.vignette += torch.tensor([-0.6, -1.2]) if vignetting else 0.0
    depth = torch.rand(H, W, generator=g) + 0.5
    valid = torch.rand(H, W, generator=g) > 0.3
    kf = MappedKeyframe(
        kf_id=4, index=1, timestamp=0.0, pose=np.eye(4),
        image=torch.randint(0, 256, (H, W, 3), generator=g, dtype=torch.uint8),
        depth=torch.where(valid, depth, torch.zeros(())), valid=valid,
        exposure=torch.tensor([0.2, -0.05], requires_grad=True),
        weight=(torch.rand(H, W, generator=g) * valid) if weights == "float" else None)
    intr = (0.9 * W, 0.85 * W, W / 2 - 0.3, H / 2 + 0.2)
    h, w = H, W
    if n > 1:
        intr, w, h = lattice(intr, W, H, n, 1, 0)
        kf = lattice_view(kf, n, 1, 0)
    results = []
    for fused in (False, True):
        rgb = torch.rand(h, w, 3, generator=torch.Generator().manual_seed(9)).requires_grad_()
        d = (torch.rand(h, w, generator=torch.Generator().manual_seed(8)) + 0.5).requires_grad_()
        out = SimpleNamespace(rgb=rgb, depth=d)
        kf.exposure.grad = None
        cam.vignette.grad = None
        loss = (fused_view_loss(kf, out, cam, intr, 0.9) if fused else
                view_loss(kf, out, lambda c, k: cam.expose(c, k, intr), 0.9))
        (3.0 * loss).backward()
        results.append((loss.detach(), rgb.grad, d.grad, kf.exposure.grad,
                        cam.vignette.grad if vignetting else torch.zeros(2)))
    names = ("loss", "d rgb", "d depth", "d exposure", "d vignetting")
    for name, a, b in zip(names, results[1], results[0]):
        assert a.shape == b.shape, name
        assert rel(a, b) < 1e-5, (name, rel(a, b))
    assert results[1][2].abs().sum() > 0 and results[1][3].abs().min() > 0
    if vignetting:
        assert results[1][4].abs().min() > 0
