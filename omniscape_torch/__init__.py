"""omniscape_torch: omnidirectional image synthesis in PyTorch.

Import as ``import omniscape_torch as ot``. Importing has no side effects.
"""

from . import cameras, cubemap, io
from .cameras import Camera
from .projection import OmniProjection

__version__ = "0.1.0"

__all__ = ["Camera", "OmniProjection", "cameras", "cubemap", "io"]
