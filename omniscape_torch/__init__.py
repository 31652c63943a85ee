"""omniscape_torch: omnidirectional image synthesis in PyTorch.

Import as ``import omniscape_torch as ot``. Importing has no side effects. The packages, in the
order they may import each other (ARCHITECTURE.md): ``data`` (datasets), ``scenes`` (the
built-in town and the ride), ``calibration``, ``render`` (the layer and what is built on it),
``cubemap``, ``cameras``, ``io``.
"""

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

__version__ = "0.1.0"

__all__ = ["Camera", "CubemapCaptureDataset", "OmniDataset", "OmniProjection", "StereoRig",
           "augment", "calibration", "cameras", "cubemap", "data", "datasets",
           "equirect_to_cubemap", "equirectangular_camera", "io", "presets", "render",
           "reproject", "required_face_size", "ride", "scenes", "sizing", "visible_faces"]
