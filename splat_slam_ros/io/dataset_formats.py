"""Readers of the RGB-D dataset layouts (TUM, Replica, ScanNet, EuRoC, pose folder, image
folder) -> :class:`~splat_slam_ros.io.dataset_base.FileDataset`."""
from __future__ import annotations

from pathlib import Path
from typing import Tuple

import numpy as np
import yaml

from splat_slam_ros.geometry import pose_from_tq
from splat_slam_ros.io.dataset_base import (ASSOC_TOL, DEFAULT_FPS, IMAGE_EXTS, REPLICA_DEFAULT,
                                            DatasetError, FileDataset, copy_intrinsics, FrameEntry,
                                            list_images, numeric_stem, read_gt_trajectory,
                                            read_stamp_list, tum_default_for, associate,
                                            interpolate_poses, load_intrinsics, natural_key,
                                            read_image)
from splat_slam_ros.types import Intrinsics


def _open_tum(root: Path, K, extra, **kw) -> FileDataset:
    rgb_txt = root / "rgb.txt"
    if not rgb_txt.is_file():
        raise DatasetError(f"{root}: TUM layout needs rgb.txt (timestamp filename rows)")
    notes = []
    local = root / "intrinsics.yaml"
    if K is None and local.is_file():
        K, extra = load_intrinsics(local)
    if K is None:
        d = tum_default_for(root)
        if d is None:
            raise DatasetError(f"{root}: no intrinsics: add intrinsics.yaml, pass --intrinsics "
                               "FILE, or name the folder after the TUM camera (fr1/fr2/fr3)")
        key, K = d
        notes.append(f"intrinsics: TUM {key} defaults chosen from the folder name")
    rgb = read_stamp_list(rgb_txt)
    entries = [FrameEntry(t, root / f) for t, f in rgb]
    depth_txt = root / "depth.txt"
    scale = None
    if depth_txt.is_file():
        scale = float(kw.pop("depth_scale", None) or extra.get("depth_scale", 5000.0))
        dep = read_stamp_list(depth_txt)
        idx = associate([t for t, _ in rgb], [t for t, _ in dep])
        if all(i is None for i in idx):
            raise DatasetError(f"{root}: no depth.txt stamp within {ASSOC_TOL} s of any rgb.txt "
                               f"stamp (rgb {rgb[0][0]:.3f}..{rgb[-1][0]:.3f}, depth "
                               f"{dep[0][0]:.3f}..{dep[-1][0]:.3f})")
        for e, i in zip(entries, idx):
            e.depth = None if i is None else root / dep[i][1]
        miss = sum(i is None for i in idx)
        if miss:
            notes.append(f"{miss} rgb frames have no depth within {ASSOC_TOL} s")
    else:
        kw.pop("depth_scale", None)
    gt_txt = root / "groundtruth.txt"
    if gt_txt.is_file():
        ts, P = read_gt_trajectory(gt_txt, "tum")
        poses = interpolate_poses(ts, P, [e.timestamp for e in entries])
        if all(p is None for p in poses):
            raise DatasetError(f"{root}: no groundtruth.txt sample within {ASSOC_TOL} s of any "
                               f"rgb.txt stamp (rgb {rgb[0][0]:.3f}..{rgb[-1][0]:.3f}, "
                               f"groundtruth {ts[0]:.3f}..{ts[-1]:.3f})")
        for e, p in zip(entries, poses):
            e.gt_pose = p
    return FileDataset(root.name, "tum", root, K, entries, depth_scale=scale, notes=notes, **kw)


def _open_replica(root: Path, K, extra, fps=None, **kw) -> FileDataset:
    res = root / "results"
    if not res.is_dir():
        raise DatasetError(f"{root}: Replica layout needs results/frame%06d.jpg")
    imgs = sorted(res.glob("frame*.jpg"), key=lambda p: natural_key(p.name)) or \
        sorted(res.glob("frame*.png"), key=lambda p: natural_key(p.name))
    if not imgs:
        raise DatasetError(f"{res}: no frame*.jpg images")
    depths = sorted(res.glob("depth*.png"), key=lambda p: natural_key(p.name))
    if depths and len(depths) != len(imgs):
        raise DatasetError(f"{res}: {len(imgs)} colour frames but {len(depths)} depth images")
    notes = []
    if K is None:
        for cp in (root / "cam_params.json", root.parent / "cam_params.json"):
            if cp.is_file():
                K, extra = load_intrinsics(cp)
                break
    if K is None:
        h, w = read_image(imgs[0], keep_mono=True).shape[:2]
        if (w, h) != (REPLICA_DEFAULT.width, REPLICA_DEFAULT.height):
            raise DatasetError(f"{root}: no intrinsics (no cam_params.json here or in the parent, "
                               f"no --intrinsics) and the images are {w}x{h}, not Replica's "
                               "1200x680")
        K = copy_intrinsics(REPLICA_DEFAULT)
        notes.append("intrinsics: Replica defaults (600, 600, 599.5, 339.5)")
    scale = float(kw.pop("depth_scale", None) or extra.get("depth_scale", 6553.5))
    fps = fps or DEFAULT_FPS
    entries = [FrameEntry(i / fps, p, depths[i] if depths else None) for i, p in enumerate(imgs)]
    traj = root / "traj.txt"
    if traj.is_file():
        rows = _numeric_matrix_rows(traj, 16)
        if len(rows) != len(imgs):
            raise DatasetError(f"{traj} has {len(rows)} poses but results/ has {len(imgs)} frames")
        for e, r in zip(entries, rows):
            e.gt_pose = r.reshape(4, 4)
    return FileDataset(root.name, "replica", root, K, entries,
                       depth_scale=scale if depths else None, notes=notes, **kw)


def _numeric_matrix_rows(path: Path, ncol: int) -> np.ndarray:
    try:
        a = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise DatasetError(f"{path}: not a numeric table ({e})") from None
    if a.size == 0 or a.shape[1] != ncol:
        raise DatasetError(f"{path}: expected {ncol} numbers per row, found "
                           f"{a.shape[1] if a.size else 0}")
    return a


def _open_scannet(root: Path, K, extra, fps=None, **kw) -> FileDataset:
    cdir = root / "color"
    if not cdir.is_dir():
        raise DatasetError(f"{root}: ScanNet layout needs color/N.jpg")
    imgs = [p for p in list_images(cdir) if p.stem.isdigit()]
    imgs.sort(key=lambda p: int(p.stem))
    if not imgs:
        raise DatasetError(f"{cdir}: no N.jpg colour images")
    notes = []
    if K is None:
        kf = root / "intrinsic" / "intrinsic_color.txt"
        if not kf.is_file():
            raise DatasetError(f"{root}: no intrinsics: expected intrinsic/intrinsic_color.txt "
                               "or --intrinsics FILE")
        M = _numeric_matrix_rows(kf, 4)
        h, w = read_image(imgs[0], keep_mono=True).shape[:2]
        K = Intrinsics(float(M[0, 0]), float(M[1, 1]), float(M[0, 2]), float(M[1, 2]), w, h)
    ddir = root / "depth"
    depths = None
    if ddir.is_dir():
        depths = {p.stem: p for p in ddir.glob("*.png")}
        missing = [p.stem for p in imgs if p.stem not in depths]
        if missing:
            raise DatasetError(f"{root}: {len(imgs)} colour frames but {len(depths)} depth images "
                               f"(no depth/{missing[0]}.png)")
        notes.append("depth resized to the colour size (nearest neighbour)")
    scale = float(kw.pop("depth_scale", None) or extra.get("depth_scale", 1000.0))
    fps = fps or DEFAULT_FPS
    entries = [FrameEntry(i / fps, p, depths[p.stem] if depths else None) for i, p in enumerate(imgs)]
    pdir = root / "pose"
    if pdir.is_dir():
        bad = 0
        for e, p in zip(entries, imgs):
            f = pdir / f"{p.stem}.txt"
            if not f.is_file():
                raise DatasetError(f"{pdir}: missing pose file {f.name}")
            try:
                T = np.loadtxt(f, dtype=np.float64)
            except ValueError as err:
                raise DatasetError(f"{f}: not a 4x4 matrix ({err})") from None
            if T.shape != (4, 4):
                raise DatasetError(f"{f}: expected a 4x4 matrix, got shape {T.shape}")
            if np.all(np.isfinite(T)):
                e.gt_pose = T
            else:
                bad += 1
        if bad:
            notes.append(f"{bad} frames have invalid (inf/nan) ground-truth poses: gt_pose=None")
    return FileDataset(root.name, "scannet", root, K, entries,
                       depth_scale=scale if depths else None, resize_depth=True,
                       notes=notes, **kw)


def _euroc_root(path: Path) -> Tuple[Path, Path]:
    """(sequence folder, mav0 folder) from either of them."""
    if (path / "mav0").is_dir():
        return path, path / "mav0"
    if path.name == "mav0" or (path / "cam0" / "data.csv").is_file():
        return path.parent, path
    raise DatasetError(f"{path}: EuRoC layout needs mav0/cam0/data.csv")


def _read_euroc_sensor(p: Path) -> Tuple[Intrinsics, np.ndarray]:
    if not p.is_file():
        raise DatasetError(f"EuRoC camera calibration not found: {p}")
    text = "\n".join(l for l in p.read_text().splitlines() if not l.startswith("%"))
    try:
        d = yaml.safe_load(text)
        fu, fv, cu, cv = [float(x) for x in d["intrinsics"]]
        w, h = [int(x) for x in d["resolution"]]
        model = str(d.get("distortion_model", "")).lower()
        coeffs = [float(x) for x in d.get("distortion_coefficients") or []]
        T_BS = np.asarray(d["T_BS"]["data"], dtype=np.float64).reshape(4, 4)
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{p}: not a EuRoC sensor.yaml (need intrinsics [fu fv cu cv], "
                           f"resolution, T_BS) ({e})") from None
    if model in ("radial-tangential", "radtan", "plumb_bob", ""):
        dm, coeffs = "plumb_bob", (coeffs + [0.0] * 5)[:5] if coeffs else []
    elif model in ("equidistant", "fisheye"):
        dm = "equidistant"
    else:
        raise DatasetError(f"{p}: unsupported distortion_model {model!r} "
                           "(radial-tangential or equidistant)")
    return Intrinsics(fu, fv, cu, cv, w, h, dm, coeffs), T_BS


def _open_euroc(root: Path, K, extra, camera: str = "cam0", **kw) -> FileDataset:
    seq, mav0 = _euroc_root(root)
    cam = mav0 / camera
    csv = cam / "data.csv"
    if not csv.is_file():
        raise DatasetError(f"{mav0}: EuRoC layout needs {camera}/data.csv")
    K_file, T_BS = _read_euroc_sensor(cam / "sensor.yaml")
    K = K or K_file
    kw.pop("depth_scale", None)
    entries = []
    for n, line in enumerate(csv.read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            ns_str, fname = [x.strip() for x in s.split(",")[:2]]
            ns = int(ns_str)
        except ValueError:
            raise DatasetError(f"{csv}:{n}: expected 'timestamp_ns,filename', got {s[:80]!r}") \
                from None
        entries.append(FrameEntry(ns / 10**9, cam / "data" / fname))   # exact int -> float
    notes = []
    gt_csv = mav0 / "state_groundtruth_estimate0" / "data.csv"
    gt_tum = sorted(seq.glob("groundtruth*.txt"))
    gt_file = gt_csv if gt_csv.is_file() else (gt_tum[0] if gt_tum else None)
    if gt_file is not None:
        ts, P = read_gt_trajectory(gt_file)
        poses = interpolate_poses(ts, P, [e.timestamp for e in entries])
        if all(p is None for p in poses):
            raise DatasetError(f"{gt_file}: no ground-truth sample within {ASSOC_TOL} s of any "
                               f"image stamp (images {entries[0].timestamp:.3f}.."
                               f"{entries[-1].timestamp:.3f}, ground truth {ts[0]:.3f}.."
                               f"{ts[-1]:.3f})")
        for e, p in zip(entries, poses):
            e.gt_pose = None if p is None else p @ T_BS   # body->world @ camera->body
        notes.append(f"ground truth: {gt_file.name} body poses x T_BS -> camera poses")
    name = seq.name if seq.name else mav0.name
    return FileDataset(name, "euroc", seq, K, entries, notes=notes, **kw)


def _folder_intrinsics(root: Path, K, extra):
    """The explicit intrinsics, else ``root/intrinsics.yaml``; DatasetError when neither."""
    if K is None and (root / "intrinsics.yaml").is_file():
        K, extra = load_intrinsics(root / "intrinsics.yaml")
    if K is None:
        raise DatasetError(f"{root}: no intrinsics: pass --intrinsics FILE (or put "
                           "intrinsics.yaml in the folder)")
    return K, extra


def _open_posefolder(root: Path, K, extra, fps=None, **kw) -> FileDataset:
    cdir, pose_txt = root / "color", root / "pose.txt"
    if not cdir.is_dir() or not pose_txt.is_file():
        raise DatasetError(f"{root}: posefolder layout needs color/N.png and pose.txt")
    imgs = [p for p in list_images(cdir)]
    if not imgs:
        raise DatasetError(f"{cdir}: no images")
    K, extra = _folder_intrinsics(root, K, extra)
    a = _numeric_matrix_rows_any(pose_txt, (7, 8))
    if len(a) != len(imgs):
        raise DatasetError(f"{pose_txt} has {len(a)} poses but color/ has {len(imgs)} images")
    ddir = root / "depth"
    depths = None
    if ddir.is_dir():
        dl = list_images(ddir)
        by_stem = {p.stem: p for p in dl}
        missing = [p.stem for p in imgs if p.stem not in by_stem]
        if missing:
            raise DatasetError(f"{root}: {len(imgs)} colour images but {len(dl)} depth images "
                               f"(no depth image for {missing[0]})")
        depths = [by_stem[p.stem] for p in imgs]
    scale = float(kw.pop("depth_scale", None) or extra.get("depth_scale", 5000.0))
    fps = fps or DEFAULT_FPS
    stamps = a[:, 0] if a.shape[1] == 8 else np.arange(len(a)) / fps
    P = pose_from_tq(a[:, -7:]).numpy()
    entries = [FrameEntry(float(stamps[i]), p, depths[i] if depths else None, P[i])
               for i, p in enumerate(imgs)]
    return FileDataset(root.name, "posefolder", root, K, entries,
                       depth_scale=scale if depths else None, **kw)


def _numeric_matrix_rows_any(path: Path, ncols) -> np.ndarray:
    try:
        a = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise DatasetError(f"{path}: not a numeric table ({e})") from None
    if a.size == 0 or a.shape[1] not in ncols:
        raise DatasetError(f"{path}: expected rows of 'tx ty tz qx qy qz qw' (7 numbers, or 8 "
                           f"with a leading timestamp), found {a.shape[1] if a.size else 0}")
    return a


def _open_folder(root: Path, K, extra, fps=None, **kw) -> FileDataset:
    imgs = list_images(root)
    if not imgs:
        raise DatasetError(f"{root}: no images ({', '.join(IMAGE_EXTS)}) in the folder")
    K, extra = _folder_intrinsics(root, K, extra)
    kw.pop("depth_scale", None)
    stamps = [numeric_stem(p) for p in imgs]
    notes = []
    if fps is None and all(s is not None for s in stamps) and len(set(stamps)) == len(stamps):
        order = np.argsort(stamps, kind="stable")
        imgs, stamps = [imgs[i] for i in order], [stamps[i] for i in order]
        notes.append("timestamps from the file names")
    else:
        fps = fps or DEFAULT_FPS
        stamps = [i / fps for i in range(len(imgs))]
        notes.append(f"timestamps: index / {fps:g} fps")
    entries = [FrameEntry(t, p) for t, p in zip(stamps, imgs)]
    return FileDataset(root.name, "folder", root, K, entries, notes=notes, **kw)
