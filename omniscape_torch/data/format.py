"""The dataset format, defined once: file names, folders, modalities, when a frame is finished.

The writer (`omniscape_torch.data.generate`), the readers (`readers`), the torch
datasets (`datasets`) and the statistics (`stats`) all name files through this
module.

Layout of ``DIR``
-----------------
::

    DIR/
      dataset.json                 manifest: config, versions, cameras, layout, conventions
      dynamics.json                per-frame vehicle state, ride.records(): CARLA names, frame
                                   and units (x north, y east, z up, metres; degrees)
      dynamics.csv                 the same, one row per frame (flattened columns)
      <camera>/                    fisheye_left, fisheye_right, catadioptric_left, ...
        camera.json                intrinsics (Camera.save_json), and under "ocamcalib" the
                                   record of calib_results.txt (degree, rms_px, max_px,
                                   fov_deg, blind_fov_deg: `ocamcalib`)
        calib_results.txt          the camera as OCamCalib's polynomial model (Scaramuzza),
                                   fitted within 0.04 px over its valid area (the file holds
                                   no field of view: camera.json's record does)
        extrinsics.json            T_rig_camera (camera -> rig, 4 x 4), and per frame
                                   T_world_camera (camera -> world) and the faces rendered
        rgb/NNNNNN.png             8-bit RGB
        depth/NNNNNN.exr           range (Euclidean distance along the ray), float32 metres,
                                   channel "Z"; 0 where not valid; sky: the town's far
                                   plane (planar 1000 m on its face: range >= 1000 m)
        labels/NNNNNN.png          8-bit class ids 0..12 (CARLA's 13 classes), 255 not valid
        labels_color/NNNNNN.png    labels in CARLA's palette (white: not valid)
        valid/NNNNNN.png           8-bit mask: 255 valid, 0 not (valid == labels != 255)
        instances/NNNNNN.png       16-bit grey instance ids, 0 = none (and outside the valid
                                   area): every vehicle, pedestrian, pole and traffic sign
                                   is an object, its id the same in every frame and camera
                                   (``scenes.town.Town``: ``instance_label`` its class)
        objects/NNNNNN.json        the objects seen, one per instance id in the image,
                                   sorted by id: ``[{"instance_id", "label" (class id),
                                   "class" (its name), "box": [x0, y0, x1, y1], "pixels"}]``;
                                   the box is the tight box of the instance's pixels in
                                   torchvision's XYXY corner convention (pixel columns u0..u1
                                   and rows v0..v1 give x0 = u0, x1 = u1 + 1, y0 = v0,
                                   y1 = v1 + 1), ``pixels`` their count (`objects`)
        cubemap/                   only with --save-cubemaps, only the faces rendered (to
                                   inspect a frame; not a training source: full cubemaps
                                   come from Town.render_cubemap):
          rgb/NNNNNN_<face>.png      faces as rendered (DESIGN.md face table), cube axes =
          depth/NNNNNN_<face>.exr    world axes; depth is planar (along the face's axis), m
          labels/NNNNNN_<face>.png
      panorama/                    only with --save-panorama: an equirectangular view
        rgb/NNNNNN.png             (H x 2H, H = image height) from the rig origin raised
        depth/NNNNNN.exr           0.9 m, turned with the motorcycle (centre column: its
        labels/NNNNNN.png          heading); range depth
      .done/NNNNNN                 written last, atomically, when all files of a frame exist
      contact_sheet.png            a look at the middle finished frame: one row per camera,
                                   columns rgb, depth (log colour map, black not valid),
                                   labels_color, valid; then, with several weathers, the first
                                   camera's rgb at the first frame of each (four a row);
                                   200 x 200 pixels per cell; rewritten only when its bytes
                                   change
      .lock                        while a run writes the folder (``io.atomic``; removed when
                                   it ends): a second run into the folder stops
      stats.json, stats.png        written by ``omniscape-torch stats``
      shards/                      only with ``generate --format webdataset`` or ``pack``:
        index.json                 frames per shard, the files of a sample (instance ids
                                   as a uint16 .npy array), the frames of each shard
        shard-NNNNNN.tar           WebDataset shard NNNNNN: frames NNNNNN * S to
                                   (NNNNNN + 1) * S - 1 (S: frames per shard), one sample
                                   per camera and frame (`shards`)

NNNNNN is the frame number (zero-padded to 6 digits). Every file is written atomically
(temporary file + rename). A frame is finished when its marker and all its files exist.
A dataset written before ``generate`` wrote instances has no ``instances`` or ``objects``
(`OPTIONAL_MODALITIES`): the readers read it all the same, its frames finished without
them (`CORE_MODALITIES`), and a rerun of ``generate`` renders its frames anew to add
them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

__all__ = ["CAMERA", "CONTACT_SHEET", "CORE_MODALITIES", "CUBE_MODALITIES", "DONE", "DYNAMICS",
           "DYNAMICS_CSV", "FORMAT", "FORMAT_VERSION", "INSTANCE_CLASSES", "MANIFEST",
           "MODALITIES", "OCAMCALIB", "OPTIONAL_MODALITIES", "STATS",
           "STATS_PLOT", "cubemap_file", "finished_frames", "frame_file", "frame_name", "layout",
           "marker", "missing_files", "panorama_file", "SHARDS", "SHARD_INDEX", "shard_file"]

FORMAT = "omniscape_torch dataset"
FORMAT_VERSION = 1

MANIFEST = "dataset.json"
DYNAMICS, DYNAMICS_CSV = "dynamics.json", "dynamics.csv"
CONTACT_SHEET = "contact_sheet.png"
STATS, STATS_PLOT = "stats.json", "stats.png"
#: The folder of the finished-frame markers.
DONE = ".done"
#: The folder of the WebDataset shards, and their index (`shards`).
SHARDS = "shards"
SHARD_INDEX = f"{SHARDS}/index.json"
#: Per-camera files: the intrinsics (Camera JSON), and the camera as OCamCalib's model.
CAMERA, OCAMCALIB = "camera.json", "calib_results.txt"

#: Per-frame files of each camera: folder -> extension.
MODALITIES = {"rgb": "png", "depth": "exr", "labels": "png", "labels_color": "png",
              "valid": "png", "instances": "png", "objects": "json"}
#: The per-frame files that a dataset written before them lacks (instance ids and objects):
#: read where a dataset has them.
OPTIONAL_MODALITIES = ("instances", "objects")
#: The per-frame files every dataset has: a frame is finished, for the readers, with these.
CORE_MODALITIES = tuple(m for m in MODALITIES if m not in OPTIONAL_MODALITIES)
#: The classes whose objects are instances (``instances``, ``objects``), of the 13 classes.
INSTANCE_CLASSES = ("Pedestrian", "Pole", "Vehicle", "TrafficSign")
#: The modalities of the saved cube faces and of the panorama: folder -> extension.
CUBE_MODALITIES = {"rgb": "png", "depth": "exr", "labels": "png"}


def frame_name(frame: int | str) -> str:
    """``7`` or ``"000007"`` -> ``"000007"``."""
    if isinstance(frame, str):
        if not frame.isdigit():
            raise ValueError(f"frame: expected a frame number, got {frame!r}")
        frame = int(frame)
    if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
        raise ValueError(f"frame: expected an integer >= 0, got {frame!r}")
    return f"{frame:06d}"


def _check_modality(modality: str, allowed: dict) -> str:
    if modality not in allowed:
        raise ValueError(f"modalities: expected some of {tuple(allowed)}, got {modality!r}")
    return allowed[modality]


def frame_file(camera: str, modality: str, frame: int | str) -> str:
    """Relative path of one camera's file of ``modality`` at ``frame``."""
    ext = _check_modality(modality, MODALITIES)
    return f"{camera}/{modality}/{frame_name(frame)}.{ext}"


def cubemap_file(camera: str, modality: str, frame: int | str, face: str) -> str:
    """Relative path of a saved cube face (``--save-cubemaps``)."""
    ext = _check_modality(modality, CUBE_MODALITIES)
    return f"{camera}/cubemap/{modality}/{frame_name(frame)}_{face}.{ext}"


def panorama_file(modality: str, frame: int | str) -> str:
    """Relative path of a panorama file (``--save-panorama``)."""
    ext = _check_modality(modality, CUBE_MODALITIES)
    return f"panorama/{modality}/{frame_name(frame)}.{ext}"


def shard_file(index: int) -> str:
    """Relative path of WebDataset shard ``index`` (``shards/shard-NNNNNN.tar``)."""
    return f"{SHARDS}/shard-{frame_name(index)}.tar"


def marker(frame: int | str) -> str:
    """Relative path of ``frame``'s finished marker, written last."""
    return f"{DONE}/{frame_name(frame)}"


def finished_frames(root: str | Path, cameras: Sequence[str],
                    modalities: Sequence[str] = CORE_MODALITIES) -> list[int]:
    """The finished frames of the dataset in ``root`` (sorted): a marker, and the files of
    ``modalities`` (default: those every dataset has) of every camera of ``cameras``."""
    root = Path(root)
    done = root / DONE
    if not done.is_dir():
        return []
    for m in modalities:
        _check_modality(m, MODALITIES)
    frames = sorted(int(p.name) for p in done.iterdir() if p.is_file() and p.name.isdigit())
    return [k for k in frames
            if all((root / frame_file(c, m, k)).is_file() for c in cameras for m in modalities)]


def missing_files(root: str | Path, cameras: Sequence[str], frame: int | str,
                  modalities: Sequence[str] = CORE_MODALITIES) -> list[str]:
    """The files (relative paths) that keep ``frame`` from being finished: its marker, then
    the files of ``modalities`` of every camera of ``cameras`` that are missing; ``[]`` for a
    finished frame."""
    root = Path(root)
    for m in modalities:
        _check_modality(m, MODALITIES)
    files = [marker(frame)] + [frame_file(c, m, frame) for c in cameras for m in modalities]
    return [f for f in files if not (root / f).is_file()]


def layout(save_cubemaps: bool, save_panorama: bool) -> dict[str, str]:
    """The manifest's description of the files of a dataset."""
    out = {MANIFEST: "this manifest",
           DYNAMICS: "ride.records(): per-frame vehicle state, CARLA names/frame/units",
           DYNAMICS_CSV: "dynamics.json flattened, one row per frame",
           "<camera>/camera.json": "intrinsics, Camera.save_json; under 'ocamcalib' the "
                                   "record of calib_results.txt (degree, rms_px, max_px, "
                                   "fov_deg, blind_fov_deg)",
           f"<camera>/{OCAMCALIB}": "the camera as OCamCalib's polynomial model, fitted "
                                    "over its valid area (no field of view in the file)",
           "<camera>/extrinsics.json": "T_rig_camera and per-frame T_world_camera",
           "<camera>/rgb/NNNNNN.png": "8-bit RGB",
           "<camera>/depth/NNNNNN.exr": "range along the ray, float32 metres, channel Z, "
                                        "0 where not valid",
           "<camera>/labels/NNNNNN.png": "class ids 0..12, 255 not valid",
           "<camera>/labels_color/NNNNNN.png": "labels in CARLA's palette",
           "<camera>/valid/NNNNNN.png": "255 valid, 0 not",
           "<camera>/instances/NNNNNN.png": "16-bit instance ids (vehicles, pedestrians, "
                                            "poles, traffic signs), 0 none and not valid",
           "<camera>/objects/NNNNNN.json": "per instance: instance_id, label, class, box "
                                           "[x0, y0, x1, y1] (tight, XYXY corners: columns "
                                           "u0..u1 -> x0 = u0, x1 = u1 + 1), pixels",
           f"{DONE}/NNNNNN": "frame finished marker, written last",
           CONTACT_SHEET: "middle finished frame: a row per camera, columns rgb, depth, "
                          "labels_color, valid; then the first camera's rgb in each "
                          "weather"}
    if save_cubemaps:
        out["<camera>/cubemap/{rgb,depth,labels}/NNNNNN_<face>.{png,exr,png}"] = \
            "rendered cube faces (planar depth), cube axes = world axes"
    if save_panorama:
        out["panorama/{rgb,depth,labels}/NNNNNN.{png,exr,png}"] = \
            "equirectangular view from the rig, turned with the motorcycle (range depth)"
    return out
