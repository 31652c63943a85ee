"""Images on disk: 8-bit PNG/JPEG in and out (written atomically), and float conversion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .atomic import atomic_write_bytes


def require_cv2():
    """``cv2``, or an ImportError saying how to install it: images are read and written with
    OpenCV, an optional dependency (the ``calibration`` and ``dev`` extras install it)."""
    try:
        import cv2
    except ImportError:
        raise ImportError("reading and writing images needs OpenCV: pip install "
                          "opencv-contrib-python-headless (or the package's [calibration] "
                          "extra)") from None
    return cv2


def read_image(path: str | Path) -> Tensor:
    """``(H, W, 3)`` uint8 RGB (or ``(H, W)`` for a grey image) of a PNG or JPEG file."""
    cv2 = require_cv2()

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such image")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{path}: not an image OpenCV can read")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4
                             else cv2.COLOR_BGR2RGB)
    return torch.from_numpy(np.ascontiguousarray(image))


def write_image(path: str | Path, image: Tensor | np.ndarray) -> Path:
    """Write ``(H, W, 3)`` RGB or ``(H, W)`` grey uint8 (or uint16 PNG) atomically."""
    cv2 = require_cv2()

    if isinstance(image, Tensor):
        image = image.detach().cpu().numpy()
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"image: expected uint8 or uint16, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    elif image.ndim != 2:
        raise ValueError(f"image: expected (H, W, 3) or (H, W), got {image.shape}")
    path = Path(path)
    ok, data = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise ValueError(f"{path}: OpenCV cannot encode {path.suffix!r}")
    return atomic_write_bytes(path, data.tobytes())


def to_float(image: Tensor | np.ndarray, *, dtype: torch.dtype = torch.float32) -> Tensor:
    """``(H, W, C)`` or ``(H, W)`` uint8/uint16 -> ``(C, H, W)`` floating in [0, 1] (divided by
    255, or 65535 for uint16)."""
    if isinstance(image, np.ndarray):
        image = torch.from_numpy(image)
    scale = {torch.uint8: 255.0, torch.uint16: 65535.0}.get(image.dtype)
    if scale is None:
        raise TypeError(f"image: expected uint8 or uint16, got {image.dtype}")
    if image.dim() == 2:
        image = image.unsqueeze(-1)
    if image.dim() != 3:
        raise ValueError(f"image: expected (H, W, C) or (H, W), got {tuple(image.shape)}")
    # uint16 has few kernels in torch: widen before converting
    return image.permute(2, 0, 1).to(torch.int32).to(dtype) / scale
