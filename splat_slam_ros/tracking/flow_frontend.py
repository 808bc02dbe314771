"""Flow front end: image preparation and dense optical flow at the BA resolution.

The paper predicts flow and per-pixel confidence with a learned recurrent
network (RAFT/DROID style, Sec. 3.1). No weights ship with this project, so the
default predictor is classical: OpenCV DIS optical flow computed forwards and
backwards, confidences from forward-backward consistency, the photometric
residual after warping, local texture (aperture problem per axis) and the flow
spread inside each BA cell. Flows are taken at the BA grid (tracking image /
``ba_downsample``) by confidence-weighted average pooling.

Anything with the :class:`FlowPredictor` interface can replace it; BA only consumes
``(flow, weight)`` at the BA grid. ``tracking.flow_model`` (a DROID-SLAM checkpoint)
selects the learned predictor of ``droid_flow.py`` in :func:`make_flow_predictor`.
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, List, Optional, Protocol, Sequence, Tuple, runtime_checkable

import cv2
import numpy as np
import torch

from splat_slam_ros.imaging import to_gray
from splat_slam_ros.tracking.droid_flow import make_droid_predictor
from splat_slam_ros.types import Intrinsics


class FrontendError(ValueError):
    """A user-facing front-end configuration mistake."""


# ---------------------------------------------------------------- interface
@runtime_checkable
class FlowPredictor(Protocol):
    """Dense flow + confidence between two tracking-resolution images.

    ``prepare(image)`` turns a tracking-resolution uint8 image (H x W x 3 RGB)
    into whatever ``predict`` consumes (cached per keyframe by the tracker).
    ``predict(img_i, img_j)`` returns ``flow`` (h, w, 2) float32 tensor: the
    displacement (BA pixels) of every BA-grid pixel of ``i`` into ``j``, and
    ``weight`` (h, w, 2) in [0, 1]. ``(h, w) = (H, W) / ba_downsample``.
    """
    ba_downsample: int

    def prepare(self, image: np.ndarray) -> Any: ...

    def predict(self, img_i: Any, img_j: Any) -> Tuple[torch.Tensor, torch.Tensor]: ...


def predict_both(pred, img_i, img_j, init_ij: Optional[torch.Tensor] = None):
    """Flows and weights in both directions: (f_ij, w_ij, f_ji, w_ji).

    Uses the predictor's ``predict_pair`` when it has one (DIS computes both
    directions anyway for its consistency check), else two ``predict`` calls.
    """
    if hasattr(pred, "predict_pair"):
        return pred.predict_pair(img_i, img_j, init_ij=init_ij)
    f_ij, w_ij = pred.predict(img_i, img_j)
    f_ji, w_ji = pred.predict(img_j, img_i)
    return f_ij, w_ij, f_ji, w_ji


# ----------------------------------------------------------- image prep
@dataclass
class PreparedImage:
    """What :class:`DISFlowPredictor` keeps per image (flow resolution)."""
    gray: np.ndarray            # Hf x Wf uint8
    tex: np.ndarray             # h x w x 2 float32 texture confidence per axis (BA grid)
    mean: float
    ptex: np.ndarray            # Hf x Wf x 2 uint8 the same per flow pixel (5x5 window), x 255


class ImagePreprocessor:
    """Raw camera image -> tracking image (undistort, crop, resize, trim to the BA grid).

    Built once per camera: the undistortion map is computed in ``__init__``
    (``cv2.initUndistortRectifyMap``). ``intrinsics`` is the tracking-resolution
    pinhole camera (no distortion) and ``ba_intrinsics`` the BA grid's.
    """

    def __init__(self, intrinsics: Intrinsics, ba_downsample: int = 8, width: int = 0,
                 height: int = 0, crop: int = 0, undistort: bool = True, multiple: int = 0):
        if ba_downsample < 1:
            raise FrontendError(f"tracking.ba_downsample must be >= 1, got {ba_downsample}")
        self.raw = intrinsics
        self.map1 = self.map2 = None
        K = intrinsics.K.copy()
        W0, H0 = int(intrinsics.width), int(intrinsics.height)
        if undistort and intrinsics.has_distortion:
            D = np.asarray(intrinsics.distortion, dtype=np.float64)
            if intrinsics.distortion_model in ("equidistant", "fisheye"):
                Kn = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
                    K, D[:4], (W0, H0), np.eye(3), balance=0.0)
                self.map1, self.map2 = cv2.fisheye.initUndistortRectifyMap(
                    K, D[:4], np.eye(3), Kn, (W0, H0), cv2.CV_16SC2)
            elif intrinsics.distortion_model in ("plumb_bob", "radtan", "rational_polynomial"):
                Kn, _ = cv2.getOptimalNewCameraMatrix(K, D, (W0, H0), 0.0, (W0, H0))
                self.map1, self.map2 = cv2.initUndistortRectifyMap(
                    K, D, None, Kn, (W0, H0), cv2.CV_16SC2)
            else:
                raise FrontendError(
                    f"unsupported distortion model '{intrinsics.distortion_model}' "
                    "(use plumb_bob/radtan or equidistant)")
            K = Kn
        self.crop = int(crop)
        if self.crop < 0 or 2 * self.crop >= min(W0, H0):
            raise FrontendError(f"camera.crop={crop} is invalid for a {W0}x{H0} image")
        Wc, Hc = W0 - 2 * self.crop, H0 - 2 * self.crop
        intr = Intrinsics(K[0, 0], K[1, 1], K[0, 2] - self.crop, K[1, 2] - self.crop, Wc, Hc)
        self.resize = None
        if width > 0 or height > 0:
            Wt = width if width > 0 else int(round(Wc * height / Hc))
            Ht = height if height > 0 else int(round(Hc * width / Wc))
            if (Wt, Ht) != (Wc, Hc):
                self.resize = (Wt, Ht)
                intr = intr.scaled(Wt / Wc, Ht / Hc)
                intr.width, intr.height = Wt, Ht
        m = multiple if multiple > 0 else ba_downsample
        Wf, Hf = (intr.width // m) * m, (intr.height // m) * m
        if Wf < 2 * ba_downsample or Hf < 2 * ba_downsample:
            raise FrontendError(f"tracking image {intr.width}x{intr.height} is too small for "
                                f"ba_downsample={ba_downsample}")
        self.trim = (Wf, Hf)
        intr.width, intr.height = Wf, Hf
        self.intrinsics = intr
        self.ba_downsample = ba_downsample
        s = 1.0 / ba_downsample
        self.ba_intrinsics = intr.scaled(s)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Raw image (H x W mono8 or H x W x 3 RGB uint8) -> tracking RGB uint8."""
        img = np.asarray(image)
        if img.dtype != np.uint8:
            if np.issubdtype(img.dtype, np.floating):
                img = np.clip(img * (255.0 if img.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
            else:   # e.g. mono16
                img = (img.astype(np.float32) * (255.0 / max(float(img.max()), 1.0))).astype(
                    np.uint8)
        if img.ndim == 3 and img.shape[2] == 1:
            img = img[..., 0]
        if img.ndim == 3 and img.shape[2] == 4:
            img = img[..., :3]
        img = self._warp(img, cv2.INTER_LINEAR, cv2.INTER_AREA)
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        return np.ascontiguousarray(img)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """A depth map of the raw camera (H x W, metres) on this image's pixels: the same
        undistortion, crop, resize and trim, with nearest-neighbour sampling (no depth is
        blended across an edge)."""
        d = np.asarray(depth, np.float32)
        if d.ndim == 3 and d.shape[2] == 1:
            d = d[..., 0]
        return np.ascontiguousarray(self._warp(d, cv2.INTER_NEAREST, cv2.INTER_NEAREST))

    def _warp(self, img: np.ndarray, remap_interp: int, resize_interp: int) -> np.ndarray:
        H0, W0 = img.shape[:2]
        if (W0, H0) != (self.raw.width, self.raw.height):
            raise FrontendError(f"image is {W0}x{H0} but the intrinsics say "
                                f"{self.raw.width}x{self.raw.height}")
        if self.map1 is not None:
            img = cv2.remap(img, self.map1, self.map2, remap_interp)
        if self.crop:
            c = self.crop
            img = img[c:H0 - c, c:W0 - c]
        if self.resize is not None:
            img = cv2.resize(img, self.resize, interpolation=resize_interp)
        Wf, Hf = self.trim
        return img[:Hf, :Wf]


def mapping_preprocessor(cfg, intrinsics: Intrinsics) -> ImagePreprocessor:
    """The mapping camera of a raw camera (``camera.*``: undistortion, crop, the processing
    size, trimmed to the BA grid): what keyframes are handed on at, and what the map's metrics
    compare against (``pipeline.evaluate_map_depth``)."""
    cam = cfg.camera
    W0, H0 = intrinsics.width - 2 * cam.crop, intrinsics.height - 2 * cam.crop
    mw, mh = cam.processing_size(W0, H0)
    return ImagePreprocessor(intrinsics, cfg.tracking.ba_downsample, mw, mh, cam.crop,
                             cam.undistort)


# ------------------------------------------------------------- DIS predictor
_PRESETS = {"dis_ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
            "dis_fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
            "dis_medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


class DISFlowPredictor:
    """OpenCV DIS flow at ``1/flow_downsample`` of the tracking image, pooled to the BA grid.

    Confidence per pixel and axis = 1 / (1 + (fb_err / fb_px)^2 + (photo / photo_sigma)^2),
    zero where the flow leaves the image; per BA cell and axis the flow is the
    confidence-weighted mean and the weight is the mean confidence, times a
    texture factor per axis and a penalty on the flow spread inside the cell
    (a cell across a depth edge cannot be explained by one disparity). With ``aperture``
    the forward-backward error and the spread along the other axis count only as far as
    the image has texture along it: on an edge the flow along the edge is not measured
    (the aperture problem), and its disagreement must not take the weight of the flow
    across the edge (low-texture scenes are mostly edges).
    Thresholds are in tracking-image pixels / grey levels.

    With ``workers`` = 2 the two halves of a pair (forward and backward DIS, then their
    confidences) and batches of forward flows run on two threads: OpenCV releases the GIL,
    each thread has its own DIS instance, and the results are those of one thread.
    """

    def __init__(self, ba_downsample: int = 8, method: str = "dis_medium",
                 flow_downsample: int = 2, fb_px: float = 1.0, photo_sigma: float = 30.0,
                 texture_grad: float = 1.0, spread_px: float = 1.5, min_weight: float = 0.0,
                 workers: int = 1, finest_scale: int = -1, patch_stride: int = -1,
                 refine_iters: int = -1, aperture: bool = True):
        if method not in _PRESETS:
            raise FrontendError(f"unknown tracking.flow_method '{method}' "
                                f"(use one of {', '.join(_PRESETS)})")
        if flow_downsample < 1 or ba_downsample % flow_downsample:
            raise FrontendError(f"tracking.flow_downsample={flow_downsample} must divide "
                                f"ba_downsample={ba_downsample}")
        self.ba_downsample = ba_downsample
        self.fds = flow_downsample
        if workers < 1:
            raise FrontendError(f"tracking.flow_workers must be >= 1, got {workers}")
        self.k = ba_downsample // flow_downsample
        self.preset = _PRESETS[method]
        # over the preset (-1 = the preset's value)
        self.dis_settings = {"FinestScale": finest_scale, "PatchStride": patch_stride,
                             "VariationalRefinementIterations": refine_iters}
        for key, v, lo in (("flow_finest_scale", finest_scale, 0),
                           ("flow_patch_stride", patch_stride, 1),
                           ("flow_refine_iters", refine_iters, 0)):
            if v != -1 and v < lo:
                raise FrontendError(f"tracking.{key} must be -1 (the preset's) or >= {lo}, "
                                    f"got {v}")
        self._local = threading.local()             # one DIS instance per thread
        self._grids = {}
        self._pool = ThreadPoolExecutor(workers - 1, thread_name_prefix="dis") \
            if workers > 1 else None
        self.fb_px = fb_px
        self.photo_sigma = photo_sigma
        self.texture_grad = texture_grad
        self.spread_px = spread_px
        self.min_weight = min_weight
        self.aperture = bool(aperture)

    # -------------------------------------------------------------- prepare
    def prepare(self, image: np.ndarray) -> PreparedImage:
        g = to_gray(image)
        if self.fds > 1:
            g = cv2.resize(g, (g.shape[1] // self.fds, g.shape[0] // self.fds),
                           interpolation=cv2.INTER_AREA)
        g = np.ascontiguousarray(g)
        gf = g.astype(np.float32)
        gx = cv2.Sobel(gf, cv2.CV_32F, 1, 0, ksize=3) / 8.0 / self.fds   # grey / tracking px
        gy = cv2.Sobel(gf, cv2.CV_32F, 0, 1, ksize=3) / 8.0 / self.fds
        k = self.k
        size = (g.shape[1] // k, g.shape[0] // k)
        sxx = cv2.resize(gx * gx, size, interpolation=cv2.INTER_AREA)
        syy = cv2.resize(gy * gy, size, interpolation=cv2.INTER_AREA)
        t2 = self.texture_grad ** 2
        tex = np.stack([sxx / (sxx + t2), syy / (syy + t2)], -1).astype(np.float32)
        px = cv2.boxFilter(gx * gx, -1, (5, 5))
        py = cv2.boxFilter(gy * gy, -1, (5, 5))
        ptex = np.rint(np.stack([px / (px + t2), py / (py + t2)], -1) * 255).astype(np.uint8)
        return PreparedImage(gray=g, tex=tex, mean=float(gf.mean()), ptex=ptex)

    def _as_prepared(self, img) -> PreparedImage:
        return img if isinstance(img, PreparedImage) else self.prepare(img)

    # -------------------------------------------------------------- predict
    def _dense(self, a: np.ndarray, b: np.ndarray, init: Optional[np.ndarray]) -> np.ndarray:
        """DIS flow a -> b (flow-resolution pixels). With ``init`` (the expected
        flow), ``b`` is first warped by it and only the residual flow is estimated
        (large, predictable displacements: far keyframes, loop candidates)."""
        dis = getattr(self._local, "dis", None)
        if dis is None:
            dis = self._local.dis = cv2.DISOpticalFlow_create(self.preset)
            for name, v in self.dis_settings.items():
                if v >= 0:
                    getattr(dis, "set" + name)(int(v))
        if init is None:
            return dis.calc(a, b, None)
        gx, gy = self._grid(*a.shape)
        bw = cv2.remap(b, gx + init[..., 0], gy + init[..., 1], cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)
        res = dis.calc(a, bw, None)
        # f(x) = r(x) + init(x + r(x))
        init_at = cv2.remap(init, gx + res[..., 0], gy + res[..., 1], cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REPLICATE)
        return res + init_at

    def _grid(self, H: int, W: int):
        g = self._grids.get((H, W))
        if g is None:           # (read-only; a race only builds the same grid twice)
            g = self._grids[(H, W)] = tuple(np.meshgrid(np.arange(W, dtype=np.float32),
                                                        np.arange(H, dtype=np.float32)))
        return g

    def _both(self, fa, fb):
        """(fa(), fb()), fb on the helper thread when there is one."""
        if self._pool is None:
            return fa(), fb()
        fut = self._pool.submit(fb)
        return fa(), fut.result()

    def _confidence(self, A: PreparedImage, B: PreparedImage, f_ab: np.ndarray,
                    f_ba: Optional[np.ndarray]) -> np.ndarray:
        """Per flow-pixel and axis confidence in [0, 1] (H x W x 2) of the flow a -> b
        (without ``f_ba``: no forward-backward term, photometric residual only)."""
        H, W = f_ab.shape[:2]
        gx, gy = self._grid(H, W)
        mx = gx + f_ab[..., 0]
        my = gy + f_ab[..., 1]
        if f_ba is None:
            inside = (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
            out = ~inside
            penalty = np.zeros((H, W, 2), np.float32)
        else:
            back = cv2.remap(f_ba, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=(1e4, 1e4))
            back += f_ab
            out = np.abs(back[..., 0]) > 1e3
            b2 = back * back
            if self.aperture:
                # per axis: the error along the other axis counts as far as the image has
                # texture along it (an edge's flow along the edge is not measured)
                b2 = b2 + b2[..., ::-1] * A.ptex[..., ::-1] * np.float32(1 / 255)
            else:
                b2 = np.repeat(b2.sum(-1, keepdims=True), 2, -1)
            penalty = b2 * ((self.fds / self.fb_px) ** 2)               # (err / fb_px)^2
        if self.photo_sigma > 0:
            warped = cv2.remap(B.gray, mx, my, cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
            gain = float(np.clip(A.mean / max(B.mean, 1.0), 0.5, 2.0))
            res = A.gray.astype(np.float32) - gain * warped
            res *= 1.0 / self.photo_sigma
            penalty += (res * res)[..., None]
        penalty += 1.0
        conf = 1.0 / penalty
        # flows leaving the image: the backward remap returned the 1e4 border value
        conf[out] = 0.0
        return conf

    def _pool_cells(self, A: PreparedImage, f: np.ndarray, c: np.ndarray):
        """Per axis, the confidence-weighted mean flow per BA cell and the cell weight."""
        k = self.k
        H, W = c.shape[:2]
        size = (W // k, H // k)
        area = cv2.INTER_AREA
        cm = cv2.resize(c, size, interpolation=area)                  # mean confidence
        fc = f * c
        cf = cv2.resize(fc, size, interpolation=area)
        csafe = np.maximum(cm, 1e-6)
        fs = cf / csafe
        weight_cell = cm
        if self.spread_px > 0:
            f2 = cv2.resize(f * fc, size, interpolation=area)
            var = np.maximum(f2 / csafe - fs * fs, 0.0) * self.fds ** 2
            # the spread along the other axis, as the forward-backward error above
            var = var + var[..., ::-1] * (A.tex[..., ::-1] if self.aperture else 1.0)
            weight_cell = cm / (1.0 + var / self.spread_px ** 2)
        weight = weight_cell * A.tex
        if self.min_weight > 0:
            weight = np.where(weight < self.min_weight, 0.0, weight)
        flow_ba = fs * (self.fds / self.ba_downsample)
        return (torch.from_numpy(np.ascontiguousarray(flow_ba, dtype=np.float32)),
                torch.from_numpy(np.ascontiguousarray(weight, dtype=np.float32)))

    def _upsample_init(self, init: Optional[torch.Tensor], shape) -> Optional[np.ndarray]:
        if init is None:
            return None
        s = self.ba_downsample / self.fds
        up = np.asarray(init.detach().cpu() if torch.is_tensor(init) else init,
                        dtype=np.float32) * s
        return cv2.resize(up, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)

    def _invert(self, f: np.ndarray, iters: int = 3) -> np.ndarray:
        """Approximate inverse of a smooth flow field: g(y) = -f(y + g(y))."""
        H, W = f.shape[:2]
        gx, gy = self._grid(H, W)
        g = -f
        for _ in range(iters):
            g = -cv2.remap(f, gx + g[..., 0], gy + g[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
        return g

    def predict_pair(self, img_i, img_j, init_ij: Optional[torch.Tensor] = None,
                     init_ji: Optional[torch.Tensor] = None):
        """(f_ij, w_ij, f_ji, w_ji) at the BA grid. ``init_ij`` / ``init_ji``
        (h, w, 2) BA-pixel flows expected from the current estimate (optional):
        DIS then only estimates the residual (``init_ji`` defaults to the inverse
        of ``init_ij``)."""
        A, B = self._as_prepared(img_i), self._as_prepared(img_j)
        init_f = self._upsample_init(init_ij, A.gray.shape)
        init_b = self._upsample_init(init_ji, B.gray.shape)
        if init_f is not None and init_b is None:
            init_b = self._invert(init_f)
        f_ij, f_ji = self._both(lambda: self._dense(A.gray, B.gray, init_f),
                                lambda: self._dense(B.gray, A.gray, init_b))
        a, b = self._both(lambda: self._pool_cells(A, f_ij, self._confidence(A, B, f_ij, f_ji)),
                          lambda: self._pool_cells(B, f_ji, self._confidence(B, A, f_ji, f_ij)))
        return a[0], a[1], b[0], b[1]

    def predict_forward(self, img_i, img_j, init_ij: Optional[torch.Tensor] = None):
        """(f_ij, w_ij) from one DIS call (half of :meth:`predict_pair`): the confidence
        has no forward-backward term, so use it where the flow is started from a good
        estimate (``init_ij``, BA pixels) and only adds a constraint."""
        A, B = self._as_prepared(img_i), self._as_prepared(img_j)
        f_ij = self._dense(A.gray, B.gray, self._upsample_init(init_ij, A.gray.shape))
        return self._pool_cells(A, f_ij, self._confidence(A, B, f_ij, None))

    def predict_forward_many(self, img_i, imgs: Sequence, inits: Sequence
                             ) -> List[Tuple[torch.Tensor, torch.Tensor]]:
        """:meth:`predict_forward` from one image into several (``inits[k]`` for
        ``imgs[k]``); the second half of the list runs on the helper thread."""
        A = self._as_prepared(img_i)
        n = len(imgs)
        half = n // 2 if self._pool is not None else n

        def run(ks):
            return [self.predict_forward(A, imgs[k], inits[k]) for k in ks]
        first, second = self._both(lambda: run(range(half)), lambda: run(range(half, n)))
        return first + second

    def predict(self, img_i, img_j) -> Tuple[torch.Tensor, torch.Tensor]:
        f_ij, w_ij, _, _ = self.predict_pair(img_i, img_j)
        return f_ij, w_ij


def make_flow_predictor(tcfg):
    """The predictor a TrackingConfig selects: the DROID-SLAM network when
    ``flow_model`` names a checkpoint, else the classical DIS predictor."""
    if getattr(tcfg, "flow_model", ""):
        return make_droid_predictor(tcfg)
    return DISFlowPredictor(ba_downsample=tcfg.ba_downsample, method=tcfg.flow_method,
                            flow_downsample=getattr(tcfg, "flow_downsample", 2),
                            fb_px=tcfg.fb_consistency_px,
                            photo_sigma=getattr(tcfg, "photo_sigma", 30.0),
                            texture_grad=getattr(tcfg, "texture_grad", 1.0),
                            spread_px=getattr(tcfg, "flow_spread_px", 1.5),
                            workers=tcfg.flow_workers, finest_scale=tcfg.flow_finest_scale,
                            patch_stride=tcfg.flow_patch_stride,
                            refine_iters=tcfg.flow_refine_iters,
                            aperture=tcfg.flow_aperture)


def compose_flows(f_ab: torch.Tensor, f_bc: torch.Tensor) -> torch.Tensor:
    """Flow a -> c from a -> b and b -> c (h, w, 2, BA pixels): f_ab(x) + f_bc(x + f_ab(x))."""
    h, w = f_ab.shape[:2]
    v, u = torch.meshgrid(torch.arange(h, dtype=f_ab.dtype, device=f_ab.device),
                          torch.arange(w, dtype=f_ab.dtype, device=f_ab.device), indexing="ij")
    x = u + f_ab[..., 0]
    y = v + f_ab[..., 1]
    g = torch.stack([2 * x / max(w - 1, 1) - 1, 2 * y / max(h - 1, 1) - 1], -1)
    s = torch.nn.functional.grid_sample(f_bc.permute(2, 0, 1)[None], g[None], mode="bilinear",
                                        padding_mode="border", align_corners=True)[0]
    return f_ab + s.permute(1, 2, 0)


def mean_flow(flow: torch.Tensor, weight: torch.Tensor, min_w: float = 0.1) -> float:
    """Mean flow magnitude (BA pixels) over confident cells (all cells if none)."""
    m = weight.mean(-1) > min_w
    mag = flow.norm(dim=-1)
    if int(m.sum()) < 0.05 * m.numel():
        return float(mag.mean())
    return float(mag[m].mean())
