"""Monocular depth loading + inference with tiny models built here (ONNX and TorchScript)."""
import warnings

import numpy as np
import pytest
import torch
import yaml

from splat_slam_ros.tracking.mono_depth import (MonoDepthError, MonoDepthModel, load_mono_depth,
                                       read_sidecar)

MEAN = [0.5, 0.25, 0.0]
STD = [0.5, 0.25, 1.0]
W_RGB = [0.5, 1.0, 2.0]
BIAS = 3.0


class Linear1x1(torch.nn.Module):
    """out = sum_c W_c x_c + BIAS (a 1x1 conv), so the expected output is computable."""

    def __init__(self, cin=3, cout=1):
        super().__init__()
        self.c = torch.nn.Conv2d(cin, cout, 1)
        with torch.no_grad():
            self.c.weight.zero_()
            self.c.weight[0, :min(cin, 3), 0, 0] = torch.tensor(W_RGB[:min(cin, 3)])
            self.c.bias.fill_(BIAS)

    def forward(self, x):
        return self.c(x)


class Rank3(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.c = torch.nn.Conv1d(3, 1, 1)

    def forward(self, x):
        return self.c(x)


def export_onnx(module, example, path, dynamic=False):
    kw = {}
    if dynamic:
        kw["dynamic_axes"] = {"image": {2: "h", 3: "w"}, "depth": {2: "h", 3: "w"}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module.eval(), (example,), str(path), dynamo=False,
                          input_names=["image"], output_names=["depth"], **kw)
    return path


def write_sidecar(model_path, **kw):
    d = dict(output="depth", mean=MEAN, std=STD)
    d.update(kw)
    (model_path.parent / (model_path.name + ".yaml")).write_text(yaml.safe_dump(d))


def expected_value(rgb):
    x = (np.asarray(rgb, np.float64) / 255.0 - MEAN) / STD
    return float(np.dot(W_RGB, x) + BIAS)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("mono")
    out = {}
    out["static"] = export_onnx(Linear1x1(), torch.zeros(1, 3, 24, 32), d / "static.onnx")
    out["dynamic"] = export_onnx(Linear1x1(), torch.zeros(1, 3, 32, 32), d / "dyn.onnx",
                                 dynamic=True)
    out["one_channel_in"] = export_onnx(Linear1x1(cin=1), torch.zeros(1, 1, 16, 16),
                                        d / "c1.onnx")
    out["two_channel_out"] = export_onnx(Linear1x1(cout=2), torch.zeros(1, 3, 16, 16),
                                         d / "o2.onnx")
    out["rank3"] = export_onnx(Rank3(), torch.zeros(1, 3, 16), d / "r3.onnx")
    ts = d / "lin.pt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.jit.script(Linear1x1()).save(str(ts))
    out["torchscript"] = ts
    return out


def image(h=60, w=80, rgb=(100, 150, 200)):
    return np.broadcast_to(np.asarray(rgb, np.uint8), (h, w, 3)).copy()


# ------------------------------------------------------------------- inference
def test_onnx_normalisation_and_resize_back(models):
    p = models["static"]
    write_sidecar(p, output="depth")            # input size from the static shape 24x32
    m = load_mono_depth(p, provider="cpu")
    assert isinstance(m, MonoDepthModel) and m.kind == "depth"
    pred = m.predict(image(60, 80))
    assert pred.shape == (60, 80) and pred.dtype == np.float32
    np.testing.assert_allclose(pred, expected_value((100, 150, 200)), rtol=1e-4)


def test_onnx_disparity_output_is_converted(models):
    p = models["static"]
    write_sidecar(p, output="disparity")
    m = load_mono_depth(p, provider="cpu")
    assert m.kind == "disparity"
    pred = m.predict(image(30, 40))
    np.testing.assert_allclose(pred, 1.0 / expected_value((100, 150, 200)), rtol=1e-4)


def test_onnx_orientation_and_bgr(models):
    """A left-to-right red ramp must give a left-to-right increasing map (no transposes)."""
    p = models["dynamic"]
    write_sidecar(p, output="depth", resize="dynamic", size_multiple=8)
    m = load_mono_depth(p, provider="cpu")
    img = image(48, 64, (0, 0, 0))
    img[..., 0] = np.linspace(0, 255, 64).astype(np.uint8)[None, :]
    pred = m.predict(img)
    assert pred.shape == (48, 64)
    col = pred.mean(0)
    assert np.all(np.diff(col) >= -1e-5) and col[-1] > col[0] + 0.9
    np.testing.assert_allclose(pred[:, 0], expected_value((0, 0, 0)), rtol=1e-4)
    # bgr: the red ramp is now read as the blue channel (weight 2.0 / std 1.0)
    write_sidecar(p, output="depth", resize="dynamic", size_multiple=8, channel_order="bgr")
    pb = load_mono_depth(p, provider="cpu").predict(img)
    np.testing.assert_allclose(pb[:, -1], expected_value((0, 0, 255)), rtol=1e-4)


def test_onnx_letterbox_keeps_aspect(models):
    p = models["dynamic"]
    write_sidecar(p, output="depth", resize="letterbox", input_size=[32, 32])
    m = load_mono_depth(p, provider="cpu")
    pred = m.predict(image(60, 80, (10, 20, 30)))
    assert pred.shape == (60, 80)
    # the padded band (mean colour) must not leak into the image: all pixels take the value
    np.testing.assert_allclose(pred, expected_value((10, 20, 30)), rtol=1e-3)


def test_torchscript_backend(models):
    p = models["torchscript"]
    write_sidecar(p, output="depth", input_size=[20, 20])
    m = load_mono_depth(p, provider="cpu")
    pred = m.predict(image(45, 60, (50, 60, 70)))
    assert pred.shape == (45, 60)
    np.testing.assert_allclose(pred, expected_value((50, 60, 70)), rtol=1e-4)


# ------------------------------------------------------------------- errors
def test_missing_file(tmp_path):
    with pytest.raises(MonoDepthError, match="not found"):
        load_mono_depth(tmp_path / "nope.onnx")


def test_corrupt_file(tmp_path):
    p = tmp_path / "junk.onnx"
    p.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    write_sidecar(p)
    with pytest.raises(MonoDepthError, match="cannot load"):
        load_mono_depth(p, provider="cpu")
    q = tmp_path / "junk.pt"
    q.write_bytes(b"\x00\x01garbage" * 100)
    write_sidecar(q)
    with pytest.raises(MonoDepthError, match="cannot load"):
        load_mono_depth(q, provider="cpu")


@pytest.mark.parametrize("key,match", [("one_channel_in", "channels"),
                                       ("two_channel_out", "1 channel"),
                                       ("rank3", "rank 3")])
def test_incompatible_models(models, key, match):
    p = models[key]
    write_sidecar(p)
    with pytest.raises(MonoDepthError, match=match):
        load_mono_depth(p, provider="cpu")


def test_sidecar_errors(models, tmp_path):
    src = models["static"]
    p = tmp_path / "m.onnx"
    p.write_bytes(src.read_bytes())
    with pytest.raises(MonoDepthError, match="no sidecar"):
        load_mono_depth(p)
    (tmp_path / "m.yaml").write_text("output: metric\n")        # model.yaml form is found too
    with pytest.raises(MonoDepthError, match="depth or disparity"):
        load_mono_depth(p)
    (tmp_path / "m.yaml").write_text("output: depth\nmean_rgb: [0, 0, 0]\n")
    with pytest.raises(MonoDepthError, match="unknown key"):
        load_mono_depth(p)
    (tmp_path / "m.yaml").write_text("input_size: [32, 32]\n")
    with pytest.raises(MonoDepthError, match="'output'"):
        read_sidecar(p)
    (tmp_path / "m.yaml").write_text("output: depth\n")
    assert load_mono_depth(p, provider="cpu").kind == "depth"
    with pytest.raises(MonoDepthError, match="mono_provider"):
        load_mono_depth(p, provider="tpu")


def test_unsupported_suffix(tmp_path):
    p = tmp_path / "model.bin"
    p.write_bytes(b"x")
    with pytest.raises(MonoDepthError, match="unsupported"):
        load_mono_depth(p)


def test_proxy_depth_estimator_runs_the_configured_model(models):
    """depth.mono_model -> ProxyDepthEstimator loads the ONNX file and fills holes with it."""
    from splat_slam_ros.config import SlamConfig
    from splat_slam_ros.depth.compose import SOURCE_MONO
    from splat_slam_ros.depth.proxy_depth import ProxyDepthEstimator
    from splat_slam_ros.types import Intrinsics, KeyframeData
    p = models["dynamic"]
    write_sidecar(p, output="depth", resize="dynamic", size_multiple=8)
    cfg = SlamConfig()
    cfg.depth.mono_model = str(p)
    cfg.depth.mono_provider = "cpu"
    cfg.depth.mv_min_parallax_deg = 0.0   # identical views (no parallax) make the valid part
    intr = Intrinsics(100.0, 100.0, 79.5, 59.5, 160, 120)
    est = ProxyDepthEstimator(cfg, intr)
    # depth ramp 1..2 m along x (identical views: consistent), image red ramp -> mono ramp
    x = (np.arange(20) + 0.5) / 20
    disp = np.broadcast_to(1.0 / (1.0 + x), (15, 20)).astype(np.float32)
    img = np.zeros((120, 160, 3), np.uint8)
    img[..., 0] = np.linspace(0, 255, 160).astype(np.uint8)[None, :]
    holed = disp.copy()
    holed[5:10, 5:12] = 0                                  # no multi-view depth here
    res = None
    for k in range(3):
        kf = KeyframeData(k, k, 0.1 * k, np.eye(4), img, intr, holed if k == 2 else disp,
                          np.ones_like(disp))
        res = est.add_keyframe(kf)
    hole = res.source == SOURCE_MONO
    assert hole.sum() > 40 * 35 * 0.8 and np.isfinite(res.mono_scale) and res.mono_scale > 0
    true = 1.0 + (np.arange(160) + 0.5) / 160
    err = np.abs(res.depth - true[None, :])[hole]
    assert np.median(err) < 0.02


def test_estimator_checks_model_file_at_start_and_loads_lazily(models, tmp_path):
    from splat_slam_ros.config import SlamConfig
    from splat_slam_ros.depth.proxy_depth import ProxyDepthEstimator
    from splat_slam_ros.types import Intrinsics
    intr = Intrinsics(100.0, 100.0, 79.5, 59.5, 160, 120)
    cfg = SlamConfig()
    cfg.depth.mono_model = str(tmp_path / "missing.onnx")
    with pytest.raises(MonoDepthError, match="not found"):
        ProxyDepthEstimator(cfg, intr)
    p = models["static"]
    write_sidecar(p, output="disparity")
    cfg.depth.mono_model = str(p)
    est = ProxyDepthEstimator(cfg, intr)
    assert est.mono is None and est.fit_space == "disparity"     # sidecar read, not loaded
