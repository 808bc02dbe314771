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
    rolling_shutter_ms: float = 0.0   # readout time from the top to the bottom row (0 = off)

    def validate(self, fps: float, preset: Optional[str] = None) -> "RealismOptions":
        """Range checks (SynthError); ``preset`` names the --realism preset in the messages
        about values that depend on the frame rate."""
        if int(self.motion_blur) != self.motion_blur or not 1 <= self.motion_blur <= 64:
            raise SynthError(f"--motion-blur must be an integer in 1..64, got {self.motion_blur}")
        self.motion_blur = int(self.motion_blur)
        frame_ms = 1000.0 / fps

        def hint(key: str) -> str:
            ref = REALISM_PRESETS.get(preset or "clean")
            if preset and ref is not None and getattr(ref, key) == getattr(self, key):
                return f" (set by --realism {preset}; give the option to override it)"
            return ""
        if not 0.0 < self.exposure_ms <= frame_ms + 1e-9:
            raise SynthError(f"--exposure must be in (0, {frame_ms:.3g}] ms (the frame period at "
                             f"{fps:g} fps), got {self.exposure_ms:g}{hint('exposure_ms')}")
        rs = self.rolling_shutter_ms
        if not (math.isfinite(rs) and 0.0 <= rs <= frame_ms + 1e-9):
            raise SynthError(f"--rolling-shutter must be in [0, {frame_ms:.3g}] ms (0 = off, at "
                             f"most the frame period at {fps:g} fps), got {rs:g}"
                             f"{hint('rolling_shutter_ms')}")
        self.rolling_shutter_ms = float(rs)
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
                or self.noise > 0 or self.jpeg > 0 or self.rolling_shutter_ms > 0)


REALISM_PRESETS: Dict[str, RealismOptions] = {
    "clean": RealismOptions(),
    # A hand-held consumer RGB-D camera indoors: short blur, slow AE drift, mild vignetting,
    # sensor noise and light JPEG artefacts (the TUM Kinect streams were compressed too).
    "realistic": RealismOptions(motion_blur=5, exposure_ms=15.0, auto_exposure=0.08,
                                vignetting=0.25, noise=2.0, jpeg=90),
    # A cheap webcam / phone in a dim room moved fast: long blur, strong AE pumping, heavy
    # vignetting and noise, visible JPEG blocks and a rolling-shutter skew.
    "harsh": RealismOptions(motion_blur=7, exposure_ms=20.0, auto_exposure=0.25,
                            vignetting=0.5, noise=4.0, jpeg=75, rolling_shutter_ms=20.0),
}

# Scene variants of the generator (--scene): name -> one-line description. "room" is the
# original furnished room; the others stress optical flow / depth in one way each.
SCENES: Dict[str, str] = {
    "room": "furnished room: mixed procedural textures, 8-32 furniture-like boxes (default)",
    "low_texture": "plain low-contrast paint on walls, floor, ceiling and the 0-2 boxes: "
                   "little for optical flow to lock on to",
    "tiled": "textures stretched to a low texel density (blurry) on some surfaces and small "
             "repeating tiles (a tile every 12-30 cm) on the others",
    "repetitive": "strictly periodic checkerboards, stripes, grids and bricks on most "
                  "surfaces: aliasing / wrong matches for flow",
    "thin": "the room plus thin structures (poles, shelf boards, tables with 4 cm legs) in "
            "front of the walls, away from the camera path",
    "deep": "a hall along the main viewing direction, its far wall 10-18 m beyond the camera "
            "path (for cameras looking down the floor is lowered so that the mean view ray "
            "runs as far), with near boxes 0.5-1.5 m from the path (depth PNGs store 0 beyond "
            "13.1 m)",
}


def check_scene(name: Optional[str]) -> str:
    """The scene variant name (None -> 'room'); SynthError when unknown."""
    name = "room" if name is None else name
    if not isinstance(name, str) or name not in SCENES:
        raise SynthError(f"unknown --scene '{name}' (use one of {', '.join(SCENES)})")
    return name


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
    """Preset (``clean`` | ``realistic`` | ``harsh``) with explicit options (not None) on
    top."""
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
