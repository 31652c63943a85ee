"""omniscape_torch: omnidirectional image synthesis in PyTorch.

Import as ``import omniscape_torch as ot``. Importing has no side effects. The packages, in the
order they may import each other (ARCHITECTURE.md): ``data`` (datasets), ``scenes`` (the
built-in town and the ride), ``calibration``, ``augment`` (the augmentation modules),
``render`` (the layer, reprojection and the kernel boundary),
``cubemap``, ``cameras``, ``io``.

The names below load on first use (PEP 562), the whole package at once as an eager import
would: `import omniscape_torch.cli` then parses a command line without importing torch, so
`omniscape-torch --help` answers at once.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

#: The public names of the top level: name -> (module, attribute; None for the module itself).
_PUBLIC = {
    "augment": (".augment", None),
    "calibration": (".calibration", None),
    "cameras": (".cameras", None),
    "cubemap": (".cubemap", None),
    "data": (".data", None),
    "io": (".io", None),
    "render": (".render", None),
    "scenes": (".scenes", None),
    "Camera": (".cameras", "Camera"),
    "presets": (".cameras.presets", None),
    "datasets": (".data.datasets", None),
    "CubemapCaptureDataset": (".data.datasets", "CubemapCaptureDataset"),
    "OmniDataset": (".data.datasets", "OmniDataset"),
    "sizing": (".render.sizing", None),
    "OmniProjection": (".render.layer", "OmniProjection"),
    "equirect_to_cubemap": (".render.reproject", "equirect_to_cubemap"),
    "equirectangular_camera": (".render.reproject", "equirectangular_camera"),
    "reproject": (".render.reproject", "reproject"),
    "StereoRig": (".render.rig", "StereoRig"),
    "required_face_size": (".render.sizing", "required_face_size"),
    "visible_faces": (".render.sizing", "visible_faces"),
    "ride": (".scenes.ride", None),
}

__all__ = sorted(_PUBLIC)

if TYPE_CHECKING:   # the same names for type checkers and the docs' static reading
    from . import augment, calibration, cameras, cubemap, data, io, render, scenes
    from .cameras import Camera, presets
    from .data import datasets
    from .data.datasets import CubemapCaptureDataset, OmniDataset
    from .render import sizing
    from .render.layer import OmniProjection
    from .render.reproject import equirect_to_cubemap, equirectangular_camera, reproject
    from .render.rig import StereoRig
    from .render.sizing import required_face_size, visible_faces
    from .scenes import ride


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'omniscape_torch' has no attribute {name!r}")
    namespace = globals()
    for key, (module, attribute) in _PUBLIC.items():   # all of them, as the eager import did
        value = importlib.import_module(module, __name__)
        namespace[key] = value if attribute is None else getattr(value, attribute)
    return namespace[name]


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
