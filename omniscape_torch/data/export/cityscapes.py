"""The Cityscapes layout (``gtFine``), in Cityscapes' own label ids.

Layout of ``OUT`` (``CITY`` the camera's name with ``-`` for ``_``, as Cityscapes' scripts
split file names at ``_``; ``SEQ`` 000000; ``FRAME`` the frame number, or a stream's position)::

    OUT/leftImg8bit/{train,val}/CITY/CITY_SEQ_FRAME_leftImg8bit.png      the images
    OUT/gtFine/{train,val}/CITY/CITY_SEQ_FRAME_gtFine_labelIds.png       8-bit label ids
    OUT/gtFine/{train,val}/CITY/CITY_SEQ_FRAME_gtFine_instanceIds.png    16-bit instance ids
    OUT/gtFine/{train,val}/CITY/CITY_SEQ_FRAME_gtFine_color.png          the labels' colours
    OUT/gtFine/{train,val}/CITY/CITY_SEQ_FRAME_gtFine_polygons.json      imgHeight, imgWidth,
                                                                          objects (polygons)

Label ids are those of Cityscapes' table (``cityscapesscripts.helpers.labels``), so that its
scripts and the loaders built on them (evaluation, ``createTrainIdLabelImgs``, detectron2's and
mmseg's Cityscapes datasets) read the export: CARLA's 13 classes map onto them by
`CITYSCAPES_IDS` (CARLA's palette is Cityscapes' colours); ``RoadLine`` becomes ``road``
(Cityscapes has no lane markings), ``Other`` ``static``; the area outside the camera's valid
area is ``out of roi`` (3), and a class left out of the user's subset ``unlabeled`` (0).
``instanceIds``: ``labelId * 1000 + k`` on the pixels of an object of an instance class
(``k`` = 0, 1, ... per class and image, in instance-id order), the label id elsewhere
(Cityscapes' convention; its scripts evaluate instances of its ``hasInstances`` classes,
person and car here, and read pole and traffic sign ids as their class). Polygons (OpenCV's
``findContours``: each region's outer boundary through its boundary pixels' centres, drawn
larger first so that a region inside another's hole is drawn after it): one per connected
region of each label and one per connected part of each object, named by Cityscapes' label
names; ``json2labelImg`` draws them back into the labelIds (the tests measure how closely).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...io.atomic import atomic_write_bytes, atomic_write_text
from ...io.images import encode_image
from ...io.labels import IGNORE_INDEX
from ..format import INSTANCE_CLASSES
from ._samples import SPLITS, Sample

__all__ = ["CITYSCAPES_IDS", "CITYSCAPES_LABELS", "CityscapesWriter", "cityscapes_city"]

#: The Cityscapes labels the export writes: id -> (name, colour), as in
#: ``cityscapesscripts.helpers.labels`` (checked by the tests).
CITYSCAPES_LABELS = {
    0: ("unlabeled", (0, 0, 0)), 3: ("out of roi", (0, 0, 0)), 4: ("static", (0, 0, 0)),
    7: ("road", (128, 64, 128)), 8: ("sidewalk", (244, 35, 232)),
    11: ("building", (70, 70, 70)), 12: ("wall", (102, 102, 156)),
    13: ("fence", (190, 153, 153)), 17: ("pole", (153, 153, 153)),
    20: ("traffic sign", (220, 220, 0)), 21: ("vegetation", (107, 142, 35)),
    24: ("person", (220, 20, 60)), 26: ("car", (0, 0, 142)),
}
#: The Cityscapes label id of each of CARLA's 13 classes, by name.
CITYSCAPES_IDS = {"Unlabeled": 0, "Building": 11, "Fence": 13, "Other": 4, "Pedestrian": 24,
                  "Pole": 17, "RoadLine": 7, "Road": 7, "Sidewalk": 8, "Vegetation": 21,
                  "Vehicle": 26, "Wall": 12, "TrafficSign": 20}
_UNLABELED, _OUT_OF_ROI = 0, 3


def cityscapes_city(camera: str | None) -> str:
    """A camera's name as a Cityscapes city: ``fisheye_left`` -> ``fisheye-left`` (the scripts
    split names at ``_``); ``omniscape`` for none."""
    return "omniscape" if not camera else camera.replace("_", "-")


def _contours(mask: np.ndarray) -> list[np.ndarray]:
    """The outer boundaries of a mask's 8-connected regions: each ``(N, 2)`` int (x, y)."""
    import cv2

    # RETR_CCOMP: outer boundaries and holes, a region inside a hole an outer boundary again
    # (RETR_EXTERNAL would drop it); the holes are left out (what fills them is drawn after)
    found, tree = cv2.findContours(mask.astype(np.uint8), cv2.RETR_CCOMP,
                                   cv2.CHAIN_APPROX_SIMPLE)
    found = [c for c, node in zip(found, tree[0] if tree is not None else []) if node[3] < 0]
    # a region of one pixel (or a line of them) is a contour of 1 (or 2) points: repeated to
    # the 3 a polygon needs (Pillow's drawing refuses fewer than 2)
    return [np.concatenate([c.reshape(-1, 2)] * (3 if len(c) < 3 else 1)) for c in found]


def _area(poly: np.ndarray) -> float:
    x, y = poly[:, 0].astype(np.float64), poly[:, 1].astype(np.float64)
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


class CityscapesWriter:
    """Writes one Cityscapes export (module docstring).

    Args:
        out: the export folder. class_ids: the user's subset (class ids).
        class_names: the name of each class id (CARLA's 13 classes' names).

    Raises:
        ValueError: a class of the subset without a Cityscapes id (names it).
    """

    def __init__(self, out: Path, class_ids: list[int], class_names: list[str]):
        try:
            import cv2  # noqa: F401 - the polygons
        except ImportError:
            raise ImportError("the cityscapes export's polygons need OpenCV: pip install "
                              "opencv-contrib-python-headless") from None
        self.out = out
        self.table = np.full(256, _UNLABELED, dtype=np.uint8)
        self.table[IGNORE_INDEX] = _OUT_OF_ROI
        for i in class_ids:
            name = class_names[i]
            if name not in CITYSCAPES_IDS:
                raise ValueError(f"classes: {name} has no Cityscapes label id (the export "
                                 f"maps {', '.join(CITYSCAPES_IDS)})")
            self.table[i] = CITYSCAPES_IDS[name]
        self.instance_ids = {i for i in class_ids if class_names[i] in INSTANCE_CLASSES}
        self.colors = np.zeros((256, 3), dtype=np.uint8)
        for k, (_, colour) in CITYSCAPES_LABELS.items():
            self.colors[k] = colour
        self.count = {s: 0 for s in SPLITS}

    def add(self, sample: Sample, split: str) -> None:
        if sample.labels is None:
            raise ValueError(f"{sample.name}: labels: the cityscapes export needs class ids")
        city = cityscapes_city(sample.camera)
        stem = f"{city}_000000_{sample.number:06d}"
        lab = np.where((sample.labels >= 0) & (sample.labels < 256), sample.labels,
                       IGNORE_INDEX)
        ids = self.table[lab]
        inst = ids.astype(np.uint16)
        objects = []      # (area, label id, polygon)
        covered = np.zeros(ids.shape, dtype=bool)
        if sample.instances is not None:
            per_class: dict[int, int] = {}
            for o in sample.objects:
                if o["instance_id"] is None or o["label"] not in self.instance_ids:
                    continue
                mask = sample.instances == o["instance_id"]
                cid = int(self.table[o["label"]])
                k = per_class.get(cid, 0)
                per_class[cid] = k + 1
                inst[mask] = cid * 1000 + k
                covered |= mask
                objects += [(_area(p), cid, p) for p in _contours(mask)]
        for cid in np.unique(ids).tolist():
            objects += [(_area(p), cid, p) for p in _contours((ids == cid) & ~covered)]
        objects.sort(key=lambda t: -t[0])    # stable: the order found on ties
        h, w = sample.size
        polygons = {"imgHeight": int(h), "imgWidth": int(w),
                    "objects": [{"label": CITYSCAPES_LABELS[cid][0],
                                 "polygon": p.tolist()} for _, cid, p in objects]}
        image = self.out / "leftImg8bit" / split / city / f"{stem}_leftImg8bit.png"
        atomic_write_bytes(image, sample.png())
        gt = self.out / "gtFine" / split / city
        atomic_write_bytes(gt / f"{stem}_gtFine_labelIds.png", encode_image(ids))
        atomic_write_bytes(gt / f"{stem}_gtFine_instanceIds.png", encode_image(inst))
        atomic_write_bytes(gt / f"{stem}_gtFine_color.png", encode_image(self.colors[ids]))
        atomic_write_text(gt / f"{stem}_gtFine_polygons.json", json.dumps(polygons) + "\n")
        self.count[split] += 1

    def finish(self) -> dict:
        return {"images": dict(self.count), "files": []}
