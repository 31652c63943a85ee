"""CARLA sensor images: depth decoding, semantic tags, and label-set conversion.

What CARLA's cameras give (CARLA "Sensors reference", ``ref_sensors.md``):

* **Depth camera** (``sensor.camera.depth``): planar depth (along the camera's optical axis,
  the distance a pinhole "depth" is, *not* the range along the ray) packed into 24 bits of the
  R, G and B channels, R the least significant byte::

      normalized = (R + G * 256 + B * 256 * 256) / (256 ** 3 - 1)
      depth_m    = 1000 * normalized

  so depth is quantised in steps of 1000 / (2**24 - 1) m (about 0.06 mm) up to the far plane
  at 1000 m, which is what the sky (no hit) decodes to.
* **Semantic segmentation camera** (``sensor.camera.semantic_segmentation``) with the ``Raw``
  converter: the class tag in the red channel (G = B = 0).
* **Instance segmentation camera** (``sensor.camera.instance_segmentation``, CARLA 0.9.14 and
  later): the class tag in the red channel, as the semantic camera's, and the object's id in
  green (low byte) and blue (high byte): ``id = G + 256 B``
  (`decode_instances`).

The server hands images over as ``BGRA`` bytes (``np.frombuffer(image.raw_data, np.uint8)
.reshape(H, W, 4)``); ``image.save_to_disk`` writes a PNG whose channels are in their proper
places, which `omniscape_torch.io.read_image` returns in ``RGB`` order. Both orders are
accepted here through ``channel_order``.

Label sets, by CARLA version:

* ``"13"``: ids 0..12 of CARLA 0.9.0 to 0.9.9, the OmniScape paper's classes
  (`omniscape_torch.io.labels.CLASSES`): the package's own classes, identity.
* ``"23"``: CARLA 0.9.10 to 0.9.13 kept ids 0..12 and appended 13 Sky, 14 Ground, 15 Bridge,
  16 RailTrack, 17 GuardRail, 18 TrafficLight, 19 Static, 20 Dynamic, 21 Water, 22 Terrain
  (the tag table of those versions' sensor docs): `EXT23_TO_13`.
* ``"new"``: later CARLA reordered the tags to Cityscapes' ids,
  ``LibCarla/source/carla/rpc/ObjectLabel.h`` (``enum class CityObjectLabel``): 0 None, 1 Roads,
  2 Sidewalks, 3 Buildings, 4 Walls, 5 Fences, 6 Poles, 7 TrafficLight, 8 TrafficSigns,
  9 Vegetation, 10 Terrain, 11 Sky, 12 Pedestrians, 13 Rider, 14 Car, 15 Truck, 16 Bus,
  17 Train, 18 Motorcycle, 19 Bicycle, 20 Static, 21 Dynamic, 22 Other, 23 Water,
  24 RoadLines, 25 Ground, 26 Bridge, 27 RailTrack, 28 GuardRail (255 = Any, a query value,
  never a pixel): `NEW_TO_13`.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import torch
from torch import Tensor

from .labels import CLASSES

__all__ = [
    "CHANNEL_ORDERS",
    "DEPTH_FAR",
    "EXT23_TO_13",
    "LABEL_SETS",
    "NEW_CLASSES",
    "NEW_TO_13",
    "decode_depth",
    "decode_instances",
    "decode_labels",
    "encode_depth",
    "map_labels",
    "mapping_table",
    "to_13",
]

#: Far plane of CARLA's depth camera, metres: what 24-bit white (the sky) decodes to.
DEPTH_FAR = 1000.0
_SCALE = 256 ** 3 - 1

#: Accepted ``channel_order`` values; where R, G, B sit in the last axis of an image.
CHANNEL_ORDERS = {"BGRA": (2, 1, 0), "BGR": (2, 1, 0), "RGB": (0, 1, 2), "RGBA": (0, 1, 2)}

_C = {name: i for i, name in enumerate(CLASSES)}

#: Names of the ids of the recent (Cityscapes-ordered) CARLA tag set, ``ObjectLabel.h``.
NEW_CLASSES = ("None", "Roads", "Sidewalks", "Buildings", "Walls", "Fences", "Poles",
               "TrafficLight", "TrafficSigns", "Vegetation", "Terrain", "Sky", "Pedestrians",
               "Rider", "Car", "Truck", "Bus", "Train", "Motorcycle", "Bicycle", "Static",
               "Dynamic", "Other", "Water", "RoadLines", "Ground", "Bridge", "RailTrack",
               "GuardRail")

#: CARLA tag names -> the 13-class name each becomes, one choice per tag name for both later
#: tag sets (``"23"`` and ``"new"`` name their shared tags alike); a tag whose name is a class
#: of the 13 (``Vegetation``, ``Other``, and ids 0..12 of ``"23"``) is that class.
_TAG_CHOICES: dict[str, tuple[str, ...]] = {
    "Unlabeled": ("None",
                  "Sky"),           # the old set has no sky; it rendered as Unlabeled there
    "Road": ("Roads",),
    "Sidewalk": ("Sidewalks",),
    "Building": ("Buildings",
                 "Bridge"),         # a construction (Cityscapes' "construction" group)
    "Wall": ("Walls",),
    "Fence": ("Fences",
              "GuardRail"),         # a roadside barrier, like a fence
    "Pole": ("Poles",),
    # TrafficLight: the 13-class set has no traffic light; a signal like a sign (0.9.10 split
    # TrafficLight out of it)
    "TrafficSign": ("TrafficSigns", "TrafficLight"),
    "Vegetation": ("Terrain",),     # grass and soil, Cityscapes' "nature" group with vegetation
    "Pedestrian": ("Pedestrians",
                   "Rider"),        # a person (the old set has no rider)
    "Vehicle": ("Car", "Truck", "Bus", "Train", "Motorcycle", "Bicycle"),
    "RoadLine": ("RoadLines",),
    "Other": ("Static",             # props, the old set's "Other"
              "Dynamic",            # movable props
              "Water",
              "Ground",             # horizontal ground that is neither road nor sidewalk
              "RailTrack"),
}
_TAG_TO_CLASS = {tag: _C[cls] for cls, tags in _TAG_CHOICES.items() for tag in tags}


def _tags_to_13(names: tuple[str, ...]) -> dict[int, int]:
    """``{tag id: class id}`` of a tag set given by its tag names in id order."""
    return {i: _C[name] if name in _C else _TAG_TO_CLASS[name] for i, name in enumerate(names)}


#: Recent CARLA tags (``ObjectLabel.h``) -> the 13 classes (the choice for each tag name:
#: ``_TAG_CHOICES``).
NEW_TO_13: dict[int, int] = _tags_to_13(NEW_CLASSES)

#: CARLA 0.9.10-0.9.13 tags (ids 0..12 as the 13-class set, 13..22 appended) -> the 13 classes.
EXT23_TO_13: dict[int, int] = _tags_to_13(
    CLASSES + ("Sky", "Ground", "Bridge", "RailTrack", "GuardRail", "TrafficLight", "Static",
               "Dynamic", "Water", "Terrain"))

#: ``label_set`` name -> mapping to the 13 classes.
LABEL_SETS: dict[str, dict[int, int]] = {
    "13": _tags_to_13(CLASSES),
    "23": EXT23_TO_13,
    "new": NEW_TO_13,
}


def _as_uint8_image(image: object, name: str) -> np.ndarray:
    if isinstance(image, Tensor):
        image = image.detach().cpu().numpy()
    if not isinstance(image, np.ndarray):
        raise TypeError(f"{name}: expected a uint8 numpy array or tensor, got "
                        f"{type(image).__name__}")
    if image.dtype != np.uint8:
        raise TypeError(f"{name}: expected uint8 pixels, got {image.dtype}")
    if image.ndim != 3 or image.shape[-1] not in (3, 4):
        raise ValueError(f"{name}: expected an (H, W, 3) or (H, W, 4) image, got shape "
                         f"{tuple(image.shape)}")
    return image


def _rgb_index(channel_order: str) -> tuple[int, int, int]:
    if channel_order not in CHANNEL_ORDERS:
        raise ValueError(f"channel_order: expected one of {tuple(CHANNEL_ORDERS)}, got "
                         f"{channel_order!r}")
    return CHANNEL_ORDERS[channel_order]


def decode_depth(image: Tensor | np.ndarray, channel_order: str = "BGRA") -> Tensor:
    """Planar depth in metres of a CARLA depth-camera image.

    Args:
        image: ``(H, W, 3)`` or ``(H, W, 4)`` uint8, as CARLA sends it (``"BGRA"``, the
            default: ``raw_data``) or as `read_image` reads a saved
            PNG (``"RGB"``).
        channel_order: ``"BGRA"``, ``"BGR"``, ``"RGB"`` or ``"RGBA"``.

    Returns:
        ``(H, W)`` float32 tensor: ``1000 (R + 256 G + 65536 B) / (2**24 - 1)`` metres, the
        distance along the camera's axis (1000 m, the far plane, where nothing was hit).
    """
    ri, gi, bi = _rgb_index(channel_order)
    image = _as_uint8_image(image, "image")
    code = (image[..., ri].astype(np.float64) + image[..., gi].astype(np.float64) * 256.0
            + image[..., bi].astype(np.float64) * 65536.0)
    return torch.from_numpy((code * (DEPTH_FAR / _SCALE)).astype(np.float32))


def encode_depth(depth: Tensor | np.ndarray, channel_order: str = "RGB") -> np.ndarray:
    """Inverse of `decode_depth` (nearest code): ``(H, W)`` metres -> ``(H, W, 3)``
    uint8 (``(H, W, 4)`` with alpha 255 for a 4-channel order). Depth is clipped to
    ``[0, 1000]`` m. For writing CARLA-like test data."""
    ri, gi, bi = _rgb_index(channel_order)
    if isinstance(depth, Tensor):
        depth = depth.detach().cpu().numpy()
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth: expected (H, W), got shape {depth.shape}")
    code = np.rint(np.clip(np.nan_to_num(depth, nan=0.0, posinf=DEPTH_FAR), 0, DEPTH_FAR)
                   * (_SCALE / DEPTH_FAR)).astype(np.int64)
    out = np.zeros((*depth.shape, 4 if channel_order.endswith("A") else 3), np.uint8)
    out[..., ri] = code & 255
    out[..., gi] = (code >> 8) & 255
    out[..., bi] = (code >> 16) & 255
    if out.shape[-1] == 4:
        out[..., 3] = 255
    return out


def decode_labels(image: Tensor | np.ndarray, channel_order: str = "BGRA") -> Tensor:
    """CARLA class tags of a raw semantic-segmentation image: its red channel.

    Args:
        image: ``(H, W, 3 | 4)`` uint8 (``Raw`` converter, not ``CityScapesPalette``).
        channel_order: where red is: ``"BGRA"`` / ``"BGR"`` (index 2) or ``"RGB"`` /
            ``"RGBA"`` (index 0).

    Returns:
        ``(H, W)`` int64 tensor of the simulator's tags (map them with `to_13`).
    """
    ri = _rgb_index(channel_order)[0]
    image = _as_uint8_image(image, "image")
    return torch.from_numpy(image[..., ri].astype(np.int64))


def decode_instances(image: Tensor | np.ndarray, channel_order: str = "BGRA"
                     ) -> tuple[Tensor, Tensor]:
    """CARLA class tags and object ids of an instance-segmentation image.

    Args:
        image: ``(H, W, 3 | 4)`` uint8, as CARLA sends it (``"BGRA"``) or a saved PNG as
            read (``"RGB"``).
        channel_order: ``"BGRA"``, ``"BGR"``, ``"RGB"`` or ``"RGBA"``.

    Returns:
        ``(tags, ids)``, two ``(H, W)`` int64 tensors: the red channel (the tag, as
        `decode_labels`) and ``G + 256 B`` (the object's id, 0..65535).
    """
    ri, gi, bi = _rgb_index(channel_order)
    image = _as_uint8_image(image, "image")
    tags = torch.from_numpy(image[..., ri].astype(np.int64))
    ids = torch.from_numpy(image[..., gi].astype(np.int64) + 256 * image[..., bi].astype(np.int64))
    return tags, ids


def mapping_table(mapping: Mapping[int, int], *, unknown: int | None = None) -> Tensor:
    """Look-up table ``(max_id + 1,)`` int64 of ``mapping``; ids absent from it hold
    ``unknown`` (or -1 to mark them as errors when ``unknown`` is None)."""
    if not mapping:
        raise ValueError("mapping: empty")
    keys = list(mapping)
    if any(isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 0 for k in keys):
        raise ValueError("mapping: keys must be non-negative ints")
    table = torch.full((max(keys) + 1,), -1 if unknown is None else int(unknown),
                       dtype=torch.int64)
    for k, v in mapping.items():
        table[int(k)] = int(v)
    return table


def map_labels(ids: Tensor | np.ndarray, mapping: Mapping[int, int], *,
               unknown: int | None = None) -> Tensor:
    """Map integer class ids through ``mapping`` (``{source_id: target_id}``).

    Args:
        ids: integer tensor or array of any shape.
        mapping: the mapping, e.g. `NEW_TO_13`.
        unknown: the id given to ids absent from ``mapping``; None (default) raises.

    Returns:
        int64 tensor of ``ids``' shape.

    Raises:
        ValueError: an id is not in ``mapping`` and ``unknown`` is None (names the ids).
    """
    if isinstance(ids, np.ndarray):
        ids = torch.from_numpy(ids)
    if not isinstance(ids, Tensor):
        raise TypeError(f"ids: expected an integer tensor or array, got {type(ids).__name__}")
    if ids.is_floating_point() or ids.is_complex() or ids.dtype == torch.bool:
        raise TypeError(f"ids: expected integer class ids, got {ids.dtype}")
    table = mapping_table(mapping, unknown=unknown).to(ids.device)
    ids = ids.long()
    inside = (ids >= 0) & (ids < table.numel())
    out = table[ids.clamp(0, table.numel() - 1)]
    fill = -1 if unknown is None else int(unknown)
    out = torch.where(inside, out, torch.full_like(out, fill))
    if unknown is None:
        bad = out < 0
        if bool(bad.any()):
            values = sorted(set(ids[bad].unique().tolist()))
            raise ValueError(f"ids: {values[:20]} not in the mapping (known ids: "
                             f"{sorted(mapping)[:40]}); pass unknown= to map them to a class")
    return out


def to_13(ids: Tensor | np.ndarray, label_set: str = "13", *,
          unknown: int | None = None) -> Tensor:
    """CARLA tags of ``label_set`` (``"13"``, ``"23"`` or ``"new"``) -> the 13 classes."""
    if label_set not in LABEL_SETS:
        raise ValueError(f"label_set: expected one of {tuple(LABEL_SETS)}, got {label_set!r}")
    return map_labels(ids, LABEL_SETS[label_set], unknown=unknown)
