"""Semantic labels: CARLA's 13 classes of the OmniScape paper, their palette, conversions.

Ids 0..12 and colours are CARLA's ``CITYSCAPES_PALETTE_MAP`` of its 13-class label set
(``LibCarla/source/carla/image/CityScapesPalette.h``, CARLA 0.9.0 to 0.9.9, the version of the
OmniScape dataset). Pixels outside a camera's valid area get ``IGNORE_INDEX``.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

CLASSES = ("Unlabeled", "Building", "Fence", "Other", "Pedestrian", "Pole", "RoadLine", "Road",
           "Sidewalk", "Vegetation", "Vehicle", "Wall", "TrafficSign")

#: (13, 3) uint8 RGB colour of each class id.
PALETTE = np.array([
    (0, 0, 0), (70, 70, 70), (190, 153, 153), (250, 170, 160), (220, 20, 60),
    (153, 153, 153), (157, 234, 50), (128, 64, 128), (244, 35, 232), (107, 142, 35),
    (0, 0, 142), (102, 102, 156), (220, 220, 0)], dtype=np.uint8)
PALETTE.setflags(write=False)

IGNORE_INDEX = 255
#: Colour drawn for ``IGNORE_INDEX`` and any id outside the palette.
IGNORE_COLOUR = (255, 255, 255)


def colorize(labels: Tensor | np.ndarray, palette: np.ndarray = PALETTE) -> np.ndarray:
    """RGB picture of integer ``labels (..., H, W)``: ``(..., H, W, 3)`` uint8; ids outside the
    palette (``IGNORE_INDEX``) are drawn white."""
    if isinstance(labels, Tensor):
        labels = labels.detach().cpu().numpy()
    labels = np.asarray(labels)
    if not np.issubdtype(labels.dtype, np.integer):
        raise TypeError(f"labels: expected integer class ids, got {labels.dtype}")
    table = np.vstack([palette, np.array([IGNORE_COLOUR], dtype=np.uint8)])
    idx = np.where((labels >= 0) & (labels < len(palette)), labels, len(palette))
    return table[idx]


def palette_to_labels(rgb: Tensor | np.ndarray, palette: np.ndarray = PALETTE,
                      max_distance: float | None = None) -> Tensor:
    """Class ids of an RGB label picture ``(H, W, 3)``: the nearest palette colour per pixel.

    Meant for label pictures whose colours were perturbed (the OmniScape demo GIFs are
    quantized and dithered). Pixels farther than ``max_distance`` (Euclidean, in 0..255 units)
    from every palette colour get ``IGNORE_INDEX``.

    Returns:
        ``(H, W)`` int64 tensor.
    """
    if isinstance(rgb, Tensor):
        rgb = rgb.detach().cpu().numpy()
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise ValueError(f"rgb: expected an (H, W, 3) picture, got shape {rgb.shape}")
    diff = rgb[:, :, None, :].astype(np.int32) - np.asarray(palette, np.int32)[None, None]
    dist2 = (diff * diff).sum(-1)
    ids = dist2.argmin(-1)
    if max_distance is not None:
        ids = np.where(dist2.min(-1) <= max_distance ** 2, ids, IGNORE_INDEX)
    return torch.from_numpy(ids.astype(np.int64))
