"""mapping.raster_backend: the configured rasterizer backend is honoured or refused with a clear
error (never a silent fallback); auto says which backend it picked and why, in the log and in
the map metrics."""
import json
import logging

import numpy as np
import pytest
import torch

import splat_slam_ros.mapping.optimise as optimise_mod
import splat_slam_ros.mapping.rasterizer as raster
from splat_slam_ros.config import (RASTER_BACKENDS, ConfigError, MappingConfig, SlamConfig,
                                   load_config)
from splat_slam_ros.evaluation.rendering import evaluate_keyframes
from splat_slam_ros.mapping.keyframe_views import KEYFRAMES_JSON
from splat_slam_ros.mapping.mapper import Mapper
from splat_slam_ros.mapping.rasterizer import (BackendChoice, RasterBackendError,
                                               RasterizerBuildError, RasterizerInputError,
                                               select_backend)
from splat_slam_ros.types import Intrinsics

W, H, F = 32, 24, 30.0
K = Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)
KEY = "mapping.raster_backend"
FAKE_BUILD_ERROR = "no C++ compiler found (test stand-in)"


def cfg_with(backend: str) -> SlamConfig:
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast(device="cpu", raster_backend=backend, iters_first=3,
                                     iters_per_keyframe=2, final_refine_iters=0, mesh=False)
    return cfg


def keyframe(seed=0):
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    return img, np.eye(4), np.full((H, W), 2.0, np.float32)


@pytest.fixture
def no_extension(monkeypatch):
    """The C++ extension made unloadable (what a failed build looks like to the loader)."""
    def fail(verbose=False):
        raise RasterizerBuildError(FAKE_BUILD_ERROR)
    monkeypatch.setattr(raster, "load_extension", fail)


@pytest.fixture
def backends_used(monkeypatch):
    """The ``backend=`` of every rasterize call the mapper makes."""
    used = []
    real = optimise_mod.rasterize

    def spy(*args, **kw):
        used.append(kw.get("backend"))
        return real(*args, **kw)
    monkeypatch.setattr(optimise_mod, "rasterize", spy)
    return used


# ------------------------------------------------------------------ config key
def test_config_key_default_values_and_unknown_rejected(tmp_path):
    assert SlamConfig().mapping.raster_backend == "auto"
    assert set(RASTER_BACKENDS) == set(raster.BACKENDS)
    for name in RASTER_BACKENDS:
        assert load_config(overrides={KEY: name}).mapping.raster_backend == name
    with pytest.raises(ConfigError, match=r"'mapping\.raster_backend' must be one of "
                                          r"auto, cpp, torch, gsplat, got 'opengl'"):
        load_config(overrides={KEY: "opengl"})
    p = tmp_path / "bad.yaml"
    p.write_text("mapping:\n  raster_backend: cuda\n")
    with pytest.raises(ConfigError, match=r"mapping\.raster_backend.*got 'cuda'"):
        load_config(p)
    # a config built in code, bypassing the loader: the mapper refuses it the same way
    with pytest.raises(ConfigError, match=r"mapping\.raster_backend: unknown rasterizer backend"):
        Mapper(cfg_with("opengl"), K)


# ------------------------------------------------------------------ explicit choices
def test_explicit_torch_is_used(backends_used):
    mp = Mapper(cfg_with("torch"), K)
    assert mp.raster == BackendChoice("torch", f"{KEY}: torch (pure torch, slow)", "torch")
    img, pose, depth = keyframe()
    st = mp.add_keyframe(0, img, pose, depth)
    rgb, _ = mp.render(pose)
    assert st["mapped"] and rgb.shape == (H, W, 3)
    assert backends_used and set(backends_used) == {"torch"}
    assert st["raster_backend"] == "torch" and KEY in st["raster_backend_reason"]


def test_explicit_cpp_without_extension_raises(no_extension):
    with pytest.raises(RasterBackendError) as ei:
        Mapper(cfg_with("cpp"), K)
    msg = str(ei.value)
    assert f"{KEY} is 'cpp'" in msg and FAKE_BUILD_ERROR in msg
    assert "install g++ and ninja" in msg and f"{KEY}: torch" in msg
    assert isinstance(ei.value, ConfigError)     # the CLI prints it as `error: ...`


def test_explicit_cpp_on_cuda_device_raises():
    with pytest.raises(RasterBackendError, match=r"'cpp' but the map is on cuda.*CPU only"):
        select_backend("cpp", torch.device("cuda"))


def test_explicit_gsplat_on_cpu_raises(monkeypatch):
    with pytest.raises(RasterBackendError, match=r"'gsplat' but the map is on cpu: gsplat "
                                                 r"needs a CUDA device"):
        Mapper(cfg_with("gsplat"), K)
    # on a CUDA device without gsplat installed: the same, with the install hint
    monkeypatch.setattr(raster, "_gsplat_error", lambda: "ModuleNotFoundError: gsplat")
    with pytest.raises(RasterBackendError, match=r"gsplat cannot be imported.*pip install gsplat"):
        select_backend("gsplat", torch.device("cuda"))
    # and the functional API refuses CPU tensors for gsplat instead of failing inside gsplat
    q = torch.tensor([[0, 0, 0, 1.0]])
    with pytest.raises(RasterizerInputError, match="gsplat' needs CUDA tensors"):
        raster.rasterize(torch.zeros(1, 3), q, torch.ones(1, 3), torch.ones(1), torch.ones(1, 3),
                         torch.eye(4), (10, 10, 5, 5), 8, 8, backend="gsplat")


# ------------------------------------------------------------------ auto
def test_auto_without_extension_runs_torch_and_says_why(no_extension, backends_used, caplog):
    with caplog.at_level(logging.INFO, logger="splat_slam_ros.mapping.rasterizer"):
        mp = Mapper(cfg_with("auto"), K)
    assert mp.raster.name == "torch" and mp.raster.fallback
    assert mp.raster.reason == f"auto: C++ extension unavailable: {FAKE_BUILD_ERROR}"
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and FAKE_BUILD_ERROR in warned[0].getMessage()
    assert "torch" in warned[0].getMessage() and KEY in warned[0].getMessage()
    img, pose, depth = keyframe()
    st = mp.add_keyframe(0, img, pose, depth)
    assert st["mapped"] and set(backends_used) == {"torch"}
    assert mp.stats()["raster_backend"] == "torch"
    assert FAKE_BUILD_ERROR in mp.stats()["raster_backend_reason"]


def test_auto_picks_cpp_when_it_loads(monkeypatch, caplog):
    monkeypatch.setattr(raster, "load_extension", lambda verbose=False: object())
    with caplog.at_level(logging.INFO, logger="splat_slam_ros.mapping.rasterizer"):
        c = select_backend("auto", "cpu", announce=True)
    assert c == BackendChoice("cpp", "auto: C++ OpenMP extension loaded")
    assert str(c) == "cpp (auto: C++ OpenMP extension loaded)"
    assert [r.levelno for r in caplog.records] == [logging.INFO]


def test_auto_on_cuda_without_gsplat_is_a_reported_fallback(monkeypatch):
    monkeypatch.setattr(raster, "_gsplat_error", lambda: "ModuleNotFoundError: gsplat")
    c = select_backend("auto", torch.device("cuda"))
    assert c.name == "torch" and c.fallback and "without gsplat" in c.reason
    monkeypatch.setattr(raster, "_gsplat_error", lambda: None)
    c = select_backend("auto", torch.device("cuda"))
    assert c.name == "gsplat" and not c.fallback


# ------------------------------------------------------------------ metrics
def test_map_metrics_carry_the_backend(no_extension, tmp_path):
    mp = Mapper(cfg_with("auto"), K)
    img, pose, depth = keyframe()
    mp.add_keyframe(0, img, pose, depth)
    st = json.loads(json.dumps(mp.stats()))          # what metrics.json "map" holds
    assert st["raster_backend"] == "torch"
    assert st["raster_backend_reason"].startswith("auto: C++ extension unavailable")
    evaluate_keyframes(mp, tmp_path / "renders")
    doc = json.loads((tmp_path / "renders" / KEYFRAMES_JSON).read_text())
    assert doc["map"]["raster_backend"] == "torch"
    assert FAKE_BUILD_ERROR in doc["map"]["raster_backend_reason"]
