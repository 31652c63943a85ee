"""omniscape_torch: omnidirectional image synthesis in PyTorch.

Import as ``import omniscape_torch as ot``. Importing has no side effects.
"""

from . import augment, calibration, cameras, cubemap, datasets, io, presets, ride, scenes, sizing
from .cameras import Camera
from .datasets import CubemapCaptureDataset, OmniDataset
from .projection import OmniProjection
from .reproject import equirect_to_cubemap, equirectangular_camera, reproject
from .rig import StereoRig
from .sizing import required_face_size, visible_faces

__version__ = "0.1.0"

__all__ = ["Camera", "CubemapCaptureDataset", "augment", "calibration", "OmniDataset", "OmniProjection", "datasets", "StereoRig", "cameras", "cubemap", "equirect_to_cubemap",
           "equirectangular_camera", "io", "presets", "reproject", "required_face_size", "ride", "scenes", "sizing",
           "visible_faces"]
