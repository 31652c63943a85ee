"""The objects of an instance map: their tight boxes, classes and pixel counts, as
``generate`` and ``convert`` write them (``objects/NNNNNN.json``, ``<camera>_objects.json``)
and the readers return them.

An object is one instance id of the map (0 is none). Its box is the tight box of its pixels,
in torchvision's XYXY corner convention (``DESIGN.md``): the pixel columns ``u0..u1`` and rows
``v0..v1`` it covers give ``[x0, y0, x1, y1] = [u0, v0, u1 + 1, v1 + 1]``. Computed from the
map itself, the boxes are exact by construction; its class is the label most of its pixels
have (an instance of the built-in town has one class on all of them).

The file is a JSON list, one object a line, sorted by instance id::

    [{"instance_id": 3, "label": 10, "class": "Vehicle", "box": [12, 30, 41, 52], "pixels": 517},
     ...]

Read back (:func:`decode_objects`) as tensors: ``boxes (N, 4)`` float32, ``box_labels (N,)``
int64 and ``box_instance_ids (N,)`` int64, the keys the augmentation takes.
"""

from __future__ import annotations

import json
import math

import numpy as np
import torch
from torch import Tensor

from ..io.labels import CLASSES
from ..render.detection import instance_boxes

__all__ = ["INSTANCE_SHIFT", "decode_objects", "encode_objects", "instance_image",
           "instance_objects", "pack_instances", "unpack_instances"]

#: The writers sample labels and instance ids in one nearest pass of the layer, as one integer
#: map ``labels + INSTANCE_SHIFT * instances`` (labels 0..255): never blended, and the ignore
#: index (255) outside the valid area unpacks to label 255 and instance 0.
INSTANCE_SHIFT = 256

#: Label values counted per instance (class ids 0..12 and the ignore index 255).
_LABEL_RANGE = 256


def instance_objects(instances: Tensor, labels: Tensor, *, min_pixels: int = 1) -> list[dict]:
    """The objects of an instance map.

    Args:
        instances: ``(H, W)`` integer instance ids, 0 for none.
        labels: ``(H, W)`` integer class ids (0..12; values outside 0..255 count as 255).
        min_pixels: objects of fewer pixels are left out (their ids stay in the map); 1, the
            default: every object.

    Returns:
        A list sorted by instance id of ``{"instance_id", "label", "class", "box": [x0, y0,
        x1, y1], "pixels"}``: each id's most frequent label (the smallest on a tie) and its
        name (``"unknown"`` past the 13 classes), the tight box of its pixels (XYXY corners,
        module docstring) and their count.

    Raises:
        TypeError: not integer maps. ValueError: shapes that are not one ``(H, W)``, or
            negative ids, or ``min_pixels`` not a positive integer.
    """
    if isinstance(min_pixels, bool) or not isinstance(min_pixels, int) or min_pixels < 1:
        raise ValueError(f"min_pixels: expected a positive integer, got {min_pixels!r}")
    for name, t in (("instances", instances), ("labels", labels)):
        if not isinstance(t, Tensor) or t.is_floating_point() or t.is_complex() or \
                t.dtype == torch.bool:
            raise TypeError(f"{name}: expected an integer tensor, got "
                            f"{getattr(t, 'dtype', type(t).__name__)}")
    if instances.dim() != 2 or labels.shape != instances.shape:
        raise ValueError(f"instances, labels: expected two (H, W) maps, got "
                         f"{tuple(instances.shape)} and {tuple(labels.shape)}")
    # numpy, on one thread (as pack_instances): a few milliseconds for an image
    ids = instances.detach().cpu().reshape(-1).numpy().astype(np.int64)
    if ids.size and int(ids.min()) < 0:
        raise ValueError("instances: ids must be >= 0 (0: none)")
    where = np.flatnonzero(ids > 0)
    if where.size == 0:
        return []
    unique, index = np.unique(ids[where], return_inverse=True)
    n = unique.size
    lab = labels.detach().cpu().reshape(-1).numpy()[where].astype(np.int64)
    lab = np.where((lab >= 0) & (lab < _LABEL_RANGE), lab, _LABEL_RANGE - 1)
    counts = np.bincount(index * _LABEL_RANGE + lab, minlength=n * _LABEL_RANGE)
    label = counts.reshape(n, _LABEL_RANGE).argmax(1)   # the first of equal counts
    # the tight boxes as the augmentation's exact mode computes them (every id has a pixel)
    boxes = instance_boxes(instances.detach().cpu().reshape(1, *instances.shape),
                           [torch.from_numpy(unique)])[0][0].long()
    pixels = np.bincount(index, minlength=n)
    return [{"instance_id": int(i), "label": int(c),
             "class": CLASSES[c] if c < len(CLASSES) else "unknown",
             "box": [int(x) for x in box], "pixels": int(p)}
            for i, c, box, p in zip(unique.tolist(), label.tolist(), boxes.tolist(),
                                    pixels.tolist()) if p >= min_pixels]


def pack_instances(labels: Tensor, instances: Tensor, out: Tensor | None = None) -> Tensor:
    """``labels + INSTANCE_SHIFT * instances`` as int64 (into ``out`` when given): one label
    map to sample both through ``OmniProjection.render(labels=...)``.

    Raises:
        ValueError: labels outside 0..255 or negative instance ids (they would not unpack).
    """
    if out is None:
        # numpy's broadcast_shapes: torch's imports its symbolic shapes, 1.4 s the first time
        out = torch.empty(np.broadcast_shapes(tuple(labels.shape), tuple(instances.shape)),
                          dtype=torch.int64, device=labels.device)
    # on the CPU in numpy, on one thread: torch would split these small loops over its threads,
    # which a busy machine makes many times slower (measured 35 ms a camera at a load of 8)
    cpu = all(t.device.type == "cpu" for t in (labels, instances, out))
    lab, ids = (t.numpy() if cpu else t for t in (labels, instances))
    for name, t, top in (("labels", lab, INSTANCE_SHIFT - 1), ("instances", ids, None)):
        if math.prod(t.shape) and (int(t.min()) < 0 or (top is not None and int(t.max()) > top)):
            raise ValueError(f"{name}: expected ids in 0..{top if top is not None else ''} to "
                             f"pack labels with instance ids, got {int(t.min())}..{int(t.max())}")
    if cpu:
        o = out.numpy()
        np.multiply(ids, INSTANCE_SHIFT, out=o, dtype=np.int64, casting="unsafe")
        np.add(o, lab, out=o, casting="unsafe")
        return out
    return torch.add(labels, instances, alpha=INSTANCE_SHIFT, out=out)


def unpack_instances(packed: Tensor) -> tuple[Tensor, Tensor]:
    """``(labels, instances)`` of a map of :func:`pack_instances` (as sampled)."""
    if packed.device.type == "cpu":   # numpy, on one thread (as pack_instances)
        p = packed.numpy()
        return torch.from_numpy(p % INSTANCE_SHIFT), torch.from_numpy(p // INSTANCE_SHIFT)
    return packed % INSTANCE_SHIFT, packed // INSTANCE_SHIFT


def instance_image(instances: Tensor) -> np.ndarray:
    """``(H, W)`` instance ids as the ``uint16`` array of a 16-bit grey PNG.

    Raises:
        ValueError: an id outside 0..65535.
    """
    ids = instances.detach().cpu().numpy()
    if ids.size and (int(ids.min()) < 0 or int(ids.max()) > 65535):
        raise ValueError(f"instances: ids must lie in 0..65535 for a 16-bit PNG, got "
                         f"{int(ids.min())}..{int(ids.max())}")
    return ids.astype(np.uint16)


def encode_objects(objects: list[dict]) -> str:
    """The text of an objects file: a JSON list, one object a line."""
    return "[" + ",\n ".join(json.dumps(o) for o in objects) + "]\n"


def decode_objects(text: str | bytes, name: str = "objects") -> dict[str, Tensor]:
    """An objects file's text (or bytes) as tensors: ``boxes (N, 4)`` float32 (XYXY corners),
    ``box_labels (N,)`` int64 class ids and ``box_instance_ids (N,)`` int64.

    Raises:
        ValueError: not such a list (``name``, the file, in the message).
    """
    try:
        objects = json.loads(text)
        if not isinstance(objects, list):
            raise ValueError("expected a JSON list of objects")
        boxes = [[float(x) for x in o["box"]] for o in objects]
        labels = [int(o["label"]) for o in objects]
        ids = [int(o["instance_id"]) for o in objects]
        if any(len(b) != 4 for b in boxes):
            raise ValueError("a box is not [x0, y0, x1, y1]")
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{name}: not an objects file ({err})") from None
    return {"boxes": torch.tensor(boxes, dtype=torch.float32).reshape(-1, 4),
            "box_labels": torch.tensor(labels, dtype=torch.int64),
            "box_instance_ids": torch.tensor(ids, dtype=torch.int64)}
