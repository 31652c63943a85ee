"""The registry of camera models."""

from __future__ import annotations

from ._base import CameraModel
from .equirectangular import EQUIRECTANGULAR
from .fisheye import FISHEYE624, THIN_PRISM_FISHEYE
from .perspective import DIVISION, FOV, OPENCV
from .pinhole import PINHOLE
from .radial import EQUIDISTANT, EQUISOLID, KANNALA_BRANDT, ORTHOGRAPHIC, STEREOGRAPHIC
from .scaramuzza import SCARAMUZZA
from .unified import DOUBLE_SPHERE, EUCM, UNIFIED
from .woodscape import WOODSCAPE

#: The registry: model name -> ``CameraModel``, in DESIGN.md's order.
MODELS: dict[str, CameraModel] = {m.name: m for m in (
    PINHOLE, EQUIDISTANT, EQUISOLID, STEREOGRAPHIC, ORTHOGRAPHIC, KANNALA_BRANDT, UNIFIED, EUCM,
    DOUBLE_SPHERE, SCARAMUZZA, EQUIRECTANGULAR, FOV, DIVISION, OPENCV, THIN_PRISM_FISHEYE,
    FISHEYE624, WOODSCAPE)}


def get_model(name: str | CameraModel) -> CameraModel:
    """The registered model called ``name`` (a ``CameraModel`` is returned as it is)."""
    if isinstance(name, CameraModel):
        return name
    if not isinstance(name, str):
        raise TypeError(f"model: expected a model name or CameraModel, got {type(name).__name__}")
    try:
        return MODELS[name]
    except KeyError:
        raise ValueError(f"model: unknown camera model {name!r}; expected one of "
                         f"{', '.join(MODELS)}") from None
