"""OpenEXR depth maps: one float32 channel per file, written atomically.

Uses the OpenEXR 3.x Python bindings (``import OpenEXR``; ``OpenEXR.File(header, channels)``
and ``.write(path)`` to write, ``OpenEXR.File(path, separate_channels=True).channels()`` to
read). Depth is stored as 32-bit float (``FLOAT`` pixels, ZIP compression, lossless), so a
round trip is bit-exact, ``inf`` (sky, no hit) and ``0`` included. Which quantity the channel
holds (planar ``depth``, ``z`` or ``range``, metres) is the caller's business: these functions
only move arrays.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .atomic import atomic_path

__all__ = ["read_exr", "write_exr", "DEFAULT_CHANNEL"]

#: Channel written by default: ``Z``, the OpenEXR name for depth.
DEFAULT_CHANNEL = "Z"

#: Channels tried, in order, by `read_exr` when the file has several and none is named.
_PREFERRED = ("Z", "depth", "Y", "R")


def _openexr():
    try:
        import OpenEXR
    except ImportError as err:  # pragma: no cover - a dependency of the project
        raise ImportError("OpenEXR depth I/O needs the OpenEXR Python bindings "
                          "(pip install OpenEXR)") from err
    return OpenEXR


def _as_float32_2d(depth: object) -> np.ndarray:
    if isinstance(depth, Tensor):
        if depth.dtype != torch.float32:
            raise TypeError(f"depth: expected a float32 tensor, got {depth.dtype}")
        array = depth.detach().cpu().numpy()
    elif isinstance(depth, np.ndarray):
        if depth.dtype != np.float32:
            raise TypeError(f"depth: expected a float32 array, got {depth.dtype}")
        array = depth
    else:
        raise TypeError(f"depth: expected a float32 torch.Tensor or numpy array, got "
                        f"{type(depth).__name__}")
    if array.ndim != 2:
        raise ValueError(f"depth: expected shape (H, W), got {tuple(array.shape)}")
    if array.shape[0] < 1 or array.shape[1] < 1:
        raise ValueError(f"depth: expected a non-empty image, got {tuple(array.shape)}")
    return np.ascontiguousarray(array)


def write_exr(path: str | os.PathLike, depth: Tensor | np.ndarray, *,
              channel: str = DEFAULT_CHANNEL) -> Path:
    """Write a ``(H, W)`` float32 map as a one-channel OpenEXR file, atomically.

    The file is written to a temporary file in the target's folder (created if missing), then
    moved over ``path`` with ``os.replace``: an interrupted run leaves the old file or the new
    one, never half of one, and no temporary file.

    Args:
        path: the ``.exr`` file to write; an existing file is replaced.
        depth: ``(H, W)`` float32 tensor (any device; detached) or numpy array. ``inf`` and
            ``nan`` are stored as they are.
        channel: the channel's name (default ``"Z"``).

    Returns:
        The path written.
    """
    if not isinstance(channel, str) or not channel:
        raise ValueError(f"channel: expected a non-empty string, got {channel!r}")
    array = _as_float32_2d(depth)
    OpenEXR = _openexr()
    path = Path(path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, suffix=".tmp.exr") as tmp:
        try:
            OpenEXR.File(header, {channel: array}).write(str(tmp))
        except RuntimeError as err:   # OpenEXR words an operating-system error in a message
            for code in (errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EROFS, errno.EIO):
                if os.strerror(code) in str(err):
                    raise OSError(code, os.strerror(code), str(path)) from err
            raise
    return path


def exr_channels(path: str | os.PathLike) -> list[str]:
    """Names of the channels of an OpenEXR file (header only)."""
    OpenEXR = _openexr()
    path = _check_readable(path)
    try:
        header = OpenEXR.File(str(path), header_only=True).header()
    except RuntimeError as err:
        raise ValueError(f"{path}: not a readable OpenEXR file ({err})") from None
    return [c.name for c in header["channels"]]


def _check_readable(path: str | os.PathLike) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such OpenEXR file")
    return path


def read_exr(path: str | os.PathLike, channel: str | None = None) -> Tensor:
    """Read one channel of an OpenEXR file as a ``(H, W)`` float32 tensor.

    Args:
        path: the ``.exr`` file.
        channel: the channel to read. Default: the only channel of a one-channel file, else
            the first of ``Z``, ``depth``, ``Y``, ``R`` present.

    Returns:
        ``(H, W)`` float32 CPU tensor. Half-float channels are widened to float32 (exactly);
        unsigned-int channels raise ``TypeError`` (they are not depth).

    Raises:
        FileNotFoundError: no such file. ValueError: not an OpenEXR file, or the channel is
        missing (the message lists the channels there). TypeError: a non-float channel.
    """
    OpenEXR = _openexr()
    path = _check_readable(path)
    if channel is not None and (not isinstance(channel, str) or not channel):
        raise ValueError(f"channel: expected a non-empty string or None, got {channel!r}")
    try:
        exr = OpenEXR.File(str(path), separate_channels=True)
    except RuntimeError as err:
        raise ValueError(f"{path}: not a readable OpenEXR file ({err})") from None
    channels = exr.channels()
    names = sorted(channels)
    if channel is None:
        if len(names) == 1:
            channel = names[0]
        else:
            channel = next((c for c in _PREFERRED if c in channels), None)
            if channel is None:
                raise ValueError(f"{path}: several channels {names} and none of "
                                 f"{list(_PREFERRED)}: name the one to read")
    elif channel not in channels:
        raise ValueError(f"{path}: no channel {channel!r}; the file has {names}")
    pixels = np.asarray(channels[channel].pixels)
    if pixels.dtype == np.float16:
        pixels = pixels.astype(np.float32)
    elif pixels.dtype != np.float32:
        raise TypeError(f"{path}: channel {channel!r} holds {pixels.dtype} pixels, expected "
                        "float32 or float16")
    if pixels.ndim != 2:
        raise ValueError(f"{path}: channel {channel!r} has shape {tuple(pixels.shape)}, "
                         "expected (H, W)")
    return torch.from_numpy(np.array(pixels, dtype=np.float32, copy=True))
