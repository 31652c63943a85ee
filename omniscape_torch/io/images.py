"""Images on disk: 8-bit PNG/JPEG and 16-bit grey PNG in and out (written atomically), and float
conversion. Read and written with Pillow (a requirement: ``benchmarks/bench_png.py`` measured it
against OpenCV's wheel, 7 against 61 MB); the pixels are those OpenCV read and wrote before."""

from __future__ import annotations

import io as _io
import re
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .atomic import atomic_write_bytes


#: zlib's settings for PNG: level 1 with the run-length strategy, OpenCV's defaults (the
#: library the images were written with before; ``benchmarks/bench_png.py``: the best of
#: Pillow's settings for speed, the size within a few percent of the default level 6's).
PNG_COMPRESS_LEVEL, PNG_STRATEGY = 1, 3   # 3: Z_RLE
#: JPEG quality: OpenCV's default (Pillow's is 75).
JPEG_QUALITY = 95


def require_pillow():
    """``PIL.Image``, or an ImportError saying how to install it: images are read and written
    with Pillow, a requirement of the package."""
    try:
        from PIL import Image
    except ImportError:
        raise ImportError("reading and writing images needs Pillow, a requirement of "
                          "omniscape_torch: pip install pillow") from None
    return Image


def _png_header(data: bytes) -> tuple[int, int] | None:
    """``(bit depth, colour type)`` of PNG bytes, None when they are not a PNG."""
    if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR" or len(data) < 26:
        return None
    return data[24], data[25]


def decode_image(data: bytes, name: str = "image") -> np.ndarray:
    """The pixels of PNG or JPEG bytes: ``(H, W, 3)`` RGB (an alpha channel dropped, a palette
    expanded) or ``(H, W)`` grey, uint8, or uint16 for a 16-bit PNG (a 16-bit colour PNG: ``(H, W, 3)`` uint16). ``name`` names the bytes
    in errors.

    A 16-bit PNG with colour or alpha (which Pillow reads as 8 bits) is read with OpenCV where
    it is installed, else refused (ValueError)."""
    Image = require_pillow()
    header = _png_header(data)
    if header is not None and header[0] == 16 and header[1] in (2, 4, 6):
        return _decode_png48(data, name)
    try:
        with Image.open(_io.BytesIO(data)) as im:
            im.load()
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                image = np.array(im)   # a copy: writable
                # "I" (int32) of a 16-bit grey file in older Pillow
                return image if image.dtype == np.uint16 else image.astype(np.uint16)
            if im.mode == "L":
                return np.asarray(im).copy()
            if im.mode == "1":
                return np.asarray(im.convert("L")).copy()
            return np.asarray(im.convert("RGB")).copy()   # alpha dropped, palette expanded
    except (OSError, SyntaxError, ValueError) as err:   # PIL.UnidentifiedImageError: OSError
        # Pillow names the buffer it read (<_io.BytesIO object at 0x...>): the file is named
        detail = re.sub(r"\s*<[^<>]* object at 0x[0-9a-fA-F]+>", "", str(err)).strip()
        raise ValueError(f"{name}: not an image Pillow can read ({detail or 'corrupt?'})"
                         ) from None


def _decode_png48(data: bytes, name: str) -> np.ndarray:
    """A 16-bit RGB(A) or grey-alpha PNG as 16-bit RGB, with OpenCV (Pillow reads 8 bits of
    it)."""
    try:
        import cv2
    except ImportError:
        raise ValueError(f"{name}: a 16-bit colour PNG; reading it needs OpenCV (pip install "
                         "opencv-contrib-python-headless)") from None
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{name}: not a PNG OpenCV can read")
    return np.ascontiguousarray(image[..., 2::-1])


def read_image(path: str | Path) -> Tensor:
    """``(H, W, 3)`` uint8 RGB (or ``(H, W)`` for a grey image; uint16 for a 16-bit PNG) of a
    PNG or JPEG file (`decode_image`)."""
    path = Path(path)
    require_pillow()
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such image")
    return torch.from_numpy(decode_image(path.read_bytes(), str(path)))


def encode_image(image: Tensor | np.ndarray, suffix: str = ".png") -> bytes:
    """The bytes of ``(H, W, 3)`` RGB or ``(H, W)`` grey uint8 (or grey uint16: PNG only) as the
    format of ``suffix`` (``.png``, ``.jpg``...). PNG: lossless, zlib level 1 with the
    run-length strategy; JPEG: quality 95 (both OpenCV's defaults)."""
    Image = require_pillow()
    if isinstance(image, Tensor):
        image = image.detach().cpu().numpy()
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"image: expected uint8 or uint16, got {image.dtype}")
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ValueError(f"image: expected (H, W, 3) or (H, W), got {image.shape}")
    image = np.ascontiguousarray(image)
    fmt = Image.registered_extensions().get((suffix or ".png").lower())
    if fmt is None:
        raise ValueError(f"{suffix!r}: not an image format Pillow writes")
    if image.dtype == np.uint16 and fmt != "PNG":
        raise ValueError(f"{suffix!r}: 16-bit images are written as PNG only")
    if image.dtype == np.uint16 and image.ndim == 3:
        # nothing in the package writes them; Pillow writes 16 bits of grey only
        raise ValueError("image: 16-bit colour is not written (Pillow writes 16-bit PNG for "
                         "grey images only): write each channel as a grey PNG, or floats "
                         "as OpenEXR (ot.io.exr)")
    buf = _io.BytesIO()
    options = {"PNG": {"compress_level": PNG_COMPRESS_LEVEL, "compress_type": PNG_STRATEGY},
               "JPEG": {"quality": JPEG_QUALITY}}.get(fmt, {})
    Image.fromarray(image).save(buf, format=fmt, **options)
    return buf.getvalue()


def write_image(path: str | Path, image: Tensor | np.ndarray) -> Path:
    """Write ``(H, W, 3)`` RGB or ``(H, W)`` grey uint8 (or grey uint16 PNG) atomically, in the
    format of the file's suffix (`encode_image`)."""
    path = Path(path)
    return atomic_write_bytes(path, encode_image(image, path.suffix or ".png"))


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
