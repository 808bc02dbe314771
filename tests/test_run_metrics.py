"""Run-level metrics of metrics.json: LPIPS with a configured backbone file
(``evaluation.lpips_backbone``), and the split of the map's depth L1 into depth edges and
surfaces on a room with boxes (clean depth, and depth with no value along the silhouettes as
sensors and many renderers leave it)."""
import json
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from splat_slam_ros.evaluation import depth as evd
from splat_slam_ros.evaluation import perceptual as evp
from splat_slam_ros import pipeline
from splat_slam_ros.evaluation import run as run_eval
from splat_slam_ros.config import ConfigError, SlamConfig, load_config
from splat_slam_ros.io.trajectory_io import write_tum
from splat_slam_ros.mapping.mapper import Mapper
from splat_slam_ros.tracking.flow_frontend import mapping_preprocessor
from splat_slam_ros.types import Intrinsics
from test_evaluation import lpips_files  # noqa: F401 (the tiny backbone fixture)
from test_evaluation import _manual_lpips as _lpips_formula
from conftest import FrameList


# ------------------------------------------------------------------------------ LPIPS
def _manual_lpips(net, img_u8, ref_u8) -> float:
    """The LPIPS formula written out (all channel weights 1), RGB uint8 inputs."""
    return _lpips_formula(net, img_u8 / 255.0, ref_u8 / 255.0)


def _write_views(renders, n=3, h=24, w=32, seed=0):
    """A renders/ folder as a run writes it: keyframes.json + kf_<id>.png / _input.png (RGB
    pairs returned, the files are BGR as cv2 writes them)."""
    rng = np.random.default_rng(seed)
    renders.mkdir(parents=True, exist_ok=True)
    pairs, ids = [], [0, 4, 9][:n]
    for k in ids:
        ref = (np.kron(rng.uniform(40, 220, (h // 4, w // 4, 3)), np.ones((4, 4, 1)))
               ).astype(np.uint8)
        img = np.clip(ref + rng.normal(0, 12, ref.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(renders / f"kf_{k:05d}.png"), img[..., ::-1])
        cv2.imwrite(str(renders / f"kf_{k:05d}_input.png"), ref[..., ::-1])
        pairs.append((img, ref))
    (renders / "keyframes.json").write_text(json.dumps(
        {"keyframes": [{"kf_id": k, "psnr": 20.0} for k in ids]}))
    return pairs


def test_evaluation_lpips_key_defaults_off_and_loads_from_yaml(tmp_path):
    assert SlamConfig().evaluation.lpips_backbone == ""
    p = tmp_path / "c.yaml"
    p.write_text("evaluation:\n  lpips_backbone: /models/vgg.pt\n")
    assert load_config(p).evaluation.lpips_backbone == "/models/vgg.pt"
    assert "evaluation.lpips_backbone" in SlamConfig().flat()      # a ROS parameter too


def test_lpips_in_metrics_is_null_without_a_backbone(tmp_path):
    _write_views(tmp_path / "renders")
    m = {}
    run_eval.evaluate_lpips(tmp_path, SlamConfig(), m)
    assert m == {"lpips": None}
    run_eval.check_lpips_config(SlamConfig())                  # nothing to check


def test_lpips_in_metrics_is_the_keyframe_mean_with_a_backbone(tmp_path, lpips_files):
    net, path = lpips_files
    pairs = _write_views(tmp_path / "renders")
    cfg = load_config(overrides={"evaluation.lpips_backbone": str(path)})
    run_eval.check_lpips_config(cfg)
    m = {}
    run_eval.evaluate_lpips(tmp_path, cfg, m)
    expect = np.mean([_manual_lpips(net, img, ref) for img, ref in pairs])
    assert m["lpips"] == pytest.approx(expect, abs=2e-6) and m["lpips"] > 0, m
    assert "lpips_error" not in m
    assert not evp._LPIPS_CACHE                                 # the backbone is let go


def test_lpips_backbone_missing_or_invalid_is_a_clear_error(tmp_path, lpips_files, capsys):
    _, path = lpips_files
    missing = tmp_path / "nope.pt"
    junk = tmp_path / "junk.pt"
    junk.write_text("not a model")
    for bad, msg in ((missing, "not found"), (junk, "not a loadable TorchScript")):
        cfg = load_config(overrides={"evaluation.lpips_backbone": str(bad)})
        with pytest.raises(ConfigError, match=msg) as e:
            run_eval.check_lpips_config(cfg)
        assert "evaluation.lpips_backbone" in str(e.value) and str(bad) in str(e.value)
    cfg = load_config(overrides={"evaluation.lpips_backbone": str(path),
                                 "evaluation.lpips_weights": str(missing)})
    with pytest.raises(ConfigError, match="weights file not found"):
        run_eval.check_lpips_config(cfg)
    with pytest.raises(ConfigError, match="lpips_backbone is not"):
        run_eval.check_lpips_config(load_config(
            overrides={"evaluation.lpips_weights": str(path)}))
    # a file gone by the end of the run: no silent skip, metrics.json says why
    _write_views(tmp_path / "renders")
    cfg = load_config(overrides={"evaluation.lpips_backbone": str(missing)})
    m = {}
    run_eval.evaluate_lpips(tmp_path, cfg, m)
    assert m["lpips"] is None and "not found" in m["lpips_error"], m
    assert "error: no LPIPS" in capsys.readouterr().err


def _fake_gt_mapping(pairs_seed=1):
    def fake(dataset, cfg, out, progress, max_frames, result, metrics):
        _write_views(out / "renders", seed=pairs_seed)
        result.frames, result.keyframes = 3, 3
        metrics.update({"psnr": 20.0, "ssim": 0.5, "gaussians": 100})
    return fake


def test_in_process_run_writes_lpips_to_metrics_json(tmp_path, lpips_files, monkeypatch):
    """splat-slam-run's pipeline: ``lpips`` in metrics.json (null without a backbone); a
    missing backbone stops the run before it starts (the CLI: ``error:``, status 2)."""
    net, path = lpips_files
    monkeypatch.setattr(pipeline, "_run_gt_mapping", _fake_gt_mapping())
    from splat_slam_ros.report import build
    monkeypatch.setattr(build, "write_report", lambda out, cfg: None)
    ds = SimpleNamespace(name="fake")
    out = tmp_path / "off"
    pipeline.run(ds, SlamConfig(), out, mode="gt_mapping", progress=False)
    m = json.loads((out / "metrics.json").read_text())
    assert "lpips" in m and m["lpips"] is None and "lpips_error" not in m
    cfg = load_config(overrides={"evaluation.lpips_backbone": str(path)})
    out = tmp_path / "on"
    res = pipeline.run(ds, cfg, out, mode="gt_mapping", progress=False)
    m = json.loads((out / "metrics.json").read_text())
    pairs = _write_views(tmp_path / "again", seed=1)
    expect = np.mean([_manual_lpips(net, img, ref) for img, ref in pairs])
    assert m["lpips"] == pytest.approx(expect, abs=2e-6) and res.metrics["lpips"] == m["lpips"]
    cfg = load_config(overrides={"evaluation.lpips_backbone": str(tmp_path / "gone.pt")})
    with pytest.raises(ConfigError, match="not found"):
        pipeline.run(ds, cfg, tmp_path / "bad", mode="gt_mapping", progress=False)
    assert not (tmp_path / "bad").exists()                      # nothing ran


def test_splat_slam_run_rejects_a_missing_backbone_before_running(tmp_path, capsys):
    from splat_slam_ros.cli.run import main
    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(2):
        cv2.imwrite(str(folder / f"{i:04d}.png"), np.full((48, 64, 3), 100, np.uint8))
    (tmp_path / "K.yaml").write_text("fx: 60\nfy: 60\ncx: 31.5\ncy: 23.5\nwidth: 64\n"
                                     "height: 48\n")
    rc = main([str(folder), "--out", str(tmp_path / "out"), "--intrinsics",
               str(tmp_path / "K.yaml"), "--no-progress",
               "--set", f"evaluation.lpips_backbone={tmp_path / 'vgg.pt'}"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: evaluation.lpips_backbone"), err
    assert "not found" in err and "Traceback" not in err


def test_launcher_writes_lpips_with_the_shared_evaluation(tmp_path, lpips_files, monkeypatch):
    """splat-slam-launch: the same check before the run and the same ``lpips`` entry."""
    from splat_slam_nodes.tools import launch, launch_results
    net, path = lpips_files
    monkeypatch.setenv("SPLAT_SLAM_DDS_RANGE", "localhost")
    bad = launch.Launcher(launch.build_parser().parse_args(
        ["--out", str(tmp_path / "bad"), "--set",
         f"evaluation.lpips_backbone={tmp_path / 'gone.pt'}"]))
    with pytest.raises(launch.LaunchError, match="LPIPS backbone file not found"):
        bad.plan()
    out = tmp_path / "run"
    L = launch.Launcher(launch.build_parser().parse_args(
        ["--out", str(out), "--set", f"evaluation.lpips_backbone={path}"]))
    L.plan()
    pairs = _write_views(out / "renders", seed=2)
    saved = {"mapper": {"metrics": {"psnr": 20.0, "gaussians": 100}},
             "tracker": {"frames": 3, "posed": 3, "keyframes": 3}}
    monkeypatch.setattr(L, "has_event", lambda node, kind: saved.get(node))
    m = launch_results.write_metrics(L, L.t0 + 1.0)
    expect = np.mean([_manual_lpips(net, img, ref) for img, ref in pairs])
    assert m["lpips"] == pytest.approx(expect, abs=2e-6), m
    assert json.loads((out / "metrics.json").read_text())["lpips"] == m["lpips"]


def test_launcher_run_with_keyframes_but_no_map_is_an_error():
    """A graph run whose own mapper finalised without mapping a keyframe (its report has no
    map) ends with a reason (exit 3), never as a success; a launcher that runs no mapper
    (--tracking-only, localize, or --nodes without it) and runs without keyframes are judged
    elsewhere."""
    from splat_slam_nodes.tools.launch_results import no_map_reason
    m = {"keyframes": 5}
    reason = no_map_reason(True, m)
    assert reason is not None and "5 keyframes" in reason and "no map" in reason
    assert no_map_reason(False, m) is None
    assert no_map_reason(True, {"keyframes": 0}) is None
    assert no_map_reason(True, {"keyframes": 5, "gaussians": 100}) is None


# ------------------------------------------------------------- depth edges and surfaces
# a room (side walls at x = -2.5 / 2.5 m, floor 1.2 m below the camera, ceiling 1.3 m above,
# back wall at 5 m) with floating boxes in front at several distances:
# (x0, x1, y0, y1, z0, z1) in metres, camera at the origin looking along +z (OpenCV axes)
ROOM = (-2.5, 2.5, -1.3, 1.2, 5.0)
# (no face seen so obliquely that its depth changes by 5 % from one pixel to the next)
BOXES = [(-1.6, -0.7, -0.2, 0.7, 1.2, 1.8), (0.5, 1.1, -0.9, -0.4, 2.4, 3.0),
         (-0.4, 0.2, 0.3, 0.8, 0.6, 0.9), (1.2, 2.0, 0.5, 1.0, 3.6, 4.0)]


def _room(K: Intrinsics):
    """(z-depth H x W metres, object id per pixel: 0 = room, i = box i) by ray casting."""
    u, v = np.meshgrid(np.arange(K.width) + 0.0, np.arange(K.height) + 0.0)
    dx, dy = (u - K.cx) / K.fx, (v - K.cy) / K.fy        # ray (dx, dy, 1): t = z-depth
    x0, x1, y0, y1, zb = ROOM
    with np.errstate(divide="ignore"):
        t = np.full(dx.shape, zb)
        for lo, hi, d in ((x0, x1, dx), (y0, y1, dy)):
            t = np.minimum(t, np.where(d > 0, hi / d, np.where(d < 0, lo / d, np.inf)))
        ids = np.zeros(dx.shape, int)
        for i, (bx0, bx1, by0, by1, bz0, bz1) in enumerate(BOXES, 1):
            near, far = np.full(dx.shape, bz0), np.full(dx.shape, bz1)
            for lo, hi, d in ((bx0, bx1, dx), (by0, by1, dy)):
                a, b = lo / d, hi / d
                lo_t = np.where(d == 0, np.where(lo <= 0 <= hi, -np.inf, np.inf), np.minimum(a, b))
                hi_t = np.where(d == 0, np.where(lo <= 0 <= hi, np.inf, -np.inf), np.maximum(a, b))
                near, far = np.maximum(near, lo_t), np.minimum(far, hi_t)
            hit = (near <= far) & (near > 0) & (near < t)
            t, ids = np.where(hit, near, t), np.where(hit, i, ids)
    return t.astype(np.float32), ids


def _tum_like(W, H) -> Intrinsics:
    f = 525.0 * W / 640
    return Intrinsics(f, f, (W - 1) / 2, (H - 1) / 2, W, H)


def _silhouettes(ids):
    """Pixels on either side of a change of object (every one a depth step here)."""
    s = np.zeros(ids.shape, bool)
    dx, dy = ids[:, 1:] != ids[:, :-1], ids[1:] != ids[:-1]
    s[:, 1:] |= dx
    s[:, :-1] |= dx
    s[1:] |= dy
    s[:-1] |= dy
    return s


def _no_depth_on_silhouettes(depth, ids, width):
    """What sensors and many renderers give: no depth on the mixed / occluded pixels along
    every silhouette (``width`` px on the far side)."""
    far_side = np.zeros(ids.shape, bool)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        step = ids[a] != ids[b]                          # neighbours a / b: which is farther
        far_side[a] |= step & (depth[a] > depth[b])
        far_side[b] |= step & (depth[b] > depth[a])
    far_side = cv2.dilate(far_side.astype(np.uint8), np.ones((width, width), np.uint8)) > 0
    out = depth.copy()
    out[far_side] = 0.0
    return out


def _dilate(mask, r):
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0


@pytest.mark.parametrize("W,H", [(640, 480), (320, 240)])
def test_depth_edge_band_of_a_room_with_boxes(W, H):
    """Exactly the pixels within the radius of a box silhouette, whatever the depth's
    resolution, and (almost) the same band when the depth has no value along the
    silhouettes."""
    depth, ids = _room(_tum_like(W, H))
    assert 0.5 <= depth.min() and depth.max() <= 5.0
    for r in (0, 2, 8):
        band = evd.depth_edge_band(depth, r).numpy()
        expect = _dilate(_silhouettes(ids), r)
        assert np.array_equal(band, expect), (r, band.mean(), expect.mean())
    clean = evd.depth_edge_band(depth, 8).numpy()
    assert 0.02 < clean.mean() < 0.4, clean.mean()
    seam = 2 if W == 640 else 1
    holed = _no_depth_on_silhouettes(depth, ids, seam)
    assert (holed == 0).mean() > 0.005
    band = evd.depth_edge_band(holed, 8).numpy()
    # the edge pixels are the valid ones either side of the gap: the band is the gap wider
    assert clean.mean() <= band.mean() < 1.25 * clean.mean(), (band.mean(), clean.mean())
    assert (band & clean).sum() > 0.98 * clean.sum()
    # the walls, floor and ceiling are no edges (grazing floor included)
    assert not evd.depth_edge_band(np.where(ids == 0, depth, 0), 0).numpy()[ids == 0].any()


class _Data(FrameList):
    """A dataset of frames with ground-truth depth at identity-ish poses (Sim(3) scale 1)."""
    has_gt_depth = True

    def __init__(self, K, depths):
        self.intrinsics = K
        self.ts = np.arange(len(depths)) * 0.1
        self.poses = np.stack([np.eye(4)] * len(depths))
        self.poses[:, 0, 3] = [0.0, 0.05, 0.05, 0.0][:len(depths)]
        self.poses[:, 1, 3] = [0.0, 0.0, 0.05, 0.05][:len(depths)]
        super().__init__(SimpleNamespace(timestamp=t, gt_depth=d) for t, d in zip(self.ts, depths))

    def gt_trajectory(self):
        return self.ts, self.poses


@pytest.mark.parametrize("W,H,holes", [(640, 480, False), (640, 480, True), (320, 240, True)])
def test_map_depth_split_on_a_room_with_boxes(tmp_path, monkeypatch, W, H, holes):
    """metrics.json on a room with boxes: a map exact on the surfaces whose boxes bleed 2 px
    onto what is behind them has all its error at the edges (depth_l1_edges_cm > 0, never
    null) and none on the surfaces, also when the ground truth has no depth along the
    silhouettes."""
    K = _tum_like(W, H)
    depth, ids = _room(K)
    gt = _no_depth_on_silhouettes(depth, ids, 2 if W == 640 else 1) if holes else depth
    cfg = SlamConfig()
    pre = mapping_preprocessor(cfg, K)
    exact = pre.depth(depth)                           # the true depth at the mapping size
    nearer = cv2.erode(exact, np.ones((5, 5), np.uint8))
    bled = np.where(nearer < 0.9 * exact, nearer, exact)   # boxes 2 px too wide, nothing else

    class BleedingMap:
        def render(self, T):
            return None, bled

    monkeypatch.setattr(Mapper, "load_ply", staticmethod(lambda path, c, intr: BleedingMap()))
    data = _Data(K, [gt] * 4)
    write_tum(tmp_path / "trajectory_keyframes.txt", data.ts, data.poses)
    (tmp_path / "map.ply").write_bytes(b"")
    m = {}
    run_eval.evaluate_map_depth(data, tmp_path, cfg, m)
    assert m["depth_l1_views"] == 4, m
    assert 0.02 < m["depth_edge_band_fraction"] < 0.4, m
    assert m["depth_l1_edges_cm"] is not None and m["depth_l1_edges_cm"] > 5.0, m
    assert m["depth_l1_surfaces_cm"] == 0.0, m
    assert m["depth_l1_cm"] == pytest.approx(
        m["depth_edge_band_fraction"] * m["depth_l1_edges_cm"], rel=0.01), m
