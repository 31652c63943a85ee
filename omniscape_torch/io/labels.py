"""Semantic labels: CARLA's 13 classes of the OmniScape paper, their palette, conversions.

Ids 0..12 and colours are CARLA's ``CITYSCAPES_PALETTE_MAP`` of its 13-class label set
(carla-simulator/carla, ``LibCarla/source/carla/image/CityScapesPalette.h``, CARLA 0.9.0 to
0.9.9, e.g. commit 1be6b86c5098b0082cba9320963f84076fdbd6cb), the version of the OmniScape
dataset. CARLA 0.9.10 and later renumbered the tags and recoloured Fence (100, 40, 40) and Other
(55, 90, 80); those colours are not used here. Pixels outside a camera's valid area get
``IGNORE_INDEX``.

The OmniScape demo frames draw the ego motorcycle in (0, 0, 228), outside this palette (close
to Cityscapes' motorcycle, (0, 0, 230)): `palette_to_labels` maps it to its nearest colour,
Vehicle (0, 0, 142), at distance 86, or to ``IGNORE_INDEX`` with ``max_distance`` below that.
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
    # np.take, not table[idx]: a third of the time on a 1024 x 1024 image
    if labels.dtype == np.uint8:   # a table of all 256 ids: no range check
        table = np.tile(np.array(IGNORE_COLOUR, dtype=np.uint8), (256, 1))
        table[:min(len(palette), 256)] = palette[:256]
        return np.take(table, labels, axis=0)
    table = np.vstack([palette, np.array([IGNORE_COLOUR], dtype=np.uint8)])
    idx = np.where((labels >= 0) & (labels < len(palette)), labels, len(palette))
    return np.take(table, idx, axis=0)


def palette_to_labels(rgb: Tensor | np.ndarray, palette: np.ndarray = PALETTE,
                      max_distance: float | None = None) -> Tensor:
    """Class ids of an RGB label picture ``(..., 3)``: the nearest palette colour per pixel.

    Meant for label pictures whose colours were perturbed (the OmniScape demo GIFs are
    quantized and dithered). Pixels farther than ``max_distance`` (Euclidean, in 0..255 units)
    from every palette colour get ``IGNORE_INDEX``. Ties go to the lower id. Distances are
    computed once per distinct colour (a few hundred in a GIF frame), not once per pixel.

    Args:
        rgb: ``(..., 3)`` RGB in 0..255, integer dtype (numpy array or tensor), e.g.
            ``(H, W, 3)`` uint8.
        palette: ``(K, 3)`` colours of ids ``0..K-1``.
        max_distance: optional largest accepted distance to a palette colour.

    Returns:
        ``(...)`` int64 tensor.
    """
    if isinstance(rgb, Tensor):
        rgb = rgb.detach().cpu().numpy()
    rgb = np.asarray(rgb)
    if rgb.ndim < 1 or rgb.shape[-1] != 3:
        raise ValueError(f"rgb: expected an (..., 3) RGB picture, got shape {rgb.shape}")
    if not np.issubdtype(rgb.dtype, np.integer):
        raise TypeError(f"rgb: expected integer colours in 0..255, got {rgb.dtype}")
    if rgb.size and (rgb.min() < 0 or rgb.max() > 255):
        raise ValueError(f"rgb: colours must lie in 0..255, got {rgb.min()}..{rgb.max()}")
    palette = np.asarray(palette, np.int64).reshape(-1, 3)
    if len(palette) > IGNORE_INDEX:
        raise ValueError(f"palette: at most {IGNORE_INDEX} colours, got {len(palette)}")
    flat = rgb.reshape(-1, 3).astype(np.int32)
    codes = (flat[:, 0] << 16) | (flat[:, 1] << 8) | flat[:, 2]
    # a lookup table over the 2^24 colours, filled only for the colours present: O(pixels)
    present = np.zeros(1 << 24, dtype=bool)
    present[codes] = True
    colours = np.flatnonzero(present)
    rgb_of = np.stack((colours >> 16, (colours >> 8) & 255, colours & 255), axis=-1)
    dist2 = ((rgb_of[:, None, :] - palette[None]) ** 2).sum(-1)  # [distinct colours, K]
    ids = dist2.argmin(-1)
    if max_distance is not None:
        ids = np.where(dist2.min(-1) <= max_distance ** 2, ids, IGNORE_INDEX)
    lut = np.empty(1 << 24, dtype=np.uint8)
    lut[colours] = ids
    return torch.from_numpy(lut[codes].reshape(rgb.shape[:-1]).astype(np.int64))
