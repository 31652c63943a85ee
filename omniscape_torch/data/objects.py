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

Read back (`decode_objects`, which checks every object: a box with ``x1 <= x0``, a
negative count or a value of the wrong type is a ValueError naming the file and the object)
as tensors: ``boxes (N, 4)`` float32, ``box_labels (N,)`` int64 and ``box_instance_ids (N,)``
int64, the keys the augmentation takes.

Instance maps travel in two encodings: the folder's 16-bit grey PNG (`instance_image`;
read it with ``cv2.IMREAD_UNCHANGED`` or Pillow, mode ``I;16``: OpenCV's default and grey
flags keep the high byte) and, in WebDataset shards, a ``uint16`` ``.npy`` array
(`instance_npy`), which ``webdataset``'s default ``decode()`` reads losslessly (its
image decoders clip a 16-bit PNG to 8 bits). `decode_instances` reads both.
"""

from __future__ import annotations

import io as _io
import json
import math

import numpy as np
import torch
from torch import Tensor

from ..io.labels import CLASSES
from ..render.detection import instance_boxes

__all__ = ["INSTANCE_SHIFT", "decode_instances", "decode_objects", "encode_objects",
           "instance_image", "instance_npy", "instance_objects", "pack_instances",
           "unpack_instances"]

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
    """``(labels, instances)`` of a map of `pack_instances` (as sampled)."""
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


def instance_npy(instances: Tensor | np.ndarray) -> bytes:
    """``(H, W)`` instance ids as the bytes of a ``uint16`` ``.npy`` file: what the shards
    hold (``numpy.load``, and ``webdataset``'s default ``decode()``, read it back exactly).
    The bytes depend on the ids only.

    Raises:
        ValueError: an id outside 0..65535, or not one ``(H, W)`` map.
    """
    ids = instance_image(torch.as_tensor(instances))
    if ids.ndim != 2:
        raise ValueError(f"instances: expected an (H, W) map, got shape {tuple(ids.shape)}")
    buf = _io.BytesIO()
    np.save(buf, np.ascontiguousarray(ids), allow_pickle=False)
    return buf.getvalue()


def decode_instances(data: bytes, name: str = "instances") -> Tensor:
    """An instance map's bytes, a ``.npy`` array (shards) or a grey PNG (the folder's 16-bit
    file; an 8-bit one reads as it is), as ``(H, W)`` int64 ids.

    Raises:
        ValueError: neither, a colour image, or an array that is not ``(H, W)`` integer ids
            (``name``, the file, in the message).
    """
    if data[:6] == b"\x93NUMPY":
        try:
            ids = np.load(_io.BytesIO(data), allow_pickle=False)
        except ValueError as err:
            raise ValueError(f"{name}: not a readable .npy array ({err})") from None
        if ids.ndim != 2 or ids.dtype.kind not in "iu":
            raise ValueError(f"{name}: expected (H, W) integer instance ids, got "
                             f"{ids.dtype} {tuple(ids.shape)}")
    else:
        from ..io.images import decode_image

        ids = decode_image(data, name)
        if ids.ndim != 2:
            raise ValueError(f"{name}: expected a one-channel instance map, got shape "
                             f"{tuple(ids.shape)}")
    return torch.from_numpy(ids.astype(np.int64))


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool)) and math.isfinite(v)


def _object_error(o) -> str | None:
    """What is wrong with one object of an objects file, or None."""
    if not isinstance(o, dict):
        return f"expected a JSON object, got {type(o).__name__}"
    missing = [k for k in ("instance_id", "label", "box") if k not in o]
    if missing:
        return f"no {', '.join(missing)}"
    if not _is_int(o["instance_id"]) or o["instance_id"] < 1:
        return f"instance_id: expected an integer >= 1, got {o['instance_id']!r}"
    if not _is_int(o["label"]) or not 0 <= o["label"] < _LABEL_RANGE:
        return f"label: expected a class id in 0..{_LABEL_RANGE - 1}, got {o['label']!r}"
    box = o["box"]
    if not isinstance(box, list) or len(box) != 4 or not all(_is_number(x) for x in box):
        return f"box: expected [x0, y0, x1, y1] of 4 finite numbers, got {box!r}"
    if not (box[0] < box[2] and box[1] < box[3]):
        return f"box: expected x0 < x1 and y0 < y1 (XYXY corners), got {box!r}"
    if "pixels" in o and (not _is_int(o["pixels"]) or o["pixels"] < 1):
        return f"pixels: expected an integer >= 1, got {o['pixels']!r}"
    if "class" in o and not isinstance(o["class"], str):
        return f"class: expected a name, got {o['class']!r}"
    return None


def decode_objects(text: str | bytes, name: str = "objects") -> dict[str, Tensor]:
    """An objects file's text (or bytes) as tensors: ``boxes (N, 4)`` float32 (XYXY corners),
    ``box_labels (N,)`` int64 class ids and ``box_instance_ids (N,)`` int64.

    Every object is checked: ``instance_id`` an integer >= 1, ``label`` a class id in 0..255,
    ``box`` four finite numbers with ``x0 < x1`` and ``y0 < y1``, ``pixels`` (where given) an
    integer >= 1, ``class`` a string.

    Raises:
        ValueError: not such a list (``name``, the file, and the object's position and id in
            the message).
    """
    try:
        objects = json.loads(text)
    except ValueError as err:
        raise ValueError(f"{name}: not an objects file (not valid JSON: {err})") from None
    if not isinstance(objects, list):
        raise ValueError(f"{name}: not an objects file (expected a JSON list of objects, got "
                         f"{type(objects).__name__})")
    for i, o in enumerate(objects):
        problem = _object_error(o)
        if problem is not None:
            which = f"object {i}" + (f" (instance_id {o['instance_id']!r})"
                                     if isinstance(o, dict) and "instance_id" in o else "")
            raise ValueError(f"{name}: {which}: {problem}")
    return {"boxes": torch.tensor([o["box"] for o in objects],
                                  dtype=torch.float32).reshape(-1, 4),
            "box_labels": torch.tensor([o["label"] for o in objects], dtype=torch.int64),
            "box_instance_ids": torch.tensor([o["instance_id"] for o in objects],
                                             dtype=torch.int64)}
