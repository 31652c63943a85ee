"""WoodScape's dataset layout, written by ``omniscape-torch generate --rig woodscape``: a car
with WoodScape's four fisheye cameras driving through the built-in town, its files where
WoodScape's tools and OmniDet's loader read them.

WoodScape (Yogamani et al., ICCV 2019; ``valeoai/WoodScape``: its README, ``scripts/`` and
OmniDet's ``omnidet/data_loader/woodscape_loader.py``, MIT licence) is the surround-view fisheye
dataset that automotive models train on; SynWoodScape (Sekkat et al., RA-L 2022) made the same
from CARLA. The generator's frame loop, resume, workers and progress are ``generate``'s
(`omniscape_torch.data.generate`); this module holds what is WoodScape's: the cameras, the
car's drive, the layout, the class tables and the writers.

Layout of ``DIR`` (``FFFFF``: the frame number, 5 digits, shared by the four cameras; ``CAM``:
FV, MVL, MVR, RV)::

    DIR/
      rgb_images/FFFFF_CAM.png                     8-bit RGB
      previous_images/FFFFF_CAM_prev.png           8-bit RGB, the same camera PREVIOUS_INTERVAL
                                                   earlier (the car at rest at its start for
                                                   frame 0)
      semantic_annotations/gtLabels/FFFFF_CAM.png  8-bit grey class ids 0..9 (SEMANTIC_CLASSES;
                                                   0 void, also outside the image circle)
      semantic_annotations/rgbLabels/FFFFF_CAM.png the ids in WoodScape's colours
      instance_annotations/FFFFF_CAM.json          the objects as polygons (below)
      box_2d_annotations/FFFFF_CAM.txt             2D boxes, one object a line (below)
      calibration_data/calibration/FFFFF_CAM.json  the camera (ot.cameras.write_woodscape)
      vehicle_data/rgb_images/FFFFF_CAM.json       {"timestamp": microseconds since the
                                                   drive's start, "ego_speed": km/h}
      vehicle_data/previous_images/FFFFF_CAM.json  the same at the previous image
      distance_maps/FFFFF_CAM.exr                  the distance along each pixel's ray (what
                                                   OmniDet's distance task estimates), float32
                                                   metres, channel "Z"; 0 outside the image
                                                   circle; the sky at the town's far plane
                                                   (>= 1000 m)
      dataset.json                                 manifest: configuration, cameras, tables
      dynamics.json (and .csv), dynamics_previous.json
                                                   the car's state at each frame and previous
                                                   image (``ride.records``: CARLA's frame)
      contact_sheet.png                            the middle frame at a glance (`contact_sheet`)
      .done/NNNNNN                                 a frame's marker, written last

`WoodScapeDataset` reads such a folder (or WoodScape's own) back as tensors.

Where WoodScape's README and OmniDet's loader (and WoodScape's own scripts) disagree, the
loader is followed: the README puts the calibration files in ``calibration_data/`` and the
vehicle data in ``vehicle_data/`` directly, the loader (and ``generate_luts.py``) reads
``calibration_data/calibration/`` and ``vehicle_data/{rgb_images,previous_images}/``; the
README names the boxes ``.png``, the loader (and ``box_2d_generator.py``) reads ``.txt``.
WoodScape numbers its images one id per image (``00164_FV``, ``00165_MVL``, ...); here the four
cameras of a frame share its number, which the loader reads alike (it splits the name at
``_``). OmniDet's loader assumes 1280 x 966 images (its ``original_res``) and its distance task
looks up tables by ``k1`` (``generate_luts.py`` makes them from the calibration files): other
``--image-size`` values write cameras scaled to that size.

Formats, as WoodScape's scripts read them:

* ``instance_annotations``: ``{"FFFFF_CAM.png": {"image_width", "image_height",
  "image_channels": 3, "annotation": [{"id", "tags": [tag], "segmentation": [[x, y], ...],
  "z_order", "group_id", "instance_id"}]}}``, one entry per 8-connected part of an object of
  the instance map (``cv2.findContours``: the outer boundary through the centres of its edge
  pixels, holes left out; a part of 1 or 2 pixels repeats its points to 3), the parts of one
  object sharing its ``group_id`` (their instance id; ``null`` for an object of one part),
  ``instance_id`` the town's id of the object (the same in every frame and camera; WoodScape's
  readers ignore it). Tags (WoodScape's ``scripts/mappers/class_names.json``): `INSTANCE_TAGS`.
  Objects of fewer than ``min_object_pixels`` pixels are left out.
* ``box_2d_annotations``: ``class_name,class_id,x_min,y_min,x_max,y_max`` a line (pixel
  indices, the extreme pixels' own: as ``box_2d_generator.py`` takes them from the polygons;
  OmniDet reads columns 1..5), empty with no box. Classes and filters are those of
  ``scripts/configs/box_2d_mapping_5_classes.json`` (`BOX_CLASSES`): an object whose box has
  ``(x_max - x_min) (y_max - y_min)`` below 400 pixels at 1280 x 966 (scaled with the image's
  area: `min_box_area`), or one side under a tenth of the other, is left out. WoodScape's
  occlusion, depiction and glass filters have nothing to act on (no object here is marked).
* ``semantic_annotations``: WoodScape's 10 classes (``semantic_mapping_9_classes.json`` and
  void), the town's 13 classes mapped by `TOWN_TO_SEMANTIC`; ``rgbLabels`` in its colours,
  which its ``semantic_map_generator.py`` gives in BGR order to ``cv2.imwrite`` (the file's
  RGB is the list reversed: `SEMANTIC_PALETTE`).

The town's classes in WoodScape's (`TOWN_TO_SEMANTIC`, `INSTANCE_TAGS`)::

    town class     gtLabels id (name)     instance tag     box class (id)
    Unlabeled      0 void
    Building       0 void
    Fence          0 void
    Other          0 void
    Pedestrian     4 person               person           person (1)
    Pole           0 void                 pole
    RoadLine       2 lanemarks
    Road           1 road
    Sidewalk       0 void (WoodScape has no sidewalk; its curb class is the kerb)
    Vegetation     0 void
    Vehicle        6 vehicles             car              vehicles (0)
    Wall           0 void
    TrafficSign    9 traffic_sign         traffic_sign     traffic_sign (4)

The cameras (`CAMERAS`, `CALIBRATION`): FV is WoodScape's ``scripts/calibration/front.json``;
MVL, MVR and RV are WoodScape's calibration files of its images 00165_MVL, 00166_MVR and
00167_RV as Valeo's Click-Calib repository ships them (``lwangvaleo/click_calib``,
``calibrations/original/``, commit 20be84e8a413f04fe42ac1c8c69560b39a0c8a47, Apache-2.0: "the
example data (images & calibrations) are from the public dataset WoodScape"), each its own
lens: 1280 x 966 pixels, the image circle 190 degrees across (``fov``; WoodScape's cameras
are 190-degree fisheyes: past it their images are dark), vehicle frame ISO 8855 (x forward,
y left, z up, the origin on the ground below the rear axle). Positions (metres) and optical
axes as those files give them (two calibrations, front.json's and those of images 00165-00167,
so the rig is WoodScape's to a few centimetres: WoodScape's FV of image 00164 sits 2 cm higher
than front.json's)::

    camera  position (x, y, z)        optical axis: azimuth (0 forward, 90 left), below
                                      the horizon, degrees
    FV      ( 3.748,  0.000, 0.660)     0.4, 23.4   (in the front grille)
    MVL     ( 1.945,  0.957, 0.955)   105.9, 73.8   (under the left mirror)
    MVR     ( 1.945, -0.957, 0.975)  -107.9, 74.2   (under the right mirror)
    RV      (-1.068,  0.055, 0.909)   178.7, 37.3   (at the boot)

The car (`drive`): the town's route (``generate.town_route``) driven with ``ride.CAR``'s
dynamics (body roll out of the turns, suspension pitch, no lean); its reference point, whose
location ``dynamics.json`` gives, is the vehicle frame's origin. A frame's rig pose turns and
places the cameras as ``generate``'s rig does (rig frame: the vehicle frame in OpenCV axes,
`ISO_TO_RIG`).
"""

from __future__ import annotations

import csv
import functools
import io as _io
import json
import math
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera
from ..cameras.woodscape_files import parse, write_woodscape
from ..io import atomic_write_text, write_exr, write_image
from ..io.labels import CLASSES
from ..scenes import ride as _ride
from . import format as fmt
from .objects import instance_objects, unpack_instances
from .run_files import _dumps, _dynamics_csv, _versions, _write_if_changed

__all__ = ["BOX_CLASSES", "BOX_PALETTE", "CALIBRATION", "CAMERAS", "DYNAMICS_PREVIOUS", "FOV_DEG",
           "IMAGE_SIZE", "INSTANCE_TAGS", "ISO_TO_RIG", "LAYOUT", "MIN_BOX_AREA",
           "PREVIOUS_INTERVAL", "SEMANTIC_CLASSES", "SEMANTIC_PALETTE", "TOWN_TO_SEMANTIC",
           "box_rows", "calibration", "contact_sheet", "drive", "file", "frame_files",
           "frame_folders", "frame_name", "instance_annotations", "min_box_area", "read_boxes",
           "require_opencv", "rig_camera", "rig_pose", "semantic_labels", "WoodScapeDataset",
           "write_camera", "write_previous", "write_run_files"]

#: WoodScape's cameras, in this order.
CAMERAS = ("FV", "MVL", "MVR", "RV")
#: WoodScape's image size ``(H, W)``, pixels.
IMAGE_SIZE = (966, 1280)
#: The image circle's full angle, degrees (WoodScape's 190-degree fisheyes).
FOV_DEG = 190.0

_INTRINSIC = {"model": "radial_poly", "poly_order": 4, "height": 966.0, "width": 1280.0,
              "aspect_ratio": 1.0}
#: WoodScape's calibration files of the four cameras (module docstring: their sources).
CALIBRATION = {
    "FV": {"quaternion": [0.5941767906169857, -0.5878843193897473, 0.3873184109007999,
                          -0.3890121040340926],
           "translation": [3.7484, 0.0, 0.6601699999999999],
           "intrinsic": {"cx_offset": 3.942, "cy_offset": -3.093, "k1": 339.749, "k2": -31.988,
                         "k3": 48.275, "k4": -7.201}},
    "MVL": {"quaternion": [0.9597923475490652, 0.24268656748912834, -0.004160525068239742,
                           -0.14101265750901937],
            "translation": [1.9445999999999999, 0.9572999999999999, 0.9549],
            "intrinsic": {"cx_offset": 1.829, "cy_offset": -0.49, "k1": 335.497, "k2": -11.41,
                          "k3": 22.009, "k4": 2.539}},
    "MVR": {"quaternion": [0.23466017209146606, 0.9622497661995224, -0.13751608301948323,
                           -0.00996584135669057],
            "translation": [1.9445999999999999, -0.9572999999999999, 0.9753099999999999],
            "intrinsic": {"cx_offset": 3.468, "cy_offset": -1.705, "k1": 337.657, "k2": -16.126,
                          "k3": 27.487, "k4": 0.888}},
    "RV": {"quaternion": [0.636314098922813, 0.6310055318192165, -0.30810493642236725,
                          -0.3193864970185268],
           "translation": [-1.0678, 0.0545, 0.90934],
           "intrinsic": {"cx_offset": 6.67, "cy_offset": -3.291, "k1": 339.039, "k2": -29.815,
                         "k3": 46.483, "k4": -6.655}},
}

#: ``rig = ISO_TO_RIG @ vehicle``: the vehicle frame (ISO 8855: x forward, y left, z up) in the
#: rig's OpenCV axes (x right, y down, z forward), the origin kept.
ISO_TO_RIG = ((0.0, -1.0, 0.0), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0))

#: WoodScape's semantic classes, the ids 0..9 of ``gtLabels``.
SEMANTIC_CLASSES = ("void", "road", "lanemarks", "curb", "person", "rider", "vehicles",
                    "bicycle", "motorcycle", "traffic_sign")
#: Their colours in ``rgbLabels``, RGB (``semantic_mapping_9_classes.json``'s BGR reversed).
SEMANTIC_PALETTE = ((0, 0, 0), (255, 0, 255), (0, 0, 255), (0, 255, 0), (255, 0, 0),
                    (255, 255, 255), (0, 255, 255), (255, 255, 0), (255, 128, 128),
                    (128, 128, 0))
#: The ``gtLabels`` id of each of the town's 13 classes (`omniscape_torch.io.CLASSES`).
TOWN_TO_SEMANTIC = (0, 0, 0, 0, 4, 0, 2, 1, 0, 0, 6, 0, 9)
#: The instance annotations' tag of the town's object classes (WoodScape's
#: ``class_names.json`` keys).
INSTANCE_TAGS = {"Pedestrian": "person", "Pole": "pole", "Vehicle": "car",
                 "TrafficSign": "traffic_sign"}
#: ``box_2d_mapping_5_classes.json``: the box classes, their ids 0..4 in this order.
BOX_CLASSES = ("vehicles", "person", "bicycle", "traffic_light", "traffic_sign")
#: The box class of each tag (``class_names.json``; ``pole`` is void there: no box).
_TAG_BOX_CLASS = {"car": "vehicles", "person": "person", "traffic_sign": "traffic_sign"}
#: The box classes' colours, RGB (``box_2d_mapping_5_classes.json``'s BGR reversed).
BOX_PALETTE = ((255, 0, 0), (255, 0, 255), (0, 255, 0), (255, 255, 100), (0, 0, 255))
#: ``min_obj_size`` of ``box_2d_mapping_5_classes.json``: pixels at 1280 x 966.
MIN_BOX_AREA = 400

#: The previous image's time before its frame, seconds: nominally a 30 fps camera's frame
#: before; exactly ``1 / (fps m)``, ``m = round(1 / (fps PREVIOUS_INTERVAL))`` (the drive is
#: simulated at ``fps m``: `drive`).
PREVIOUS_INTERVAL = 1 / 30

#: The folders of a frame's files, and each one's file name after ``FFFFF_CAM``.
LAYOUT = {"rgb": ("rgb_images", ".png"), "previous": ("previous_images", "_prev.png"),
          "gt_labels": ("semantic_annotations/gtLabels", ".png"),
          "rgb_labels": ("semantic_annotations/rgbLabels", ".png"),
          "instances": ("instance_annotations", ".json"),
          "boxes": ("box_2d_annotations", ".txt"),
          "calibration": ("calibration_data/calibration", ".json"),
          "vehicle": ("vehicle_data/rgb_images", ".json"),
          "vehicle_previous": ("vehicle_data/previous_images", ".json"),
          "distance": ("distance_maps", ".exr")}
#: The per-run files besides the manifest.
DYNAMICS_PREVIOUS = "dynamics_previous.json"


def frame_name(frame: int) -> str:
    """``7`` -> ``"00007"`` (WoodScape's image numbers: 5 digits)."""
    if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
        raise ValueError(f"frame: expected an integer >= 0, got {frame!r}")
    return f"{frame:05d}"


def file(kind: str, camera: str, frame: int) -> str:
    """Relative path of one file of the layout: ``kind`` a key of `LAYOUT`
    (``file("rgb", "FV", 3)`` -> ``"rgb_images/00003_FV.png"``)."""
    if kind not in LAYOUT:
        raise ValueError(f"kind: expected one of {tuple(LAYOUT)}, got {kind!r}")
    folder, suffix = LAYOUT[kind]
    return f"{folder}/{frame_name(frame)}_{camera}{suffix}"


def frame_files(cameras: Sequence[str], frame: int) -> list[str]:
    """Relative paths of every file of ``frame`` (its marker excluded)."""
    return [file(kind, c, frame) for c in cameras for kind in LAYOUT]


def frame_folders(out: Path) -> list[Path]:
    """The folders a frame's files (and its marker) are written in."""
    return [out, out / fmt.DONE] + [out / folder for folder, _ in LAYOUT.values()]


# --------------------------------------------------------------------------------------------
# The cameras and the drive
# --------------------------------------------------------------------------------------------

def calibration(name: str) -> dict:
    """Camera ``name``'s WoodScape calibration document (a new dict: `CALIBRATION`, keys in
    WoodScape's order)."""
    if name not in CALIBRATION:
        raise ValueError(f"camera: expected one of {CAMERAS}, got {name!r}")
    c = CALIBRATION[name]
    intrinsic = {**_INTRINSIC, **c["intrinsic"]}
    return {"extrinsic": {"quaternion": list(c["quaternion"]),
                          "translation": list(c["translation"])},
            "intrinsic": {k: intrinsic[k] for k in sorted(intrinsic)}, "name": name}


def rig_camera(name: str, image_size: tuple[int, int] = IMAGE_SIZE, *,
               dtype: torch.dtype = torch.float64) -> tuple[Camera, Tensor]:
    """WoodScape's camera ``name`` at ``image_size`` and its extrinsic.

    At another size than 1280 x 966 the lens is scaled with the image: the principal point as
    the pixels' centres (``(c + 0.5) s - 0.5``), ``k1..k4`` by the width's scale ``sx`` and
    ``aspect_ratio`` by ``sy / sx``, so that each pixel sees what the same place of the
    full-size image sees.

    Returns:
        ``(camera, T)``: the ``woodscape`` camera (``fov`` `FOV_DEG`) and ``T (4, 4)``
        float64, camera (OpenCV axes) -> vehicle (ISO 8855), metres.
    """
    found = parse(calibration(name), f"WoodScape's {name}")
    h, w = (int(s) for s in image_size)
    sx, sy = w / IMAGE_SIZE[1], h / IMAGE_SIZE[0]
    cx, cy, aspect, *k = found["params"]
    params = [(cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5, aspect * sy / sx,
              *(ki * sx for ki in k)]
    camera = Camera("woodscape", torch.tensor(params, dtype=dtype), (h, w),
                    fov=math.radians(FOV_DEG))
    return camera, torch.from_numpy(found["T"])


def rig_pose(T: Tensor) -> tuple[Tensor, Tensor]:
    """``(rotation (3, 3), position (3,))`` camera -> rig of the camera -> vehicle transform
    ``T`` (rig: the vehicle frame in OpenCV axes, `ISO_TO_RIG`), float64."""
    m = torch.tensor(ISO_TO_RIG, dtype=torch.float64)
    T = T.double()
    return m @ T[:3, :3], m @ T[:3, 3]


def drive(route: _ride.Route, fps: float, frames: int, seed: int) -> tuple[dict, dict]:
    """The car's drive along ``route`` (``ride.simulate(..., **ride.CAR)``) at the frames
    and at their previous images.

    The drive is simulated at ``fps m`` (`PREVIOUS_INTERVAL`); frame ``k`` is its state
    ``k m``, its previous image's the state ``k m - 1``, frame 0's the car at rest at its start
    (the state of frame 0, ``PREVIOUS_INTERVAL`` earlier). Frame ``k`` depends on the seed,
    ``fps`` and ``k`` only.

    Returns:
        ``(frames, previous)``: two dicts of ``simulate``'s keys, ``frames`` rows each,
        ``frame`` the frame number and ``time`` the state's time (seconds).
    """
    m = max(1, round(1.0 / (fps * PREVIOUS_INTERVAL)))
    states = _ride.simulate(route, fps * m, frames=(frames - 1) * m + 1, seed=seed, **_ride.CAR)
    now = torch.arange(frames) * m
    before = (now - 1).clamp(min=0)
    current = {key: v[now] for key, v in states.items()}
    previous = {key: v[before] for key, v in states.items()}
    current["frame"] = previous["frame"] = torch.arange(frames)
    previous["time"] = current["time"] - 1.0 / (fps * m)
    return current, previous


# --------------------------------------------------------------------------------------------
# Labels, polygons and boxes
# --------------------------------------------------------------------------------------------

def semantic_labels(labels: Tensor | np.ndarray) -> np.ndarray:
    """``(H, W)`` class ids of the town (0..12, others void) -> WoodScape's ``gtLabels`` ids
    ``(H, W)`` uint8 (`TOWN_TO_SEMANTIC`)."""
    lab = np.asarray(labels.numpy() if isinstance(labels, Tensor) else labels)
    table = np.zeros(256, np.uint8)
    table[:len(TOWN_TO_SEMANTIC)] = TOWN_TO_SEMANTIC
    return table[np.where((lab >= 0) & (lab < 256), lab, 0).astype(np.intp)]


def require_opencv() -> None:
    """Raise ``ImportError`` (naming the install) when OpenCV, which traces the instance
    annotations' polygons, is missing."""
    try:
        import cv2  # noqa: F401
    except ImportError:
        raise ImportError("generate --rig woodscape traces its instance polygons with OpenCV: "
                          "pip install opencv-contrib-python-headless") from None


def _contours(mask: np.ndarray) -> list[np.ndarray]:
    """The outer boundaries of a mask's 8-connected parts, each ``(N >= 3, 2)`` int (x, y)."""
    import cv2

    found, tree = cv2.findContours(mask.astype(np.uint8), cv2.RETR_CCOMP,
                                   cv2.CHAIN_APPROX_SIMPLE)
    found = [c for c, node in zip(found, tree[0] if tree is not None else []) if node[3] < 0]
    return [np.concatenate([c.reshape(-1, 2)] * (3 if len(c) < 3 else 1)) for c in found]


def instance_annotations(instances: Tensor, labels: Tensor, image_name: str, *,
                         min_pixels: int = 1) -> dict:
    """WoodScape's instance annotation document of an instance map (module docstring).

    Args:
        instances: ``(H, W)`` integer instance ids, 0 none.
        labels: ``(H, W)`` the town's class ids.
        image_name: the key of the document (the RGB image's name, ``FFFFF_CAM.png``).
        min_pixels: objects of fewer pixels are left out.

    Raises:
        ImportError: no OpenCV (the polygons are traced with ``cv2.findContours``).
    """
    ids = instances.numpy() if isinstance(instances, Tensor) else np.asarray(instances)
    annotation = []
    for obj in instance_objects(torch.as_tensor(ids), torch.as_tensor(labels),
                                min_pixels=min_pixels):
        tag = INSTANCE_TAGS.get(obj["class"])
        if tag is None:
            continue
        x0, y0, x1, y1 = obj["box"]   # only the object's box is traced
        parts = _contours(ids[y0:y1, x0:x1] == obj["instance_id"])
        for points in parts:
            annotation.append({
                "id": len(annotation) + 1, "tags": [tag],
                "segmentation": (points + [x0, y0]).tolist(), "z_order": len(annotation) + 1,
                "group_id": obj["instance_id"] if len(parts) > 1 else None,
                "instance_id": obj["instance_id"]})
    h, w = ids.shape
    return {image_name: {"image_width": w, "image_height": h, "image_channels": 3,
                         "annotation": annotation}}


def min_box_area(image_size: tuple[int, int]) -> float:
    """`MIN_BOX_AREA` scaled to an image of ``image_size`` ``(H, W)``: 400 at 1280 x 966."""
    return MIN_BOX_AREA * image_size[0] * image_size[1] / (IMAGE_SIZE[0] * IMAGE_SIZE[1])


def box_rows(document: dict) -> list[list]:
    """The 2D box rows of an instance annotation document, as ``box_2d_generator.py`` makes
    them: ``[class_name, class_id, x_min, y_min, x_max, y_max]``, the parts of an object (one
    ``group_id``) merged, only `BOX_CLASSES`, WoodScape's size and shape filters
    (module docstring)."""
    (entry,) = document.values()
    limit = min_box_area((entry["image_height"], entry["image_width"]))
    objects: dict = {}
    for a in entry["annotation"]:
        name = _TAG_BOX_CLASS.get(a["tags"][0])
        if name is None:
            continue
        pts = np.asarray(a["segmentation"])
        box = [int(pts[:, 0].min()), int(pts[:, 1].min()), int(pts[:, 0].max()),
               int(pts[:, 1].max())]
        key = a["group_id"] if a.get("group_id") else ("part", a["id"])
        if key in objects:
            old = objects[key][1]
            box = [min(old[0], box[0]), min(old[1], box[1]), max(old[2], box[2]),
                   max(old[3], box[3])]
        objects[key] = (name, box)
    rows = []
    for name, (x0, y0, x1, y1) in objects.values():
        w, h = x1 - x0, y1 - y0
        if w * h < limit or w < 0.1 * h or h < 0.1 * w:
            continue
        rows.append([name, BOX_CLASSES.index(name), x0, y0, x1, y1])
    return rows


def _box_text(rows: list[list]) -> str:
    buf = _io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(rows)
    return buf.getvalue()


def read_boxes(path: str | Path) -> list[tuple[str, int, int, int, int, int]]:
    """A ``box_2d_annotations`` file: ``[(class_name, class_id, x_min, y_min, x_max, y_max)]``
    (empty for an empty file)."""
    rows = csv.reader(Path(path).read_text(encoding="utf-8").splitlines())
    return [(r[0], *(int(v) for v in r[1:6])) for r in rows if r]


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

def _vehicle_record(states: dict, k: int) -> str:
    return json.dumps({"timestamp": int(round(float(states["time"][k]) * 1e6)),
                       "ego_speed": float(states["speed"][k]) * 3.6}) + "\n"


def write_camera(out: Path, name: str, k: int, rgb: np.ndarray, res: dict[str, Tensor],
                 camera: Camera, T: Tensor, states: dict, min_pixels: int = 1) -> None:
    """Write camera ``name``'s files of frame ``k`` but the previous image's.

    Args:
        out: the dataset folder.
        rgb: ``(H, W, 3)`` uint8, the image.
        res: the layer's outputs: ``depth (1, 1, H, W)`` the range, ``labels (1, 1, H, W)``
            the labels packed with the instance ids (``objects.pack_instances``).
        camera: the camera (`rig_camera`).
        T: its camera -> vehicle transform (`rig_camera`).
        states: the drive's frames (`drive`).
        min_pixels: the instance annotations' smallest object, pixels.
    """
    labels, instances = unpack_instances(res["labels"][0])
    write_image(out / file("rgb", name, k), rgb)
    gt = semantic_labels(labels)
    write_image(out / file("gt_labels", name, k), gt)
    write_image(out / file("rgb_labels", name, k), np.asarray(SEMANTIC_PALETTE, np.uint8)[gt])
    write_exr(out / file("distance", name, k), res["depth"][0, 0].float())
    doc = instance_annotations(instances, labels, f"{frame_name(k)}_{name}.png",
                               min_pixels=min_pixels)
    atomic_write_text(out / file("instances", name, k), json.dumps(doc) + "\n")
    atomic_write_text(out / file("boxes", name, k), _box_text(box_rows(doc)))
    path = out / file("calibration", name, k)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_woodscape(path, camera, T, name)
    atomic_write_text(out / file("vehicle", name, k), _vehicle_record(states, k))


def write_previous(out: Path, name: str, k: int, rgb: np.ndarray, previous: dict) -> None:
    """Write camera ``name``'s previous image of frame ``k`` (``rgb (H, W, 3)`` uint8) and its
    vehicle data (``previous``: `drive`'s)."""
    write_image(out / file("previous", name, k), rgb)
    atomic_write_text(out / file("vehicle_previous", name, k), _vehicle_record(previous, k))


def write_run_files(plan, out: Path, log: Callable[[str], None] = lambda msg: None) -> None:
    """The per-run files of a ``generate --rig woodscape`` plan (each rewritten only when its
    text changes): ``dataset.json`` (what a rerun compares), ``dynamics.json`` (and ``.csv``)
    and ``dynamics_previous.json``."""
    config = plan.config
    recs = _ride.records(plan.frames)
    _write_if_changed(out / fmt.DYNAMICS, _dumps(recs))
    _write_if_changed(out / fmt.DYNAMICS_CSV, _dynamics_csv(recs))
    _write_if_changed(out / DYNAMICS_PREVIOUS, _dumps(_ride.records(plan.previous)))
    cameras = {name: {"calibration": calibration(name), "image_size": list(config.image_size),
                      "params": c["camera"].params.tolist(), "face_size": c["face_size"],
                      "fov_deg": FOV_DEG}
               for name, c in plan.cameras.items()}
    manifest = {
        "format": "WoodScape (omniscape_torch generate --rig woodscape)",
        "format_version": 1, "config": config.to_dict(), "versions": _versions(),
        "frames": config.frames, "cameras": cameras,
        "semantic_classes": list(SEMANTIC_CLASSES),
        "semantic_palette": [list(c) for c in SEMANTIC_PALETTE],
        "town_to_semantic": dict(zip(CLASSES, TOWN_TO_SEMANTIC)),
        "instance_tags": INSTANCE_TAGS, "box_classes": list(BOX_CLASSES),
        "min_box_area_px": min_box_area(config.image_size),
        "previous_interval_s": float(plan.frames["time"][0] - plan.previous["time"][0]),
        "weather_per_frame": [plan.weather(k) for k in range(config.frames)],
        "layout": {f"{folder}/FFFFF_CAM{suffix}": kind for kind, (folder, suffix)
                   in LAYOUT.items()},
        "conventions": {"vehicle frame": "ISO 8855: x forward, y left, z up, metres, origin "
                                         "on the ground below the rear axle",
                        "distance": "distance_maps: range along the ray, float32 metres, "
                                    "channel Z, 0 not valid",
                        "timestamp": "microseconds since the drive's start",
                        "ego_speed": "km/h",
                        "pixels": "(x, y) = (column, row), (0, 0) the top-left pixel's "
                                  "centre"}}
    _write_if_changed(out / fmt.MANIFEST, _dumps(manifest))


# --------------------------------------------------------------------------------------------
# A look at a frame
# --------------------------------------------------------------------------------------------

def contact_sheet(root: str | Path, cameras: Sequence[str] = CAMERAS, frame: int = 0) -> bytes:
    """PNG bytes of frame ``frame`` of the WoodScape-layout dataset in ``root``: one row per
    camera, its RGB with the 2D boxes drawn (in `BOX_PALETTE`'s colours), ``rgbLabels``, the
    distance (log colour map, black where 0) and the previous image; each cell
    ``contact_sheet.SHEET_CELL`` pixels square, titled. ``generate --rig woodscape`` writes it
    as ``contact_sheet.png`` (the middle finished frame)."""
    from PIL import Image, ImageDraw

    from ..io import read_exr, read_image
    from ..io.images import encode_image
    from .contact_sheet import _TURBO, _sheet_cell

    root = Path(root)
    rows = []
    for name in cameras:
        rgb = Image.fromarray(read_image(root / file("rgb", name, frame)).numpy())
        draw = ImageDraw.Draw(rgb)
        for _, cls, x0, y0, x1, y1 in read_boxes(root / file("boxes", name, frame)):
            draw.rectangle((x0, y0, x1, y1), outline=BOX_PALETTE[cls],
                           width=max(1, rgb.width // 320))
        distance = read_exr(root / file("distance", name, frame)).numpy()
        seen = distance > 0
        log = np.log10(np.maximum(distance, 1e-3))
        lo, hi = (float(log[seen].min()), float(log[seen].max())) if seen.any() else (0.0, 1.0)
        scaled = np.clip((log - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
        cells = [(np.asarray(rgb), f"{name} {frame_name(frame)}, boxes"),
                 (read_image(root / file("rgb_labels", name, frame)).numpy(), "rgbLabels"),
                 (np.where(seen[..., None], _TURBO[scaled], 0).astype(np.uint8),
                  "distance (log)"),
                 (read_image(root / file("previous", name, frame)).numpy(), "previous")]
        rows.append(np.hstack([_sheet_cell(image, title) for image, title in cells]))
    return encode_image(np.vstack(rows))


# --------------------------------------------------------------------------------------------
# Reading it back
# --------------------------------------------------------------------------------------------

class WoodScapeDataset(torch.utils.data.Dataset):
    """A folder in WoodScape's layout (``generate --rig woodscape``'s, or WoodScape's own: the
    files it has), one item per image ``FFFFF_CAM`` of ``rgb_images/``: with ``.done/``
    markers (a generated folder), the finished frames only. Each item is a dict::

        frame          str, "FFFFF"
        camera         str, FV, MVL, MVR or RV
        rgb            (3, H, W) float32 in [0, 1]
        previous       (3, H, W) float32, previous_images' (where there)
        labels         (H, W) int64, gtLabels' WoodScape ids 0..9 (where there)
        depth          (H, W) float32, distance_maps' range along the ray, metres, 0 not
                       valid; valid (1, H, W) bool: depth > 0 (where there)
        boxes          (N, 4) float32, the 2D boxes as XYXY corners (columns x_min..x_max
                       give x_min, x_max + 1: the augmentation's convention); box_labels
                       (N,) int64, their BOX_CLASSES ids (where there)
        model, intrinsics, image_size, T_vehicle_camera
                       "woodscape", (7,) float64 params, (2,) int64 (H, W), (4, 4) float64
                       camera -> vehicle (ISO 8855), from calibration_data (where there)
        vehicle, vehicle_previous
                       the vehicle data's dicts (timestamp in microseconds, ego_speed in
                       km/h), where there

    Items with boxes need ``collate_fn=omniscape_torch.data.datasets.collate``. Plain data
    only: it pickles, for ``DataLoader(num_workers=N)``.

    Args:
        root: the folder.
        cameras: the cameras to serve (default: all four).

    Raises:
        ValueError: no ``rgb_images/`` images (of these cameras) in ``root``.
    """

    def __init__(self, root: str | Path, cameras: Sequence[str] = CAMERAS):
        self.root = Path(root)
        self.cameras = tuple(cameras)
        for c in self.cameras:
            if c not in CAMERAS:
                raise ValueError(f"cameras: expected some of {CAMERAS}, got {c!r}")
        done = self.root / fmt.DONE
        finished = ({int(p.name) for p in done.iterdir() if p.name.isdigit()}
                    if done.is_dir() else None)
        self.items = []
        for p in sorted((self.root / LAYOUT["rgb"][0]).glob("*.png")):
            frame, _, camera = p.stem.partition("_")
            if camera in self.cameras and frame.isdigit() and (
                    finished is None or int(frame) in finished):
                self.items.append((frame, camera))
        if not self.items:
            raise ValueError(f"root: no {LAYOUT['rgb'][0]}/FFFFF_CAM.png images of "
                             f"{', '.join(self.cameras)} in {self.root}")

    def __len__(self) -> int:
        return len(self.items)

    def _path(self, kind: str, frame: str, camera: str) -> Path:
        folder, suffix = LAYOUT[kind]
        return self.root / folder / f"{frame}_{camera}{suffix}"

    def __getitem__(self, index: int) -> dict:
        from ..cameras import read_woodscape
        from ..io import read_exr, read_image, to_float

        frame, camera = self.items[index]
        item: dict = {"frame": frame, "camera": camera}
        path = functools.partial(self._path, frame=frame, camera=camera)
        item["rgb"] = to_float(read_image(path("rgb")))
        if path("previous").is_file():
            item["previous"] = to_float(read_image(path("previous")))
        if path("gt_labels").is_file():
            item["labels"] = read_image(path("gt_labels")).to(torch.int64)
        if path("distance").is_file():
            item["depth"] = read_exr(path("distance"))
            item["valid"] = (item["depth"] > 0)[None]
        if path("boxes").is_file():
            rows = read_boxes(path("boxes"))
            item["boxes"] = torch.tensor([[x0, y0, x1 + 1, y1 + 1] for _, _, x0, y0, x1, y1
                                          in rows], dtype=torch.float32).reshape(-1, 4)
            item["box_labels"] = torch.tensor([r[1] for r in rows], dtype=torch.int64)
        if path("calibration").is_file():
            cam, T, _ = read_woodscape(path("calibration"))
            item.update(model=cam.model.name, intrinsics=cam.params.detach().clone(),
                        image_size=torch.tensor(cam.image_size, dtype=torch.int64),
                        T_vehicle_camera=T)
        for kind, key in (("vehicle", "vehicle"), ("vehicle_previous", "vehicle_previous")):
            if path(kind).is_file():
                item[key] = json.loads(path(kind).read_text(encoding="utf-8"))
        return item
