"""Options of the synthetic-sequence generator: constants, errors, camera-realism settings,
image size and default intrinsics."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Dict, Optional, Tuple

from splat_slam_ros.types import Intrinsics

DEPTH_SCALE = 5000.0          # uint16 units per metre (TUM)
TEX_SIZE = 512                # texture tile size (texels, power of two)
TEX_LEVELS = 8                # mip levels 512 .. 4
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
GAP_WARN_S = 0.2              # ground-truth gaps longer than this are reported


class SynthError(ValueError):
    """A user mistake in the synthetic-sequence options (printed as ``error: ...``)."""


# ============================================================ options / parsing
@dataclass
class RealismOptions:
    """Camera-realism effects (RGB only). Zero / 1 means off."""
    motion_blur: int = 1          # sub-exposure renders averaged per frame (1 = off)
    exposure_ms: float = 15.0     # exposure window before the frame stamp (for motion blur)
    auto_exposure: float = 0.0    # relative amplitude of the smooth gain drift (0.1 = +-10 %)
    vignetting: float = 0.0       # brightness loss in the image corners (0.3 = -30 %)
    noise: float = 0.0            # noise std at mid-grey, 8-bit units (shot + read)
    jpeg: int = 0                 # JPEG quality 1..100 (0 = off)

    def validate(self, fps: float) -> "RealismOptions":
        if int(self.motion_blur) != self.motion_blur or not 1 <= self.motion_blur <= 64:
            raise SynthError(f"--motion-blur must be an integer in 1..64, got {self.motion_blur}")
        self.motion_blur = int(self.motion_blur)
        frame_ms = 1000.0 / fps
        if not 0.0 < self.exposure_ms <= frame_ms + 1e-9:
            raise SynthError(f"--exposure must be in (0, {frame_ms:.3g}] ms (the frame period at "
                             f"{fps:g} fps), got {self.exposure_ms:g}")
        if not 0.0 <= self.auto_exposure <= 0.9:
            raise SynthError(f"--auto-exposure must be in [0, 0.9], got {self.auto_exposure:g}")
        if not 0.0 <= self.vignetting < 1.0:
            raise SynthError(f"--vignetting must be in [0, 1), got {self.vignetting:g}")
        if not 0.0 <= self.noise <= 64.0:
            raise SynthError(f"--noise must be in [0, 64] (8-bit units), got {self.noise:g}")
        if int(self.jpeg) != self.jpeg or not 0 <= self.jpeg <= 100:
            raise SynthError(f"--jpeg must be an integer quality in 1..100 (0 = off), got {self.jpeg}")
        self.jpeg = int(self.jpeg)
        return self

    @property
    def any(self) -> bool:
        return (self.motion_blur > 1 or self.auto_exposure > 0 or self.vignetting > 0
                or self.noise > 0 or self.jpeg > 0)


REALISM_PRESETS: Dict[str, RealismOptions] = {
    "clean": RealismOptions(),
    # A hand-held consumer RGB-D camera indoors: short blur, slow AE drift, mild vignetting,
    # sensor noise and light JPEG artefacts (the TUM Kinect streams were compressed too).
    "realistic": RealismOptions(motion_blur=5, exposure_ms=15.0, auto_exposure=0.08,
                                vignetting=0.25, noise=2.0, jpeg=90),
}


def parse_size(size) -> Tuple[int, int]:
    """'640x480' or (640, 480) -> (width, height)."""
    if isinstance(size, str):
        parts = size.lower().replace("*", "x").split("x")
        try:
            if len(parts) != 2:
                raise ValueError
            w, h = int(parts[0]), int(parts[1])
        except ValueError:
            raise SynthError(f"--size must look like WIDTHxHEIGHT (e.g. 640x480), got '{size}'") \
                from None
    else:
        try:
            w, h = (int(x) for x in size)
        except (TypeError, ValueError):
            raise SynthError(f"size must be (width, height) or 'WxH', got {size!r}") from None
    if not (8 <= w <= 8192 and 8 <= h <= 8192):
        raise SynthError(f"image size {w}x{h} out of range (each side 8..8192 pixels)")
    return w, h


def default_intrinsics(width: int, height: int, fov_deg: Optional[float] = None) -> Intrinsics:
    """TUM-like pinhole: fx = fy = 525 at 640 px wide (scaled), principal point at the centre;
    or the focal length giving a horizontal field of view ``fov_deg``."""
    if fov_deg is None:
        f = 525.0 * width / 640.0
    else:
        if not 10.0 <= fov_deg <= 160.0:
            raise SynthError(f"--fov must be in [10, 160] degrees, got {fov_deg:g}")
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


def resolve_realism(realism: Optional[str] = None, **overrides) -> RealismOptions:
    """Preset (``clean`` | ``realistic``) with explicit options (not None) on top."""
    name = realism or "clean"
    if name not in REALISM_PRESETS:
        raise SynthError(f"unknown --realism '{name}' (use one of {sorted(REALISM_PRESETS)})")
    d = asdict(REALISM_PRESETS[name])
    for k, v in overrides.items():
        if k not in d:
            raise SynthError(f"unknown realism option '{k}'")
        if v is not None:
            d[k] = v
    return RealismOptions(**d)
