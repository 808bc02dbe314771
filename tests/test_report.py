"""The run report: produced by a short synthetic run, complete, rebuilt byte-identically by
splat-slam-report, and still produced (saying what is missing) without ground truth or map."""
import base64
import json
import logging
import re
import shutil
from html.parser import HTMLParser

import cv2
import numpy as np
import pytest

from splat_slam_ros.cli.report import main as report_main
from splat_slam_ros.config import load_config
from splat_slam_ros.io.datasets import open_dataset
from splat_slam_synth import generate_sequence
from splat_slam_ros.pipeline import NotInitializedError, run
from splat_slam_ros.report.build import write_report
from splat_slam_ros.report.recording import WarningRecorder, WarningTee

SECTIONS = ["summary", "warnings", "missing", "trajectory", "keyframes", "map", "timing",
            "config"]
FAST = {"tracking.warmup": 4, "tracking.motion_filter_thresh": 2.0,
        "tracking.keyframe_thresh": 2.0, "mapping.iters_first": 30,
        "mapping.iters_per_keyframe": 5, "mapping.final_refine_iters": 10,
        "mapping.random_views_per_iter": 1, "mapping.window_views_per_iter": 3}


class Page(HTMLParser):
    """Sections (id -> text, images) of a report page."""

    def __init__(self, text: str):
        super().__init__()
        self.order, self.text, self.imgs, self.tags = [], {}, {}, set()
        self.cur = None
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.add(tag)
        if tag == "section":
            self.cur = a["id"]
            self.order.append(self.cur)
            self.text[self.cur], self.imgs[self.cur] = "", []
        elif tag == "img" and self.cur is not None:
            self.imgs[self.cur].append((a["src"], a.get("alt", "")))

    def handle_endtag(self, tag):
        if tag == "section":
            self.cur = None

    def handle_data(self, data):
        if self.cur is not None:
            self.text[self.cur] += data


def decode(src: str) -> np.ndarray:
    head, data = src.split(",", 1)
    assert head in ("data:image/png;base64", "data:image/jpeg;base64"), head
    im = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
    assert im is not None
    return im


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    d = tmp_path_factory.mktemp("report_seq")
    generate_sequence("builtin", 30, (160, 120), d / "seq", overwrite=True, progress=False,
                      realism="clean", fps=3)           # 10 s of the slow built-in path
    return d / "seq"


@pytest.fixture(scope="module")
def full_run(seq, tmp_path_factory):
    out = tmp_path_factory.mktemp("report_run") / "out"
    cfg = load_config(None, FAST)
    res = run(open_dataset(seq), cfg, out, mode="full", progress=False)
    return out, cfg, res


def test_full_run_writes_a_complete_report(full_run):
    out, cfg, res = full_run
    assert res.keyframes >= 3, res.metrics
    page = Page((out / "report.html").read_text())
    assert page.order == SECTIONS
    # self-contained: no script, no external link (base64 data may hold "http" by chance)
    outside_data = re.sub(r"data:[^\"']*", "", (out / "report.html").read_text())
    assert "script" not in page.tags and "http" not in outside_data
    assert "nothing" in page.text["missing"]                  # GT, map, config all present
    # summary figure embedded and identical to report.png
    src = page.imgs["summary"][0][0]
    assert base64.b64decode(src.split(",", 1)[1]) == (out / "report.png").read_bytes()
    assert decode(src).shape == (900, 1500, 3)
    m = json.loads((out / "metrics.json").read_text())
    assert f"{m['ate_rmse_cm_full']:.2f} cm" in page.text["summary"]
    causes = ", ".join(f"{c} {k}" for c, k in m["keyframe_causes"].items())
    assert f"{m['keyframes_per_s']:.2f} ({causes})" in page.text["summary"]
    assert f"{m['fps']:.2f}" in page.text["timing"] and "mapping" in page.text["timing"]
    assert len(page.imgs["trajectory"]) == 1 and len(page.imgs["map"]) == 1
    # keyframe grid: five tiles per mapped keyframe, at the keyframe's aspect ratio
    kj = json.loads((out / "renders" / "keyframes.json").read_text())
    n = len(kj["keyframes"])
    assert n == m["map"]["keyframes"] >= 1
    imgs = page.imgs["keyframes"]
    assert len(imgs) == 5 * n and "not recorded" not in page.text["keyframes"]
    for src, alt in imgs:
        assert decode(src).shape == (120, 160, 3), alt
    # per-keyframe metrics are the ones the run's summary averages
    assert np.mean([k["psnr"] for k in kj["keyframes"]]) == pytest.approx(m["psnr"], abs=1e-3)
    for k in kj["keyframes"]:
        assert f"PSNR {k['psnr']:.2f} dB" in page.text["keyframes"]
        assert 0 < k["coverage"] <= 1 and k["depth_l1_proxy"] >= 0
    # map history: one entry per keyframe offered, Gaussians counted as the map grew
    hist = kj["history"]
    assert len(hist) >= n and sum(h["mapped"] for h in hist) == n
    assert [h["keyframes"] for h in hist] == sorted(h["keyframes"] for h in hist)
    # keyframes carry their frame timestamps (those of the tracker's keyframe trajectory)
    kts = np.loadtxt(out / "trajectory_keyframes.txt", ndmin=2)[:, 0]
    for k in kj["keyframes"]:
        assert np.abs(kts - k["timestamp"]).min() < 1e-4, (k, kts)
    # configuration used, loadable back
    assert "keyframe_thresh: 2.0" in page.text["config"]
    assert load_config(out / "config.yaml").to_dict() == cfg.to_dict()


def test_rebuilt_identically_by_the_cli(full_run, tmp_path, capsys):
    out, _, _ = full_run
    assert report_main([str(out), "--out", str(tmp_path / "again")]) == 0
    assert "report.html" in capsys.readouterr().out
    for f in ("report.html", "report.png"):
        assert (tmp_path / "again" / f).read_bytes() == (out / f).read_bytes(), f
    # rebuilding in place keeps the bytes too
    before = (out / "report.html").read_bytes()
    assert report_main([str(out)]) == 0
    assert (out / "report.html").read_bytes() == before


def test_fewer_keyframes_shown_when_asked(full_run, tmp_path):
    out, _, _ = full_run
    write_report(out, out_dir=tmp_path, max_keyframes=2)
    page = Page((tmp_path / "report.html").read_text())
    assert len(page.imgs["keyframes"]) == 10 and "2 of" in page.text["keyframes"]
    kfs = json.loads((out / "renders" / "keyframes.json").read_text())["keyframes"]
    worst = min(kfs, key=lambda k: k["psnr"])["kf_id"]       # always shown
    assert f"kf {worst} input" in [alt for _, alt in page.imgs["keyframes"]]


def test_no_ground_truth_and_no_map(seq, tmp_path):
    nogt = tmp_path / "nogt"
    shutil.copytree(seq, nogt)
    (nogt / "groundtruth.txt").unlink()
    rgb = [ln.split()[1] for ln in (nogt / "rgb.txt").read_text().splitlines()
           if ln and not ln.startswith("#")]
    for name in rgb[20:22]:                                  # two black frames: tracking lost
        im = cv2.imread(str(nogt / name))
        cv2.imwrite(str(nogt / name), np.zeros_like(im))
    out = tmp_path / "out"
    run(open_dataset(nogt), load_config(None, FAST), out, mode="tracking", progress=False)
    assert not (out / "groundtruth.txt").exists()
    page = Page((out / "report.html").read_text())
    assert page.order == SECTIONS
    missing = page.text["missing"]
    assert "ground truth" in missing and "no Gaussian map" in missing
    assert page.imgs["keyframes"] == [] and "no map" in page.text["keyframes"]
    assert "no ground-truth poses" in page.text["trajectory"]
    assert len(page.imgs["trajectory"]) == 1                  # the estimate alone
    assert "ATE" not in page.text["summary"]
    assert "frame 20: tracking lost" in page.text["warnings"]     # logged by the tracker


def test_tracker_never_initialised_is_a_warning(tmp_path):
    """A static camera: no keyframe, the report says so (and has no trajectory error)."""
    d = tmp_path / "static"
    generate_sequence("builtin", 1, (160, 120), d, overwrite=True, progress=False,
                      realism="clean")
    lines = (d / "rgb.txt").read_text().splitlines()
    name = lines[-1].split()[1]
    (d / "rgb.txt").write_text("\n".join([l for l in lines if l.startswith("#")] +
                                         [f"{i * 0.1:.6f} {name}" for i in range(8)]) + "\n")
    for f in ("depth.txt", "groundtruth.txt"):
        (d / f).unlink()
    out = tmp_path / "out"
    with pytest.raises(NotInitializedError):      # the run fails, after writing its report
        run(open_dataset(d), load_config(None, FAST), out, mode="full", progress=False)
    page = Page((out / "report.html").read_text())
    assert "never initialised" in page.text["warnings"]
    assert "tracking.motion_filter_thresh" in page.text["warnings"]
    assert "no Gaussian map" in page.text["missing"]


def test_warning_recorder_collects_and_still_prints(capsys, monkeypatch):
    # as in a CLI process: no logging configured, warnings go to stderr (logging.lastResort)
    monkeypatch.setattr(logging.getLogger(), "handlers", [])
    rec = WarningRecorder()
    logging.getLogger("splat_slam_ros.tracking.tracker").warning("frame %d: tracking lost", 7)
    logging.getLogger("splat_slam_ros.tracking.tracker").info("not a warning")
    got = rec.close()
    assert got == ["warning: frame 7: tracking lost"]
    assert "tracking lost" in capsys.readouterr().err
    logging.getLogger("splat_slam_ros.tracking.tracker").warning("after close")
    assert got == ["warning: frame 7: tracking lost"]
    capsys.readouterr()
    a, b = WarningRecorder(), WarningRecorder()          # e.g. one left by a failed run
    logging.getLogger("splat_slam_ros.depth").warning("twice recorded, printed once")
    assert b.close() == a.close() == ["warning: twice recorded, printed once"]
    assert capsys.readouterr().err.count("printed once") == 1


def test_warning_tee_keeps_the_graph_warnings():
    import io
    sink = io.StringIO()
    tee = WarningTee(sink)
    text = ("[tracker]  [INFO] [1.0] [tracker]: tracker started\n"
            "[tracker]  frame 12: tracking lost (low flow confidence (0.05 valid))\n"
            "[mapper]   [WARN] [2.0] [mapper]: render request ignored: the map is empty\n"
            "[launch] warning: the loop closure stage is not available\n")
    tee.write(text)
    tee.flush()
    assert sink.getvalue() == text
    assert tee.lines == ["[tracker] frame 12: tracking lost (low flow confidence (0.05 valid))",
                         "[mapper] [WARN] [2.0] [mapper]: render request ignored: the map is "
                         "empty", "[launch] warning: the loop closure stage is not available"]


def test_cli_user_errors(tmp_path, capsys):
    assert report_main([str(tmp_path / "nope")]) == 2
    assert capsys.readouterr().err.startswith("error: run directory not found")
    assert report_main([str(tmp_path)]) == 2
    assert "is not a run directory" in capsys.readouterr().err
    (tmp_path / "metrics.json").write_text("{broken")
    assert report_main([str(tmp_path)]) == 2
    assert "not valid JSON" in capsys.readouterr().err
    (tmp_path / "metrics.json").write_text("{}")
    assert report_main([str(tmp_path), "--max-keyframes", "0"]) == 2
    assert "max_keyframes" in capsys.readouterr().err


def test_keyframe_views_against_ground_truth_depth(seq, tmp_path):
    """The files the report reads: 16-bit depths decode to the rendered/proxy depth, the
    depth L1 against ground truth equals the one against a proxy depth that is the truth."""
    from splat_slam_ros.evaluation.rendering import write_keyframe_views
    from splat_slam_ros.mapping.mapper import Mapper
    ds = open_dataset(seq)
    fr = next(iter(ds))
    mapper = Mapper(load_config(None, FAST), ds.intrinsics)
    mapper.add_keyframe(0, fr.image, fr.gt_pose, fr.gt_depth, timestamp=fr.timestamp)
    (e,) = write_keyframe_views(mapper, tmp_path, gt_depth={0: fr.gt_depth})
    assert e["depth_l1_cm"] == pytest.approx(100 * e["depth_l1_proxy"], rel=1e-4)
    assert e["timestamp"] == pytest.approx(fr.timestamp) and e["proxy_valid"] > 0.9
    doc = json.loads((tmp_path / "keyframes.json").read_text())
    scale = doc["depth_scale"]
    rgb, depth = mapper.render(fr.gt_pose, kf_id=0)
    got = cv2.imread(str(tmp_path / "kf_00000_depth.png"), cv2.IMREAD_UNCHANGED) / scale
    np.testing.assert_allclose(got, depth, atol=0.6 / scale)
    prx = cv2.imread(str(tmp_path / "kf_00000_proxy.png"), cv2.IMREAD_UNCHANGED) / scale
    np.testing.assert_allclose(prx, np.asarray(fr.gt_depth), atol=0.6 / scale)
    assert (cv2.imread(str(tmp_path / "kf_00000_input.png"))[..., ::-1] == fr.image).all()
    assert doc["history"] == [{"gaussians": doc["map"]["gaussians"], "iterations": 30,
                               "keyframes": 1, "kf_id": 0, "mapped": True, "steps": 30,
                               "steps_skipped": 0, "ms": doc["history"][0]["ms"],
                               "timestamp": fr.timestamp}]


def test_mapping_on_ground_truth_report(seq, tmp_path):
    cfg = load_config(None, {**FAST, "mapping.keyframe_every": 2})
    run(open_dataset(seq), cfg, tmp_path, mode="gt_mapping", progress=False, max_frames=4)
    page = Page((tmp_path / "report.html").read_text())
    assert "ground-truth poses" in page.text["missing"]
    assert len(page.imgs["keyframes"]) == 10 and "depth L1 in cm" in page.text["keyframes"]
