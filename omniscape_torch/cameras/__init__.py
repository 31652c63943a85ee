"""Camera models: one registry, pure ``project``/``unproject`` functions, one ``Camera`` module.

Every model maps between points ``(..., 3)`` in the OpenCV camera frame (x right, y down,
z forward) and pixels ``(..., 2)`` = (u, v) = (column, row), integer coordinates at pixel
centres, with parameters ``(..., P)`` broadcasting over the leading dimensions::

    pixels, valid = ot.cameras.get_model("kannala_brandt").project(points, params)
    rays, valid = ot.cameras.get_model("kannala_brandt").unproject(pixels, params)

========================= ==============================================================
name                      params
========================= ==============================================================
pinhole                   fx, fy, cx, cy
equidistant               fx, fy, cx, cy
equisolid                 fx, fy, cx, cy
stereographic             fx, fy, cx, cy
orthographic              fx, fy, cx, cy
kannala_brandt            fx, fy, cx, cy, k1, k2, k3, k4
unified                   fx, fy, cx, cy, xi, k1, k2, p1, p2
eucm                      fx, fy, cx, cy, alpha, beta
double_sphere             fx, fy, cx, cy, xi, alpha
scaramuzza                cx, cy, c, d, e, a0, a1, ..., aN
equirectangular           fx, fy, cx, cy
fov                       fx, fy, cx, cy, omega
division                  fx, fy, cx, cy, k
opencv                    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4
thin_prism_fisheye        fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1
fisheye624                fx, fy, cx, cy, k0, k1, k2, k3, k4, k5, p0, p1, s0, s1, s2, s3
woodscape                 cx, cy, aspect_ratio, k1, k2, k3, k4
========================= ==============================================================
"""

from __future__ import annotations

from ._base import CameraModel
from .camera import Camera, load_all, read_woodscape
from .export import FORMATS, write_camera
from .readers import READ_FORMATS
from .registry import MODELS, get_model
from .unified import unified_from_mirror
from .woodscape_files import write_woodscape

__all__ = ["Camera", "CameraModel", "FORMATS", "MODELS", "READ_FORMATS", "get_model", "load_all",
           "read_woodscape", "unified_from_mirror", "write_camera", "write_woodscape"]


def __getattr__(name: str):
    """A submodule on first use (``ot.cameras.presets`` without importing it first: the
    package's top level loads lazily, so nothing else may have imported it)."""
    import importlib
    import importlib.util

    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}"):
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
