"""Monocular depth models supplied by the user (paper §3.1, D^mono in Eq. 2; §3.2 proxy depth).

The paper runs a pretrained relative-depth DPT (Omnidata). No weights ship with this
project and none are downloaded: the user points ``depth.mono_model`` at a model file and
a small sidecar file that says how to feed it. Two backends:

- ONNX Runtime (``*.onnx``): e.g. an exported DPT / MiDaS / Depth-Anything;
  CPU or CUDA execution provider.
- TorchScript (``*.pt``, ``*.pth``, ``*.ts``, ``*.torchscript``): ``torch.jit.save`` of a
  module mapping a (1, 3, H, W) float tensor to a depth or disparity map.

Sidecar (YAML or JSON), looked up as ``<model file>.yaml``/``.yml``/``.json`` first, then
the model path with its suffix replaced by ``.yaml``/``.yml``/``.json``::

    output: disparity          # REQUIRED: depth | disparity (what the network predicts)
    input_size: [384, 384]     # H W fed to the network (default: the model's static input
                               #   shape; dynamic models: the image size rounded, see resize)
    resize: stretch            # stretch | letterbox | dynamic
    size_multiple: 32          # dynamic: both sides rounded to a multiple of this
    long_side: 0               # dynamic: longest side scaled to this first (0 = keep)
    mean: [0.485, 0.456, 0.406]  # normalisation after scaling pixels to [0, 1]
    std: [0.229, 0.224, 0.225]
    channel_order: rgb         # rgb | bgr
    input_name: null           # ONNX input/output names (default: the first ones)
    output_name: null
    threads: 0                 # ONNX Runtime intra-op threads (0 = its default)

``predict(image)`` always returns RELATIVE DEPTH at the image resolution, float32,
positive where defined and 0 where the model gives no usable value. Disparity outputs are
resized in disparity space (affine for planes) and converted by ``depth = 1 / disp`` for
``disp > 1e-3 * max(disp)`` (0 elsewhere: sky / infinitely far). ``model.kind`` keeps the
native output kind so that callers can fit the scale/shift in that space (affine-invariant
disparity models such as MiDaS or Depth-Anything have an unknown disparity *shift*, so a
fit in depth space would be wrong for them).
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import List, Optional, Tuple

import cv2
import numpy as np
import torch
import yaml

from splat_slam_ros.config import ConfigError
from splat_slam_ros.extras import missing_extra_message


class MonoDepthError(ConfigError):
    """A user-supplied monocular depth model or its sidecar is missing, unreadable or unusable
    (a configuration error: ``depth.mono_model``; a graph node stops on it, exit status 2)."""


TORCH_SUFFIXES = (".pt", ".pth", ".ts", ".torchscript", ".jit")
DISP_EPS = 1e-3          # disparities below this fraction of the max are treated as "far"


@dataclass
class MonoSidecar:
    """How to feed a model and read its output (the sidecar file)."""
    output: str                                   # depth | disparity
    input_size: Optional[List[int]] = None        # [H, W]
    resize: str = "stretch"                       # stretch | letterbox | dynamic
    size_multiple: int = 32
    long_side: int = 0
    mean: List[float] = field(default_factory=lambda: [0.485, 0.456, 0.406])
    std: List[float] = field(default_factory=lambda: [0.229, 0.224, 0.225])
    channel_order: str = "rgb"
    input_name: Optional[str] = None
    output_name: Optional[str] = None
    threads: int = 0


def sidecar_candidates(model_path: Path) -> List[Path]:
    p = Path(model_path)
    out = [p.with_name(p.name + ext) for ext in (".yaml", ".yml", ".json")]
    out += [p.with_suffix(ext) for ext in (".yaml", ".yml", ".json")]
    return out


def read_sidecar(model_path) -> MonoSidecar:
    """Find, parse and validate the sidecar of ``model_path`` (raises MonoDepthError)."""
    cands = sidecar_candidates(Path(model_path))
    path = next((c for c in cands if c.is_file()), None)
    if path is None:
        raise MonoDepthError(
            f"no sidecar for mono depth model {model_path}: expected one of "
            f"{', '.join(c.name for c in cands[:1] + cands[3:4])} (YAML/JSON with at least "
            "'output: depth|disparity'; see docs/depth.md 'Monocular depth models')")
    try:
        text = path.read_text()
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, ValueError, yaml.YAMLError) as e:
        raise MonoDepthError(f"sidecar {path} is not valid YAML/JSON: {e}") from None
    if not isinstance(data, dict):
        raise MonoDepthError(f"sidecar {path} must hold a mapping")
    known = {f.name for f in fields(MonoSidecar)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise MonoDepthError(f"sidecar {path}: unknown key(s) {', '.join(unknown)}; "
                             f"valid keys: {', '.join(sorted(known))}")
    if "output" not in data:
        raise MonoDepthError(f"sidecar {path} lacks the required key 'output' (depth|disparity)")
    try:
        sc = MonoSidecar(**data)
        sc.output = str(sc.output).lower()
        sc.resize = str(sc.resize).lower()
        sc.channel_order = str(sc.channel_order).lower()
        if sc.output not in ("depth", "disparity"):
            raise ValueError(f"output must be depth or disparity, got {sc.output!r}")
        if sc.resize not in ("stretch", "letterbox", "dynamic"):
            raise ValueError(f"resize must be stretch, letterbox or dynamic, got {sc.resize!r}")
        if sc.channel_order not in ("rgb", "bgr"):
            raise ValueError(f"channel_order must be rgb or bgr, got {sc.channel_order!r}")
        if sc.input_size is not None:
            sc.input_size = [int(x) for x in sc.input_size]
            if len(sc.input_size) != 2 or min(sc.input_size) < 1:
                raise ValueError(f"input_size must be [H, W], got {data['input_size']!r}")
        sc.mean = [float(x) for x in sc.mean]
        sc.std = [float(x) for x in sc.std]
        if len(sc.mean) != 3 or len(sc.std) != 3 or min(abs(s) for s in sc.std) == 0:
            raise ValueError("mean and std must be 3 numbers each (std non-zero)")
        sc.size_multiple = max(1, int(sc.size_multiple))
        sc.long_side = int(sc.long_side)
        sc.threads = int(sc.threads)
    except (TypeError, ValueError) as e:
        raise MonoDepthError(f"sidecar {path}: {e}") from None
    return sc


# ------------------------------------------------------------------ pre/post
def _round_to(x: float, m: int) -> int:
    return max(m, int(round(x / m)) * m)


def _network_size(sc: MonoSidecar, static_hw: Tuple[Optional[int], Optional[int]],
                  H: int, W: int) -> Tuple[int, int]:
    if sc.resize == "dynamic":
        s = sc.long_side / max(H, W) if sc.long_side > 0 else 1.0
        return _round_to(H * s, sc.size_multiple), _round_to(W * s, sc.size_multiple)
    if sc.input_size is not None:
        return sc.input_size[0], sc.input_size[1]
    if static_hw[0] is not None and static_hw[1] is not None:
        return int(static_hw[0]), int(static_hw[1])
    return _round_to(H, sc.size_multiple), _round_to(W, sc.size_multiple)


def preprocess(image: np.ndarray, sc: MonoSidecar, net_hw: Tuple[int, int]):
    """uint8 HxWx3 RGB -> (1, 3, h, w) float32 network input and the valid crop box."""
    H, W = image.shape[:2]
    h, w = net_hw
    img = image[..., ::-1] if sc.channel_order == "bgr" else image
    x = img.astype(np.float32) * (1.0 / 255.0)
    x = (x - np.asarray(sc.mean, np.float32)) / np.asarray(sc.std, np.float32)
    if sc.resize == "letterbox":
        s = min(h / H, w / W)
        nh, nw = max(1, int(round(H * s))), max(1, int(round(W * s)))
        top, left = (h - nh) // 2, (w - nw) // 2
        canvas = np.zeros((h, w, 3), np.float32)      # 0 = the mean colour after normalisation
        canvas[top:top + nh, left:left + nw] = cv2.resize(x, (nw, nh),
                                                         interpolation=cv2.INTER_AREA)
        x, box = canvas, (top, left, nh, nw)
    else:
        if (h, w) != (H, W):
            interp = cv2.INTER_AREA if h * w < H * W else cv2.INTER_LINEAR
            x = cv2.resize(x, (w, h), interpolation=interp)
        box = (0, 0, h, w)
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None]), box


def postprocess(out: np.ndarray, kind: str, box, H: int, W: int) -> np.ndarray:
    """Network output (h, w) in its native space -> relative depth (H, W), 0 = undefined."""
    top, left, nh, nw = box
    y = np.asarray(out, np.float32)[top:top + nh, left:left + nw]
    y = np.where(np.isfinite(y), y, 0.0).astype(np.float32)
    if y.shape != (H, W):
        y = cv2.resize(y, (W, H), interpolation=cv2.INTER_LINEAR)
    if kind == "disparity":
        ymax = float(y.max()) if y.size else 0.0
        ok = y > DISP_EPS * ymax if ymax > 0 else np.zeros_like(y, bool)
        return np.where(ok, 1.0 / np.where(ok, y, 1.0), 0.0).astype(np.float32)
    return np.where(y > 0, y, 0.0).astype(np.float32)


def _squeeze_output(y: np.ndarray, where: str) -> np.ndarray:
    """Accept (h,w), (1,h,w), (1,1,h,w); anything else is an incompatible model."""
    shp = tuple(y.shape)
    if y.ndim == 4 and shp[0] == 1 and shp[1] == 1:
        return y[0, 0]
    if y.ndim == 3 and shp[0] == 1:
        return y[0]
    if y.ndim == 2:
        return y
    raise MonoDepthError(f"{where}: output has shape {list(shp)}; a mono depth model must "
                         "output one channel: (1,1,H,W), (1,H,W) or (H,W)")


# ------------------------------------------------------------------ models
class MonoDepthModel:
    """Interface: ``predict(image_rgb_uint8 HxWx3) -> relative depth HxW float32``.

    ``kind`` is the network's native output ('depth' or 'disparity'); the returned map is
    always depth (positive, 0 where undefined), see the module docstring.
    """
    kind: str = "depth"
    name: str = "mono"

    def predict(self, image: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    @staticmethod
    def _check_image(image) -> np.ndarray:
        a = np.asarray(image)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"mono depth expects an HxWx3 RGB image, got shape {a.shape}")
        if a.dtype != np.uint8:
            raise ValueError(f"mono depth expects a uint8 image, got {a.dtype}")
        return a


class _NetworkMonoDepth(MonoDepthModel):
    """A loaded network with its sidecar ``sc``: preprocess (sidecar resize / normalisation),
    ``_run`` (the backend), postprocess (back to the image size, depth)."""
    sc: MonoSidecar
    static_hw: Tuple[Optional[int], Optional[int]]   # the network's fixed input size, if any

    def _run(self, x: np.ndarray) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def predict(self, image: np.ndarray) -> np.ndarray:
        img = self._check_image(image)
        H, W = img.shape[:2]
        hw = _network_size(self.sc, self.static_hw, H, W)
        x, box = preprocess(img, self.sc, hw)
        return postprocess(self._run(x), self.kind, box, H, W)


class OnnxMonoDepth(_NetworkMonoDepth):
    """ONNX Runtime backend."""

    def __init__(self, path, sidecar: MonoSidecar, provider: str = "auto"):
        self.path = Path(path)
        self.name = self.path.name
        self.sc = sidecar
        self.kind = sidecar.output
        ort = _import_onnxruntime()
        self.providers = _ort_providers(ort, provider)
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        if sidecar.threads > 0:
            opts.intra_op_num_threads = sidecar.threads
        try:
            self.session = ort.InferenceSession(str(self.path), sess_options=opts,
                                                providers=self.providers)
        except Exception as e:  # onnxruntime raises its own exception types
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise MonoDepthError(f"cannot load {self.path} as an ONNX model: {msg}") from None
        ins = self.session.get_inputs()
        outs = self.session.get_outputs()
        if len(ins) != 1 and sidecar.input_name is None:
            raise MonoDepthError(f"{self.path.name}: model has {len(ins)} inputs "
                                 f"({', '.join(i.name for i in ins)}); a mono depth model takes "
                                 "one image (set input_name in the sidecar to pick one)")
        inp = ins[0] if sidecar.input_name is None else next(
            (i for i in ins if i.name == sidecar.input_name), None)
        if inp is None:
            raise MonoDepthError(f"{self.path.name}: no input named {sidecar.input_name!r}")
        out = outs[0] if sidecar.output_name is None else next(
            (o for o in outs if o.name == sidecar.output_name), None)
        if out is None:
            raise MonoDepthError(f"{self.path.name}: no output named {sidecar.output_name!r}")
        self.input_name, self.output_name = inp.name, out.name
        shape = list(inp.shape)
        if len(shape) != 4:
            raise MonoDepthError(f"{self.path.name}: input {inp.name!r} has rank {len(shape)} "
                                 f"(shape {shape}); expected a 4-D (1, 3, H, W) image tensor")
        if isinstance(shape[1], int) and shape[1] != 3:
            raise MonoDepthError(f"{self.path.name}: input {inp.name!r} has {shape[1]} "
                                 "channels; expected 3 (RGB, NCHW layout)")
        if inp.type not in ("tensor(float)", "tensor(float16)"):
            raise MonoDepthError(f"{self.path.name}: input type {inp.type} is not supported "
                                 "(float32 or float16 expected)")
        self.in_dtype = np.float16 if inp.type == "tensor(float16)" else np.float32
        oshape = list(out.shape)
        if len(oshape) == 4 and isinstance(oshape[1], int) and oshape[1] != 1:
            raise MonoDepthError(f"{self.path.name}: output {out.name!r} has {oshape[1]} "
                                 "channels; a mono depth model must output 1 channel")
        if len(oshape) not in (2, 3, 4):
            raise MonoDepthError(f"{self.path.name}: output {out.name!r} has rank "
                                 f"{len(oshape)}; expected (1,1,H,W), (1,H,W) or (H,W)")
        self.static_hw = tuple(s if isinstance(s, int) else None for s in shape[2:4])
        _dry_run(self)

    def _run(self, x: np.ndarray) -> np.ndarray:
        try:
            y = self.session.run([self.output_name],
                                 {self.input_name: x.astype(self.in_dtype, copy=False)})[0]
        except Exception as e:
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise MonoDepthError(f"{self.path.name}: inference failed: {msg}") from None
        return _squeeze_output(np.asarray(y, np.float32), self.path.name)


class TorchScriptMonoDepth(_NetworkMonoDepth):
    """TorchScript backend (``torch.jit.save`` of a module (1,3,H,W) -> depth/disparity)."""

    def __init__(self, path, sidecar: MonoSidecar, provider: str = "auto"):
        self.torch = torch
        self.path = Path(path)
        self.name = self.path.name
        self.sc = sidecar
        self.kind = sidecar.output
        if provider == "cuda" and not torch.cuda.is_available():
            raise MonoDepthError("mono_provider 'cuda' requested but torch sees no CUDA device")
        self.device = torch.device("cuda" if provider in ("cuda", "auto")
                                   and torch.cuda.is_available() else "cpu")
        try:
            with warnings.catch_warnings():      # TorchScript is deprecated in torch >= 2.10
                warnings.simplefilter("ignore", DeprecationWarning)
                self.module = torch.jit.load(str(self.path), map_location=self.device).eval()
        except Exception as e:
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise MonoDepthError(f"cannot load {self.path} as a TorchScript model: {msg}") from None
        self.static_hw = (None, None)
        _dry_run(self)

    def _run(self, x: np.ndarray) -> np.ndarray:
        torch = self.torch
        try:
            with torch.inference_mode():
                y = self.module(torch.from_numpy(x).to(self.device))
        except Exception as e:
            msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise MonoDepthError(f"{self.path.name}: inference failed: {msg}") from None
        if isinstance(y, (tuple, list)):
            y = y[0]
        if isinstance(y, dict):
            y = next(iter(y.values()))
        if not torch.is_tensor(y):
            raise MonoDepthError(f"{self.path.name}: model returned {type(y).__name__}, "
                                 "expected a tensor")
        return _squeeze_output(y.detach().float().cpu().numpy(), self.path.name)


def _dry_run(model) -> None:
    """Run once on a neutral image at load time: incompatible models fail here, clearly."""
    sc = model.sc
    if sc.resize == "dynamic":
        hw = (2 * sc.size_multiple, 2 * sc.size_multiple)
    else:
        hw = _network_size(sc, model.static_hw, 2 * sc.size_multiple, 2 * sc.size_multiple)
    x = np.zeros((1, 3, hw[0], hw[1]), np.float32)
    y = model._run(x)
    if y.size == 0:
        raise MonoDepthError(f"{model.name}: model produced an empty output")


def _import_onnxruntime():
    """onnxruntime (the [onnx] extra) serves .onnx models only: imported on use."""
    try:
        import onnxruntime
    except ImportError as e:
        raise MonoDepthError(missing_extra_message("onnx", "an .onnx mono depth model", e)) \
            from None
    return onnxruntime


def _ort_providers(ort, provider: str) -> List[str]:
    avail = ort.get_available_providers()
    provider = (provider or "auto").lower()
    if provider == "cpu":
        return ["CPUExecutionProvider"]
    if provider == "cuda":
        if "CUDAExecutionProvider" not in avail:
            raise MonoDepthError("mono_provider 'cuda' requested but onnxruntime has no CUDA "
                                 f"provider (available: {', '.join(avail)}); install "
                                 "onnxruntime-gpu or use 'cpu'")
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    if provider != "auto":
        raise MonoDepthError(f"unknown mono_provider {provider!r} (cpu | cuda | auto)")
    return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in avail else []) + \
        ["CPUExecutionProvider"]


def check_mono_model(path) -> MonoSidecar:
    """The checks that need no network: the file exists, has a model suffix and a valid
    sidecar (its MonoSidecar; raises :class:`MonoDepthError`). Nodes run it at start."""
    p = Path(str(path)).expanduser()
    if not str(path):
        raise MonoDepthError("no mono depth model path given")
    if not p.is_file():
        raise MonoDepthError(f"mono depth model not found: {p}")
    if p.suffix.lower() not in (".onnx",) + TORCH_SUFFIXES:
        raise MonoDepthError(f"unsupported mono depth model file {p.name}: expected .onnx or a "
                             f"TorchScript file ({', '.join(TORCH_SUFFIXES)})")
    return read_sidecar(p)


def load_mono_depth(path, provider: str = "auto") -> MonoDepthModel:
    """Load a user-supplied relative-depth model (.onnx or TorchScript) with its sidecar.

    Raises :class:`MonoDepthError` with a one-line message for a missing/corrupt file, a
    missing/invalid sidecar or an incompatible model (checked with one dry run).
    """
    p = Path(str(path)).expanduser()
    sc = check_mono_model(path)
    if p.suffix.lower() == ".onnx":
        return OnnxMonoDepth(p, sc, provider)
    return TorchScriptMonoDepth(p, sc, provider)
