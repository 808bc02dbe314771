"""ORB-SLAM3 (monocular) as a peer beside us in ``bench_generalise.py --orbslam3``.

ORB-SLAM3 (https://github.com/UZ-SLAMLab/ORB_SLAM3, GPL-3.0) runs through the
``pyorbslam3`` wheel from PyPI, installed into a scratch virtual environment under the
benchmark's data folder, never into the project's (:func:`peer_env`). Each sequence is one
child process of that environment (this file, run as a script there): the frames in order
at their timestamps, headless (``bench_generalise.run_orbslam3`` measures it as it measures
DSO); its final trajectory (``SaveTrajectoryEuRoC``: every tracked
frame, after its local and global BA) is read as the posed frames.

ORB-SLAM3 needs a DBoW2 vocabulary of ORB descriptors. Its own ``ORBvoc.txt`` (139 MB) is
downloaded from GitHub, which a machine without internet access cannot reach; pass it with
``--orb-vocab FILE`` when you have it. Otherwise :func:`train_vocabulary` builds one the same
way (hierarchical k-majority clustering of ORB descriptors, TF-IDF weights, DBoW2's text
format) from the real photos of ``../shared/data``. Those photos also texture the photo
scenes of the suite, so such a vocabulary favours the peer there, never us.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Iterable, List

import numpy as np

WHEEL = "pyorbslam3==0.1.1"
VOCAB_K, VOCAB_L = 10, 5          # branching factor and depth: up to 10^5 words (ORB-SLAM3
                                  # groups features at 4 levels above the words: a 4-level
                                  # tree put them all in one group and it lost track)
N_FEATURES = 1000                 # ORB features a frame (ORB-SLAM3's TUM / EuRoC settings)


# ------------------------------------------------------------------ vocabulary (main env)
def orb_descriptors(images: Iterable[Path], n_features: int = 2000) -> List[np.ndarray]:
    """ORB descriptors (N x 32 uint8) of each image, ORB-SLAM3's pyramid (8 levels, 1.2)."""
    import cv2
    orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=1.2, nlevels=8, fastThreshold=20)
    out = []
    for p in images:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ValueError(f"{p}: not an image")
        _, d = orb.detectAndCompute(img, None)
        if d is not None and len(d):
            out.append(d)
    return out


def _hamming(bits: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Hamming distances (N x K) between unpacked bit rows ``bits`` (N x 256, 0/1 float32)
    and ``centres`` (K x 256): |a| + |b| - 2 a.b."""
    return bits.sum(1, keepdims=True) + centres.sum(1)[None] - 2.0 * bits @ centres.T


def _k_majority(bits: np.ndarray, k: int, rng, iters: int = 8) -> np.ndarray:
    """Cluster labels of ``bits`` (N x 256) into k clusters: k-means++ seeds under the
    Hamming distance, then bitwise-majority centres (DBoW2's k-medians for binary words)."""
    n = len(bits)
    centres = [bits[int(rng.integers(n))]]
    d = _hamming(bits, np.stack(centres))[:, 0]
    for _ in range(1, k):
        p = d ** 2
        s = p.sum()
        i = int(rng.choice(n, p=p / s)) if s > 0 else int(rng.integers(n))
        centres.append(bits[i])
        d = np.minimum(d, _hamming(bits, bits[i:i + 1])[:, 0])
    C = np.stack(centres)
    labels = np.zeros(n, dtype=np.int64)
    for it in range(iters):
        new = _hamming(bits, C).argmin(1)
        if it and np.array_equal(new, labels):
            break
        labels = new
        for j in range(k):
            m = bits[labels == j]
            if len(m):
                C[j] = (m.mean(0) > 0.5).astype(np.float32)
    return labels


def train_vocabulary(descs: List[np.ndarray], out: Path, k: int = VOCAB_K, L: int = VOCAB_L,
                     seed: int = 0) -> int:
    """A DBoW2 vocabulary (ORB-SLAM3's text format: ``k L scoring weighting``, then one line
    a node, breadth first: parent, leaf flag, 32 descriptor bytes, weight) of the
    descriptors ``descs`` (one array an image): L1-norm scoring, TF-IDF weights (a word's
    weight: log(images / images that have it)). Returns the number of words."""
    rng = np.random.default_rng(seed)
    allb = np.concatenate(descs)
    img_of = np.concatenate([np.full(len(d), i) for i, d in enumerate(descs)])
    bits = np.unpackbits(allb, axis=1).astype(np.float32)
    lines: List[str] = []
    words = 0
    # queue of (node id, member indices, level); node 0 is the root (not written)
    queue = [(0, np.arange(len(bits)), 0)]
    next_id = 1
    while queue:
        nid, idx, level = queue.pop(0)
        if len(idx) <= k:
            groups = [idx[i:i + 1] for i in range(len(idx))]
        else:
            lab = _k_majority(bits[idx], k, rng)
            groups = [idx[lab == j] for j in range(k) if np.any(lab == j)]
        for g in groups:
            centre = np.packbits((bits[g].mean(0) > 0.5).astype(np.uint8))
            leaf = level + 1 >= L or len(g) <= 1
            if leaf:
                n_img = len(np.unique(img_of[g]))
                weight = float(np.log(len(descs) / n_img))
                words += 1
            else:
                weight = 0.0
            lines.append(f"{nid} {int(leaf)} " + " ".join(str(int(b)) for b in centre) +
                         f" {weight:.6f}")
            if not leaf:
                queue.append((next_id, g, level + 1))
            next_id += 1
    out.parent.mkdir(parents=True, exist_ok=True)
    # DBoW2 reads nodes until end of file: no newline after the last one
    out.write_text(f"{k} {L} 0 0\n" + "\n".join(lines))
    return words


def settings_yaml(fx: float, fy: float, cx: float, cy: float, w: int, h: int, fps: float,
                  dist=(0.0, 0.0, 0.0, 0.0)) -> str:
    """ORB-SLAM3's monocular settings: pinhole with radial-tangential ``dist`` (k1 k2 p1
    p2; the renders have none, the real EuRoC clip has), its TUM / EuRoC examples' ORB
    parameters."""
    k1, k2, p1, p2 = (list(dist) + [0.0] * 4)[:4]
    return f"""%YAML:1.0
Camera.type: "PinHole"
Camera.fx: {fx}
Camera.fy: {fy}
Camera.cx: {cx}
Camera.cy: {cy}
Camera.k1: {k1}
Camera.k2: {k2}
Camera.p1: {p1}
Camera.p2: {p2}
Camera.width: {w}
Camera.height: {h}
Camera.fps: {fps}
Camera.RGB: 1
ORBextractor.nFeatures: {N_FEATURES}
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7
Viewer.KeyFrameSize: 0.05
Viewer.KeyFrameLineWidth: 1.0
Viewer.GraphLineWidth: 0.9
Viewer.PointSize: 2.0
Viewer.CameraSize: 0.08
Viewer.CameraLineWidth: 3.0
Viewer.ViewpointX: 0.0
Viewer.ViewpointY: -0.7
Viewer.ViewpointZ: -1.8
Viewer.ViewpointF: 500.0
"""


# ------------------------------------------------------------------ scratch environment
def peer_env(data_dir: Path) -> Path:
    """The scratch virtual environment's python with ``pyorbslam3`` (and headless OpenCV,
    numpy), created on first use under ``data_dir``; exits with a clear error when pip
    cannot install the wheel (it is x86-64 Linux only)."""
    venv = data_dir / "orbslam3_env"
    py = venv / "bin" / "python"
    probe = [str(py), "-c", "import pyorbslam3, cv2"]
    if py.is_file() and subprocess.run(probe, capture_output=True).returncode == 0:
        return py
    print(f"installing {WHEEL} into {venv} (a scratch environment, once)", flush=True)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    r = subprocess.run([str(py), "-m", "pip", "install", "-q", WHEEL, "numpy",
                        "opencv-python-headless"], capture_output=True, text=True)
    if r.returncode != 0 or subprocess.run(probe, capture_output=True).returncode != 0:
        sys.exit(f"error: cannot install {WHEEL} into {venv}:\n{r.stderr[-2000:]}")
    return py


def write_job(work: Path, vocab: Path, settings: str, images: List[Path],
              stamps: List[float]) -> Path:
    """The child's input in ``work``: settings.yaml and job.json (frames in order, their
    stamps, where to write the trajectory: ``work``/trajectory.txt)."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "settings.yaml").write_text(settings)
    job = dict(vocab=str(vocab), settings=str(work / "settings.yaml"),
               images=[str(p) for p in images], stamps=[float(t) for t in stamps],
               out=str(work / "trajectory.txt"))
    (work / "job.json").write_text(json.dumps(job))
    return work / "job.json"


def read_trajectory(path: Path):
    """``SaveTrajectoryEuRoC``'s file (stamp in ns, tx ty tz qx qy qz qw per line): stamps
    (s) and 4x4 camera-to-world poses; empty when ORB-SLAM3 wrote nothing."""
    from scipy.spatial.transform import Rotation
    if not path.is_file():
        return np.zeros(0), np.zeros((0, 4, 4))
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip()
            and not ln.startswith("#")]
    if not rows:
        return np.zeros(0), np.zeros((0, 4, 4))
    a = np.array(rows, dtype=np.float64)
    ts = a[:, 0] / 1e9
    P = np.tile(np.eye(4), (len(a), 1, 1))
    P[:, :3, :3] = Rotation.from_quat(a[:, 4:8]).as_matrix()
    P[:, :3, 3] = a[:, 1:4]
    return ts, P


# ------------------------------------------------------------------ child (scratch env)
def _child(job_file: str) -> int:
    import cv2
    import pyorbslam3 as pos
    job = json.loads(Path(job_file).read_text())
    slam = pos.Slam(job["vocab"], job["settings"], pos.Sensor.MONOCULAR, use_viewer=False)
    states = {}
    for p, t in zip(job["images"], job["stamps"]):
        img = cv2.imread(p, cv2.IMREAD_COLOR)
        r = slam.track_monocular(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), t)
        state = str(r.state).split(".")[-1]
        states[state] = states.get(state, 0) + 1
    slam.shutdown()
    slam.save_trajectory_euroc(job["out"])
    print(json.dumps({"states": states}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1]))
