"""Input and output: calibration files, and (later) images, depth and datasets.

I/O never leaks into the maths: these functions read and write, then call the pure functions.
"""

from .atomic import atomic_write_bytes, atomic_write_text
from .exr import exr_channels, read_exr, write_exr
from .images import read_image, to_float, write_image
from .labels import CLASSES, IGNORE_INDEX, PALETTE, colorize, palette_to_labels
from .readers import (list_cameras, list_frames, read_camera, read_camera_dict, read_dynamics,
                      read_extrinsics, read_frame, read_manifest)
from .calibration import (camera_from_dict, camera_to_dict, from_opencv_fisheye,
                          from_opencv_omnidir, load_json, read_ocamcalib, save_json,
                          to_opencv_fisheye, to_opencv_omnidir, write_ocamcalib)

__all__ = ["CLASSES", "IGNORE_INDEX", "PALETTE", "colorize", "exr_channels", "palette_to_labels",
           "read_exr", "read_image", "to_float", "write_exr", "write_image", "list_cameras",
           "list_frames", "read_camera", "read_camera_dict", "read_dynamics", "read_extrinsics",
           "read_frame", "read_manifest",
           "atomic_write_bytes", "atomic_write_text", "camera_from_dict", "camera_to_dict",
           "from_opencv_fisheye", "from_opencv_omnidir", "load_json", "read_ocamcalib",
           "save_json", "to_opencv_fisheye", "to_opencv_omnidir", "write_ocamcalib"]
