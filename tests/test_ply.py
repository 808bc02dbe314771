import numpy as np
import pytest
import torch

from splat_slam_ros.mapping.ply_io import SH_C0, PlyError, load_gaussians_ply, save_gaussians_ply


def random_gaussians(n=257, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return dict(means=rng.normal(size=(n, 3)).astype(np.float32),
                quats=q,
                log_scales=rng.normal(-3, 1, size=(n, 3)).astype(np.float32),
                opacity_logits=rng.normal(size=n).astype(np.float32),
                colors=rng.uniform(size=(n, 3)).astype(np.float32),
                kf_id=rng.integers(0, 1000, size=n))


def test_round_trip_values_equal(tmp_path):
    g = random_gaussians()
    p = tmp_path / "map.ply"
    save_gaussians_ply(p, g["means"], g["quats"], g["log_scales"], g["opacity_logits"],
                       g["colors"], g["kf_id"])
    d = load_gaussians_ply(p)
    for k in ("means", "quats", "log_scales", "opacity_logits"):
        np.testing.assert_array_equal(d[k], g[k])
    np.testing.assert_array_equal(d["kf_id"], g["kf_id"])
    # colour goes through the SH DC coefficient (c - 0.5) / C0 in float32
    np.testing.assert_allclose(d["colors"], g["colors"], atol=1e-6, rtol=0)


def test_layout_is_standard_3dgs(tmp_path):
    g = random_gaussians(5)
    p = tmp_path / "map.ply"
    save_gaussians_ply(p, torch.from_numpy(g["means"]), torch.from_numpy(g["quats"]),
                       g["log_scales"], g["opacity_logits"], g["colors"])   # torch or numpy
    raw = p.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    lines = header.decode().splitlines()
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 5"]
    props = [ln.split()[-1] for ln in lines if ln.startswith("property")]
    assert props == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                     "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert all(ln.split()[1] == "float" for ln in lines if ln.startswith("property"))
    v = np.frombuffer(body, dtype="<f4").reshape(5, 17)
    # rot_0 is w (our quats are x, y, z, w), f_dc is the SH DC of the colour
    np.testing.assert_array_equal(v[:, 13], g["quats"][:, 3])
    np.testing.assert_array_equal(v[:, 14:17], g["quats"][:, :3])
    np.testing.assert_allclose(v[:, 6:9], (g["colors"] - 0.5) / SH_C0, rtol=1e-6)
    np.testing.assert_array_equal(v[:, 3:6], 0)


def test_reads_foreign_3dgs_file_with_extra_properties(tmp_path):
    """A file as the 3DGS trainer writes it (SH degree 1 rest coefficients, no kf_id)."""
    n = 4
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(9)] + ["opacity", "scale_0", "scale_1", "scale_2",
                                                    "rot_0", "rot_1", "rot_2", "rot_3"])
    v = np.zeros(n, dtype=[(k, "<f4") for k in names])
    v["x"] = np.arange(n)
    v["rot_0"] = 1.0                                    # identity in w, x, y, z
    v["f_dc_0"] = 1.0
    header = "ply\nformat binary_little_endian 1.0\ncomment made by hand\n" \
             f"element vertex {n}\n" + "".join(f"property float {k}\n" for k in names) + \
             "end_header\n"
    p = tmp_path / "foreign.ply"
    p.write_bytes(header.encode() + v.tobytes())
    d = load_gaussians_ply(p)
    np.testing.assert_array_equal(d["means"][:, 0], np.arange(n))
    np.testing.assert_array_equal(d["quats"], np.tile([0, 0, 0, 1], (n, 1)))
    # float32 colour 0.5 + C0 * f_dc: two float32 roundings (<= 2 x 2^-24 relative) against
    # the exact float64 value; assert_allclose's default rtol=1e-7 is below float32 eps
    np.testing.assert_allclose(d["colors"][:, 0], 0.5 + SH_C0, rtol=2 * np.finfo(np.float32).eps)
    np.testing.assert_array_equal(d["kf_id"], 0)


def test_errors(tmp_path):
    with pytest.raises(PlyError, match="not found"):
        load_gaussians_ply(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_text("hello\n")
    with pytest.raises(PlyError, match="not a PLY"):
        load_gaussians_ply(bad)
    mesh = tmp_path / "mesh.ply"
    mesh.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    with pytest.raises(PlyError, match="binary"):
        load_gaussians_ply(mesh)
    g = random_gaussians(3)
    p = tmp_path / "cut.ply"
    save_gaussians_ply(p, g["means"], g["quats"], g["log_scales"], g["opacity_logits"],
                       g["colors"])
    p.write_bytes(p.read_bytes()[:-10])
    with pytest.raises(PlyError, match="truncated"):
        load_gaussians_ply(p)
