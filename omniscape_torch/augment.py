"""The augmentation modules, importable as a module (DESIGN.md): ``from omniscape_torch.augment
import RandomOmniCamera``, or ``ot.augment.RandomOmniCamera`` after ``import omniscape_torch as
ot``. Their code lives in :mod:`omniscape_torch.render.augment` (the layer's package); the names
here are the same objects."""

from .render.augment import (FISHEYE_MODELS, MODES, ApplyToKey, RandomOmniCamera,
                             RandomReproject)
from .render.adapters import to_albumentations

__all__ = ["ApplyToKey", "FISHEYE_MODELS", "MODES", "RandomOmniCamera", "RandomReproject",
           "to_albumentations"]
