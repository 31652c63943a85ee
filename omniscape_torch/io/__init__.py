"""Files: atomic writes and their leftovers, images, OpenEXR depth, labels and their palette,
CARLA's encodings. A leaf: it imports no other package of ``omniscape_torch``.

Camera calibration formats are read and written by ``ot.Camera`` (``cameras/formats.py``), and
datasets by ``ot.data``.
"""

from .atomic import atomic_write_bytes, atomic_write_text
from .exr import exr_channels, read_exr, write_exr
from .images import read_image, to_float, write_image
from .labels import CLASSES, IGNORE_INDEX, PALETTE, colorize, palette_to_labels

__all__ = ["CLASSES", "IGNORE_INDEX", "PALETTE", "atomic_write_bytes", "atomic_write_text",
           "colorize", "exr_channels", "palette_to_labels", "read_exr", "read_image", "to_float",
           "write_exr", "write_image"]
