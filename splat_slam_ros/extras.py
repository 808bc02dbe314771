"""Optional dependencies: the ``extras_require`` of setup.cfg.

Code that needs one imports it where it is used (inside the function), never at module level,
so that every command imports and runs its base features without the extras. A missing one is
reported with :class:`MissingExtra`, whose message names the extra that installs it::

    try:
        import onnxruntime
    except ImportError as e:
        raise MissingExtra("onnx", "an .onnx mono depth model", e) from None

``tests/test_packaging.py`` checks that this table matches setup.cfg.
"""
from __future__ import annotations

from typing import Optional

# extra name -> the distribution it installs (setup.cfg [options.extras_require])
EXTRAS = {
    "onnx": "onnxruntime",      # .onnx mono depth models (depth.mono_model)
    "rerun": "rerun-sdk",       # splat-slam-rerun-logger, splat-slam-launch --rerun
    "gsplat": "gsplat",         # the CUDA rasterizer backend (mapping.raster_backend: gsplat)
}


def missing_extra_message(extra: str, feature: str, cause: Optional[BaseException] = None) -> str:
    """One line: what needs the extra, that it is missing, and how to install it."""
    dist = EXTRAS[extra]
    why = f" ({type(cause).__name__}: {cause})" if cause is not None else ""
    return (f"{feature} needs {dist}, which is not installed{why}; install the [{extra}] extra: "
            f"pip install '.[{extra}]' from the source tree (or pip install {dist})")


class MissingExtra(ImportError):
    """An optional dependency (a setup.cfg extra) is not installed."""

    def __init__(self, extra: str, feature: str, cause: Optional[BaseException] = None):
        super().__init__(missing_extra_message(extra, feature, cause))
        self.extra = extra
