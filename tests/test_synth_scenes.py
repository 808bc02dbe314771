"""Tests of the generator's scene variants (--scene), rolling shutter and the harsh preset."""
from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
import yaml

from splat_slam_synth.cli import main as synth_main
import splat_slam_synth as synth
from splat_slam_synth.options import TEX_SIZE
from splat_slam_synth.textures import PERIODIC, procedural_texture
from splat_slam_ros.types import Intrinsics

SIZE = "96x72"


@pytest.fixture(scope="module")
def plans():
    """Every scene on the same seed and built-in trajectory (3 frames)."""
    return {name: synth.plan_sequence("builtin", 3, SIZE, seed=1, scene=name, warn=False)
            for name in synth.SCENES}


def _grad(img: np.ndarray) -> np.ndarray:
    g = img.astype(float).mean(-1)
    return np.hypot(np.diff(g, axis=1)[:-1], np.diff(g, axis=0)[:, :-1])


def _periodicity(tex: np.ndarray, dip: float = 0.3) -> float:
    """Highest normalised (circular) autocorrelation at a horizontal or vertical shift that
    follows a dip of at least ``dip`` below it: ~1 for a periodic tile, -1 when no such
    secondary peak exists (a texture without repetition)."""
    g = tex.astype(float).mean(-1)
    g -= g.mean()
    F = np.fft.fft2(g)
    ac = np.real(np.fft.ifft2(F * np.conj(F)))
    ac /= ac[0, 0]
    best = -1.0
    for line in (ac[0, :ac.shape[1] // 2], ac[:ac.shape[0] // 2, 0]):
        ok = line - np.minimum.accumulate(line) >= dip
        if ok.any():
            best = max(best, float(line[ok].max()))
    return best


def _box_dist(P, lo, hi):
    return np.linalg.norm(np.maximum(np.maximum(lo - P, 0), P - hi), axis=-1)


def _room_positions(plan):
    """Every camera position of the plan's frames (and their exposure windows), room frame."""
    t0 = max(plan.stamps[0] - 2.0 / plan.fps, plan.interpolator.t_start)
    P = plan.interpolator.positions_between(t0, plan.stamps[-1])
    T = plan.scene.T_room_world
    return P @ T[:3, :3].T + T[:3, 3]


# ------------------------------------------------------------------- every scene
def test_every_scene_builds_and_renders(plans):
    assert list(plans) == ["room", "low_texture", "tiled", "repetitive", "thin", "deep"]
    for name, plan in plans.items():
        sc = plan.scene
        assert sc.summary()["name"] == name and plan.record["scene"]["name"] == name
        cams = _room_positions(plan)
        assert np.all(cams > sc.room_lo) and np.all(cams < sc.room_hi), name
        for lo, hi in zip(sc.boxes_lo, sc.boxes_hi):   # inside the room, clear of the camera
            assert np.all(hi > lo) and np.all(lo >= sc.room_lo - 1e-9), name
            assert np.all(hi <= sc.room_hi + 1e-9), name
            assert _box_dist(cams, lo, hi).min() >= 0.5 - 1e-9, name
        diag = float(np.linalg.norm(sc.room_hi - sc.room_lo))
        for k in (0, 2):
            rgb_f, depth = synth.render_frame(sc, plan.poses[k], plan.intrinsics, as_float=True)
            assert rgb_f.shape == (72, 96, 3) and np.isfinite(rgb_f).all(), name
            assert 5 < rgb_f.mean() < 250 and rgb_f.std() > 1, name
            assert np.isfinite(depth).all() and depth.min() > 0.05 and depth.max() < diag, name
        rgb, d = plan.render(1)
        assert rgb.dtype == np.uint8 and d.shape == (72, 96)


def test_room_is_the_default_and_never_a_variant(plans, monkeypatch):
    """The default scene is the original room: no variant code runs for it, and the same
    arguments give the same geometry and textures with or without ``scene='room'``."""
    from splat_slam_synth import variants

    def boom(*a, **k):
        raise AssertionError("variant path taken for the room")

    monkeypatch.setattr(variants, "build_variant", boom)
    plan = plans["room"]
    a = synth.build_scene(plan.poses, seed=1)
    b = synth.build_scene(plan.poses, seed=1, scene="room")
    assert np.array_equal(a.boxes_lo, b.boxes_lo) and np.array_equal(a.surf_density,
                                                                      b.surf_density)
    assert a.texture_names == b.texture_names and a.n_boxes >= 8
    with pytest.raises(AssertionError, match="variant path"):
        synth.build_scene(plan.poses, seed=1, scene="thin")


def test_unknown_scene_and_textures_with_procedural_scenes(tmp_path):
    with pytest.raises(synth.SynthError, match="unknown --scene 'cave'"):
        synth.plan_sequence("builtin", 2, "32x24", scene="cave")
    (tmp_path / "tex").mkdir()
    cv2.imwrite(str(tmp_path / "tex" / "a.png"), np.full((32, 32, 3), 128, np.uint8))
    for name in ("low_texture", "repetitive"):
        with pytest.raises(synth.SynthError, match="--textures cannot be combined"):
            synth.plan_sequence("builtin", 2, "32x24", scene=name, textures=tmp_path / "tex")
    plan = synth.plan_sequence("builtin", 2, "32x24", scene="deep", textures=tmp_path / "tex",
                               warn=False)
    assert any(n.startswith("image:") for n in plan.scene.texture_names)


def test_deep_has_far_walls_and_near_boxes(plans):
    plan = plans["deep"]
    sc = plan.scene
    cams = _room_positions(plan)
    assert sc.room_hi[0] - cams[:, 0].max() >= 10.0          # far wall 10-18 m further on
    # the camera looks down (builtin path): the mean view ray still runs >= 10 m in the room
    fwd = np.einsum("ij,njk->nik", sc.T_room_world[:3, :3], plan.poses[:, :3, :3])[:, :, 2]
    fwd = fwd.mean(0) / np.linalg.norm(fwd.mean(0))
    o = cams.mean(0)
    assert fwd[2] < -0.1
    with np.errstate(divide="ignore"):
        exit_s = np.max([(sc.room_lo - o) / fwd, (sc.room_hi - o) / fwd], 0).min()
    assert exit_s >= 10.0
    near = [_box_dist(cams, lo, hi).min() for lo, hi in zip(sc.boxes_lo, sc.boxes_hi)]
    assert sc.info["near_boxes"] >= 1 and all(0.5 <= x <= 1.5 for x in near[:sc.info["near_boxes"]])
    bare = sc.without_boxes()
    far = near_box = 0.0
    for k in range(3):
        _, depth = synth.render_frame(sc, plan.poses[k], plan.intrinsics)
        _, d_room = synth.render_frame(bare, plan.poses[k], plan.intrinsics)
        far = max(far, float(depth.max()))
        on_box = depth < d_room - 1e-4
        if on_box.any():
            near_box = min(near_box or np.inf, float(depth[on_box].min()))
    assert far > 8.0 and 0 < near_box < 2.0
    assert sc.info["far_wall_m"] >= 10.0


def test_thin_has_thin_structures_clear_of_the_path(plans):
    sc = plans["thin"].scene
    size = sc.boxes_hi - sc.boxes_lo
    thin = size.min(1) < 0.1
    assert thin.sum() >= 4 and sum(sc.info["thin_structures"].values()) >= 4
    # thin in two dimensions (poles, legs) and boards (thin in height only)
    assert np.any(np.sort(size[thin], 1)[:, 1] < 0.1)
    cams = _room_positions(plans["thin"])
    assert min(_box_dist(cams, lo, hi).min() for lo, hi in zip(sc.boxes_lo[thin],
                                                                 sc.boxes_hi[thin])) >= 0.5
    # they are in view: removing the boxes changes the depth of some pixels
    plan = plans["thin"]
    _, d = synth.render_frame(sc, plan.poses[1], plan.intrinsics)
    _, d0 = synth.render_frame(sc.without_boxes(), plan.poses[1], plan.intrinsics)
    assert (d < d0 - 1e-4).mean() > 0.01


def test_low_texture_has_far_less_gradient_than_room():
    for seed in (0, 1):
        g = {}
        for name in ("room", "low_texture"):
            plan = synth.plan_sequence("builtin", 3, SIZE, seed=seed, scene=name, warn=False)
            g[name] = _grad(plan.render(2)[0])
        assert (g["low_texture"] ** 2).mean() < 0.5 * (g["room"] ** 2).mean(), seed
        assert np.median(g["low_texture"]) < 0.3 * np.median(g["room"]), seed


def test_repetitive_textures_are_periodic(plans):
    # the measure: 1 for the periodic kinds, -1 for noise-like ones
    for kind in PERIODIC:
        assert _periodicity(procedural_texture(kind, 5, 3)) > 0.9, kind
    for kind in ("plaster", "clutter", "granite", "paint"):
        assert _periodicity(procedural_texture(kind, 5, 3)) < 0.3, kind
    sc = plans["repetitive"].scene
    walls = [sc.textures[int(i)] for i in sc.surf_tex[:4]]
    assert all(_periodicity(t) > 0.9 for t in walls)
    all_faces = [_periodicity(sc.textures[int(i)]) for i in sc.surf_tex]
    assert np.mean(np.array(all_faces) > 0.9) > 0.6                 # most surfaces
    room = plans["room"].scene
    assert np.mean([_periodicity(room.textures[int(i)]) > 0.9 for i in room.surf_tex]) < 0.6


def test_tiled_mixes_stretched_and_small_tiles(plans):
    room, tiled = plans["room"].scene, plans["tiled"].scene
    tile_m = TEX_SIZE / tiled.surf_density                 # metres per texture tile
    room_m = TEX_SIZE / room.surf_density
    assert room_m.min() >= 0.5 and room_m.max() <= 2.5
    walls = tile_m[:6]
    assert (walls >= 6.0).sum() >= 2 and (walls <= 0.3).sum() >= 2
    assert tiled.info["stretched_surfaces"] >= 3 and tiled.info["small_tile_surfaces"] >= 3
    # same geometry and textures as the room of that seed, only the texel densities differ
    assert np.array_equal(tiled.boxes_lo, room.boxes_lo)
    assert tiled.texture_names == room.texture_names


# ----------------------------------------------------------------- rolling shutter
def _pan(duration=3.0, rate=200.0, omega=1.5):
    """A pure yaw pan at a fixed position, looking horizontally (world z up)."""
    t = np.arange(0, duration, 1 / rate)
    P = np.tile(np.eye(4), (len(t), 1, 1))
    for i, a in enumerate(omega * t):
        z = np.array([np.cos(a), np.sin(a), 0.0])           # camera forward
        x = np.array([np.sin(a), -np.cos(a), 0.0])          # camera right
        P[i, :3, :3] = np.stack([x, np.cross(z, x), z], 1)
        P[i, :3, 3] = [0.0, 0.0, 1.4]
    return t, P


def _shift(a, b) -> float:
    (dx, dy), _ = cv2.phaseCorrelate(a.astype(np.float64).mean(-1), b.astype(np.float64).mean(-1))
    return dx


def test_rolling_shutter_zero_is_global_shutter():
    base = dict(trajectory="builtin", frames=3, size=SIZE, seed=2, warn=False)
    for mb in (1, 3):
        a = synth.plan_sequence(**base, motion_blur=mb, rolling_shutter_ms=0.0)
        b = synth.plan_sequence(**base, motion_blur=mb)
        ra, da = a.render(2)
        rb, db = b.render(2)
        assert np.array_equal(ra, rb) and np.array_equal(da, db)


@pytest.mark.parametrize("model,dist", [("plumb_bob", [-0.2, 0.05, 0.001, -0.001, 0.0]),
                                        ("equidistant", [0.05, -0.01, 0.0, 0.0])])
def test_rolling_shutter_of_a_still_camera_is_global_shutter(model, dist):
    """Row bands are rendered through cropped intrinsics: exact, also with lens distortion."""
    t = np.arange(0, 3, 0.01)
    P = np.tile(synth.builtin_trajectory(5)[1][100], (len(t), 1, 1))
    K = Intrinsics(70, 70, 47.5, 35.5, 96, 72, model, dist)
    gs = synth.plan_sequence((t, P), 2, None, intrinsics=K, start=0.5, warn=False)
    rs = replace(gs, realism=synth.resolve_realism(rolling_shutter_ms=20).validate(30))
    assert np.array_equal(gs.render(1)[0], rs.render(1)[0])


def test_rolling_shutter_skews_a_pan():
    H, rs = 96, 30.0
    gs = synth.plan_sequence(_pan(), 3, "128x96", seed=3, start=0.5, warn=False)
    rsp = replace(gs, realism=synth.resolve_realism(rolling_shutter_ms=rs).validate(gs.fps))
    bands = synth.rolling_shutter_bands(H, rs)
    assert bands[0][0] == 0 and bands[-1][1] == H and len(bands) == 60
    assert bands[0][2] == pytest.approx(rs * 1e-3 * (1 - 0.5 * (bands[0][1] - 1) / (H - 1)))
    assert bands[-1][2] < 1e-3 * rs / 50                     # bottom row: at the stamp
    img_g, d_g = gs.render(2)
    img_r, d_r = rsp.render(2)
    assert np.array_equal(d_g, d_r)                          # depth: the stamp's pose
    # top band = a global-shutter view at the band's (earlier) readout time
    r0, r1, dt = bands[0]
    early = synth.render_frame(gs.scene, gs.interpolator([gs.stamps[2] - dt])[0], gs.intrinsics)[0]
    assert np.abs(img_r[r0:r1].astype(int) - early[r0:r1]).max() <= 1
    # the top rows are shifted against the global-shutter frame, the bottom rows barely
    top, bot = slice(0, 16), slice(H - 16, H)
    s_top, s_bot = _shift(img_g[top], img_r[top]), _shift(img_g[bot], img_r[bot])
    f = gs.intrinsics.fx
    assert abs(s_top) > 0.7 * f * 1.5 * rs * 1e-3 * (1 - 7.5 / (H - 1))   # pan 1.5 rad/s
    assert abs(s_bot) < 0.15 * abs(s_top)
    # each row strip matches the global-shutter view at its own readout time best
    taus = np.arange(0.0, 36.0, 1.0)
    views = [synth.render_frame(gs.scene, T, gs.intrinsics)[0].astype(float)
             for T in gs.interpolator(gs.stamps[2] - taus * 1e-3)]
    for rows, centre in ((top, 7.5), (slice(40, 56), 47.5), (bot, H - 8.5)):
        err = [np.abs(v[rows] - img_r[rows]).mean() for v in views]
        assert abs(taus[int(np.argmin(err))] - rs * (1 - centre / (H - 1))) <= 1.5, rows
        assert np.argmin([np.abs(v[rows] - img_g[rows]).mean() for v in views]) == 0
    # with motion blur on top: blurred and still skewed
    both = replace(gs, realism=synth.resolve_realism(rolling_shutter_ms=rs, motion_blur=3,
                                                     exposure_ms=10).validate(gs.fps))
    img_b = both.render(2)[0]
    assert np.isfinite(img_b).all() and not np.array_equal(img_b, img_r)
    assert _grad(img_b).mean() < _grad(img_r).mean()


def test_rolling_shutter_validation_and_harsh_preset():
    with pytest.raises(synth.SynthError, match="--rolling-shutter must be in"):
        synth.resolve_realism(rolling_shutter_ms=-1.0).validate(30.0)
    with pytest.raises(synth.SynthError, match="frame period"):
        synth.resolve_realism(rolling_shutter_ms=40.0).validate(30.0)
    assert synth.resolve_realism(rolling_shutter_ms=33.0).validate(30.0).rolling_shutter_ms == 33
    h = synth.resolve_realism("harsh").validate(30.0)
    r = synth.resolve_realism("realistic")
    assert h.motion_blur > r.motion_blur and h.exposure_ms > r.exposure_ms
    assert h.auto_exposure > r.auto_exposure and h.vignetting > r.vignetting
    assert h.noise > r.noise and 0 < h.jpeg < r.jpeg and h.rolling_shutter_ms > 0
    # at 60 fps the preset's 20 ms do not fit: the message names the preset; options override
    with pytest.raises(synth.SynthError, match="set by --realism harsh"):
        synth.resolve_realism("harsh").validate(60.0, "harsh")
    o = synth.resolve_realism("harsh", exposure_ms=10.0, rolling_shutter_ms=0.0).validate(60.0)
    assert o.rolling_shutter_ms == 0 and o.noise == 4.0


# ---------------------------------------------------------------------------- CLI
def _cli(capsys, tmp_path, *args):
    rc = synth_main(["--frames", "2", "--size", "32x24", "--out", str(tmp_path / "o"), "--quiet",
                     *args])
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("args", [["--scene", "cave"], ["--scene", ""],
                                  ["--rolling-shutter", "-1"], ["--rolling-shutter", "40"],
                                  ["--rolling-shutter", "nan"],
                                  ["--fps", "60", "--realism", "harsh"]])
def test_cli_bad_scene_or_rolling_shutter(tmp_path, capsys, args):
    rc, err = _cli(capsys, tmp_path, *args)
    assert rc == 2 and err.startswith("error:") and err.count("\n") == 1, err
    assert ("--scene" in err) if args[0] == "--scene" else ("--" in err)
    assert not (tmp_path / "o" / "rgb").exists()


def test_cli_scene_and_harsh_are_recorded(tmp_path, capsys):
    rc, err = _cli(capsys, tmp_path, "--scene", "deep", "--realism", "harsh")
    assert rc == 0, err
    gen = yaml.safe_load((tmp_path / "o" / "intrinsics.yaml").read_text())["generation"]
    assert gen["scene"]["name"] == "deep" and gen["realism"] == "harsh"
    assert gen["realism_options"]["rolling_shutter_ms"] == 20.0
    assert len(list((tmp_path / "o" / "rgb").iterdir())) == 2


def test_cli_help_lists_scenes_and_options(capsys):
    with pytest.raises(SystemExit):
        synth_main(["--help"])
    text = capsys.readouterr().out
    for word in ("--scene", "--rolling-shutter", "harsh", *synth.SCENES):
        assert word in text, word
