"""mmsegmentation's and YOLO's layouts.

mmsegmentation (its documented layout for a custom dataset, ``BaseSegDataset`` with
``img_suffix=".png"``, ``seg_map_suffix=".png"``, ``reduce_zero_label=False``)::

    OUT/img_dir/train/NAME.png, OUT/img_dir/val/NAME.png     the images
    OUT/ann_dir/train/NAME.png, OUT/ann_dir/val/NAME.png     8-bit one-channel class indices
    OUT/metainfo.json                                       classes, palette, ignore_index ...

A class index is the class's position in ``metainfo.json``'s ``classes`` (the user's subset in
its order: 0..K-1, as mmseg wants them), 255 (``ignore_index``) outside the valid area and for
the classes left out; ``source_class_ids`` gives the dataset's id of each.

YOLO (Ultralytics' detection format)::

    OUT/images/train/NAME.png, OUT/images/val/NAME.png       the images
    OUT/labels/train/NAME.txt, OUT/labels/val/NAME.txt       one line an object:
                                                            "class cx cy w h"
    OUT/data.yaml                                           path, train, val, nc, names

``class`` is the object's class's position in ``names`` (0..K-1); ``cx cy w h`` its tight box
(corner coordinates) normalised by the image's width and height, written with 10 significant
digits; an image without objects has an empty file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...io.atomic import atomic_write_bytes, atomic_write_text
from ...io.images import encode_image
from ...io.labels import IGNORE_INDEX
from ._samples import SPLITS, Sample, remap

__all__ = ["MmsegWriter", "YoloWriter"]


class MmsegWriter:
    """Writes one mmsegmentation export (module docstring)."""

    def __init__(self, out: Path, class_ids: list[int], class_names: list[str],
                 palette: np.ndarray):
        self.out, self.class_ids = out, list(class_ids)
        self.class_names, self.palette = list(class_names), np.asarray(palette)
        self.table = np.full(256, IGNORE_INDEX, dtype=np.uint8)
        for new, old in enumerate(self.class_ids):
            self.table[old] = new
        self.count = {s: 0 for s in SPLITS}

    def add(self, sample: Sample, split: str) -> None:
        if sample.labels is None:
            raise ValueError(f"{sample.name}: labels: the mmseg export needs class ids")
        atomic_write_bytes(self.out / "img_dir" / split / f"{sample.name}.png", sample.png())
        atomic_write_bytes(self.out / "ann_dir" / split / f"{sample.name}.png",
                           encode_image(remap(sample.labels, self.table)))
        self.count[split] += 1

    def finish(self) -> dict:
        meta = {"classes": [self.class_names[i] for i in self.class_ids],
                "palette": [[int(v) for v in self.palette[i]] if i < len(self.palette)
                            else [255, 255, 255] for i in self.class_ids],
                "ignore_index": IGNORE_INDEX, "reduce_zero_label": False,
                "img_suffix": ".png", "seg_map_suffix": ".png",
                "data_prefix": {s: {"img_path": f"img_dir/{s}", "seg_map_path": f"ann_dir/{s}"}
                                for s in SPLITS},
                "source_class_ids": self.class_ids}
        path = self.out / "metainfo.json"
        atomic_write_text(path, json.dumps(meta, indent=2) + "\n")
        return {"images": dict(self.count), "files": [str(path)]}


def _g(v: float) -> str:
    return f"{v:.10g}"


class YoloWriter:
    """Writes one YOLO export (module docstring)."""

    def __init__(self, out: Path, class_ids: list[int], class_names: list[str]):
        self.out, self.class_ids, self.class_names = out, list(class_ids), list(class_names)
        self.index = {c: i for i, c in enumerate(self.class_ids)}
        self.count = {s: 0 for s in SPLITS}
        self.objects = {s: 0 for s in SPLITS}

    def add(self, sample: Sample, split: str) -> None:
        atomic_write_bytes(self.out / "images" / split / f"{sample.name}.png", sample.png())
        h, w = sample.size
        lines = []
        for o in sample.objects:
            if o["label"] not in self.index:
                continue
            x0, y0, x1, y1 = (float(v) for v in o["box"])
            x0, x1 = max(x0, 0.0), min(x1, float(w))
            y0, y1 = max(y0, 0.0), min(y1, float(h))
            if x1 <= x0 or y1 <= y0:
                continue
            lines.append(" ".join([str(self.index[o["label"]]), _g((x0 + x1) / 2 / w),
                                   _g((y0 + y1) / 2 / h), _g((x1 - x0) / w),
                                   _g((y1 - y0) / h)]))
        atomic_write_text(self.out / "labels" / split / f"{sample.name}.txt",
                          "".join(f"{line}\n" for line in lines))
        self.count[split] += 1
        self.objects[split] += len(lines)

    def finish(self) -> dict:
        import yaml

        data = {"path": str(self.out.resolve()), "train": "images/train", "val": "images/val",
                "nc": len(self.class_ids),
                "names": {i: self.class_names[c] for i, c in enumerate(self.class_ids)}}
        path = self.out / "data.yaml"
        atomic_write_text(path, yaml.safe_dump(data, sort_keys=False))
        return {"images": dict(self.count), "annotations": dict(self.objects),
                "files": [str(path)]}
