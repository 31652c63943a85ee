"""COCO instances JSON: images, categories and annotations with RLE masks.

Layout of ``OUT``::

    OUT/train/NAME.png, OUT/val/NAME.png      the images (a dataset's files, byte for byte)
    OUT/annotations/instances_train.json      COCO's instances format, one file a split
    OUT/annotations/instances_val.json

An annotation is one object (one instance id of the map): ``segmentation`` its mask as COCO's
compressed RLE (``{"size": [H, W], "counts": str}``: the column-major runs of the mask,
Fortran order, as ``pycocotools.mask.encode`` writes them, their bytes decoded to ASCII so
that the JSON holds a string), ``area`` its pixel count, ``bbox`` ``[x, y, w, h]`` the tight
box of its pixels (corner coordinates: pixel columns ``u0..u1`` give ``x = u0``, ``w = u1 + 1
- u0``, COCO's and ``toBbox``'s convention), ``iscrowd`` 0, ``category_id`` the class id
(``categories`` names each), ``instance_id`` the dataset's id; ``keypoints`` ``[x, y, v, ...]``
(``v`` 2 visible, 0 not) and ``num_keypoints`` where the samples give them. Images and
annotations are numbered from 1 (COCOeval takes an annotation id 0 for "unmatched"). Objects
given as boxes only (a stream without instance maps) get ``bbox`` and ``area`` (w h) and no
``segmentation``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...io.atomic import atomic_write_bytes, atomic_write_text
from ._samples import SPLITS, Sample

__all__ = ["coco_rle", "CocoWriter"]


def coco_rle(mask: np.ndarray) -> dict:
    """A binary mask as COCO's compressed RLE, ``{"size": [H, W], "counts": str}``, equal to
    ``pycocotools.mask.encode(np.asfortranarray(mask.astype(np.uint8)))`` with its counts
    decoded to ``str`` (written without pycocotools).

    The runs alternate 0s and 1s over the pixels in column-major (Fortran) order, starting
    with 0s; each count is written as COCO's ``rleToString`` does: from the third on, the
    difference to the count two before, in 5-bit groups with a continuation bit, each plus 48.

    Args:
        mask: ``(H, W)`` boolean or 0/1.

    Raises:
        ValueError: not one ``(H, W)`` mask.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask: expected (H, W), got shape {mask.shape}")
    h, w = mask.shape
    flat = (mask != 0).reshape(-1, order="F").astype(np.int8)
    change = np.flatnonzero(np.diff(flat)) + 1
    bounds = np.concatenate(([0], change, [flat.size]))
    counts = np.diff(bounds).tolist()
    if flat.size and flat[0] == 1:
        counts = [0] + counts
    if not flat.size:
        counts = [0]
    chars = []
    for i, x in enumerate(counts):
        if i > 2:
            x -= counts[i - 2]
        more = True
        while more:
            c = x & 0x1F
            x >>= 5
            more = (x != -1) if (c & 0x10) else (x != 0)
            if more:
                c |= 0x20
            chars.append(chr(c + 48))
    return {"size": [int(h), int(w)], "counts": "".join(chars)}


class CocoWriter:
    """Writes one COCO export (module docstring): `add` each sample, then `finish`.

    Args:
        out: the export folder.
        class_ids: the categories (class ids), in order.
        class_names: the name of each class id.
    """

    def __init__(self, out: Path, class_ids: list[int], class_names: list[str]):
        self.out = out
        self.class_ids = list(class_ids)
        self.class_names = list(class_names)
        self.images = {s: [] for s in SPLITS}
        self.annotations = {s: [] for s in SPLITS}
        self.keypoints = 0
        self._ids = {"image": 0, "annotation": 0}

    def add(self, sample: Sample, split: str) -> None:
        """Write the sample's image and keep its record and annotations."""
        file = f"{sample.name}.png"
        atomic_write_bytes(self.out / split / file, sample.png())
        self._ids["image"] += 1
        image_id = self._ids["image"]
        h, w = sample.size
        record = {"id": image_id, "file_name": file, "height": int(h), "width": int(w)}
        if sample.frame is not None:
            record["frame"] = int(sample.frame)
        if sample.camera is not None:
            record["camera"] = sample.camera
        self.images[split].append(record)
        keep = set(self.class_ids)
        for o in sample.objects:
            if o["label"] not in keep:
                continue
            self._ids["annotation"] += 1
            x0, y0, x1, y1 = o["box"]
            ann = {"id": self._ids["annotation"], "image_id": image_id,
                   "category_id": int(o["label"]), "iscrowd": 0,
                   "bbox": [x0, y0, x1 - x0, y1 - y0]}
            if o["instance_id"] is not None:
                mask = sample.instances == o["instance_id"]
                ann["segmentation"] = coco_rle(mask)
                ann["area"] = int(o["pixels"])
                ann["bbox"] = [int(v) for v in ann["bbox"]]
                ann["instance_id"] = int(o["instance_id"])
            else:
                ann["area"] = float((x1 - x0) * (y1 - y0))
            kp = o.get("keypoints")
            if kp is not None:
                self.keypoints = max(self.keypoints, len(kp))
                ann["keypoints"] = [float(v) if j % 3 < 2 else int(v)
                                    for j, v in enumerate(np.asarray(kp).reshape(-1).tolist())]
                ann["num_keypoints"] = int((np.asarray(kp)[:, 2] > 0).sum())
            self.annotations[split].append(ann)

    def finish(self) -> dict:
        """Write ``annotations/instances_<split>.json``; returns the counts."""
        categories = []
        for i in self.class_ids:
            cat = {"id": int(i), "name": self.class_names[i], "supercategory": "object"}
            if self.keypoints:
                cat["keypoints"] = [str(k) for k in range(self.keypoints)]
                cat["skeleton"] = []
            categories.append(cat)
        files = []
        for split in SPLITS:
            data = {"info": {"description": "omniscape_torch export"},
                    "images": self.images[split], "annotations": self.annotations[split],
                    "categories": categories}
            path = self.out / "annotations" / f"instances_{split}.json"
            atomic_write_text(path, json.dumps(data) + "\n")
            files.append(str(path))
        return {"images": {s: len(self.images[s]) for s in SPLITS},
                "annotations": {s: len(self.annotations[s]) for s in SPLITS}, "files": files}
