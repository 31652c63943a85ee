"""Read a dataset written by ``omniscape-torch generate`` (layout: `format`).

Everything is read from the files alone (nothing is re-rendered): frames, intrinsics,
extrinsics and the vehicle dynamics. A frame counts as written only when it is *finished*: its
``.done/NNNNNN`` marker exists (written last by the writer) and so do its per-camera files.

Returned types::

    rgb           (3, H, W) float32 in [0, 1]  (or uint8 with ``rgb_uint8=True``)
    depth         (H, W) float32, range in metres, 0 where not valid, 1000 m for the sky
    labels        (H, W) int64 class ids 0..12, 255 (IGNORE_INDEX) where not valid
    labels_color  (3, H, W) uint8, the labels in CARLA's palette
    valid         (1, H, W) bool, the shape the augmentation returns per sample (its
                  ``(B, 1, H, W)`` batched), so a read frame and an augmented one match
    instances     (H, W) int64 instance ids, 0 for none and where not valid
    objects       three keys (`omniscape_torch.data.objects.decode_objects`):
                  boxes (N, 4) float32, the objects' tight boxes (XYXY corners),
                  box_labels (N,) int64 class ids, box_instance_ids (N,) int64

``instances`` and ``objects`` are only in datasets written since ``generate`` writes them
(`OPTIONAL_MODALITIES`): ask for them where a dataset has
them (`has_modality`).

Reading the 16-bit instance maps outside this package: `read_instances`, or
``cv2.imread(path, cv2.IMREAD_UNCHANGED)`` (uint16; OpenCV's default and grey flags keep the
high byte: ids below 256 read 0), or Pillow's ``numpy.asarray(Image.open(path))`` (mode
``I;16``, uint16); never through a conversion to ``"L"`` or ``"RGB"``, which clips the ids to
8 bits.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor

from ..cameras import Camera
from ..io.exr import read_exr
from ..io.images import read_image
from .format import (CAMERA, CORE_MODALITIES, DYNAMICS, MANIFEST, MODALITIES, OCAMCALIB,
                     finished_frames, frame_file)
from .objects import decode_instances, decode_objects
from .ocamcalib import polynomial_camera

__all__ = ["has_modality", "list_cameras", "list_frames", "read_camera", "read_camera_dict",
           "read_dynamics", "read_extrinsics", "read_frame", "read_instances", "read_manifest",
           "read_ocamcalib"]

_DEFAULT = ("rgb", "depth", "labels", "valid")


def _root(root: str | Path) -> Path:
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such dataset folder")
    return root


def _json(path: Path):
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing (not a dataset written by "
                                f"'omniscape-torch generate'?)")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}, line {err.lineno}: not valid JSON ({err.msg})") from None


def read_manifest(root: str | Path) -> dict:
    """``dataset.json``: config, versions, cameras, classes, weather per frame, layout."""
    return _json(_root(root) / MANIFEST)


def list_cameras(root: str | Path) -> list[str]:
    """The cameras of the dataset, in the writer's order (``dataset.json``); without a manifest,
    the sorted sub-folders holding a ``camera.json``."""
    root = _root(root)
    if (root / MANIFEST).is_file():
        return list(read_manifest(root)["cameras"])
    return sorted(p.name for p in root.iterdir() if (p / "camera.json").is_file())


def list_frames(root: str | Path, cameras: Sequence[str] | None = None, *,
                modalities: Sequence[str] = CORE_MODALITIES,
                check_files: bool = True) -> list[int]:
    """The finished frames (sorted): a ``.done`` marker and (``check_files``) the files of
    ``modalities`` (default: those every dataset has) for every camera of ``cameras``
    (default: all)."""
    root = _root(root)
    cameras = list_cameras(root) if cameras is None else list(cameras)
    return finished_frames(root, cameras if check_files else (), modalities)


def read_frame(root: str | Path, camera: str, frame: int | str,
               modalities: Sequence[str] = _DEFAULT, *, rgb_uint8: bool = False
               ) -> dict[str, Tensor]:
    """The images of one camera at one frame, as tensors (types in the module docstring).

    Raises:
        ValueError: an unknown modality. FileNotFoundError: a missing file (names it).
    """
    root = _root(root)
    out: dict[str, Tensor] = {}
    for m in modalities:
        path = root / frame_file(camera, m, frame)
        if m == "depth":
            out[m] = read_exr(path)
            continue
        if m == "objects":
            if not path.is_file():
                raise FileNotFoundError(f"{path}: no such file")
            out.update(decode_objects(path.read_bytes(), str(path)))
            continue
        image = read_image(path)
        if m in ("rgb", "labels_color"):
            if image.dim() == 2:
                image = image.unsqueeze(-1).expand(-1, -1, 3)
            image = image.permute(2, 0, 1).contiguous()
            out[m] = image.float() / 255.0 if (m == "rgb" and not rgb_uint8) else image
        elif m in ("labels", "instances"):
            out[m] = _grey(image, path).long()
        else:  # valid
            out[m] = (_grey(image, path) > 0).unsqueeze(0)
    return out


def read_instances(path: str | Path) -> Tensor:
    """An instance map file, exactly: the dataset's 16-bit grey PNG (``instances/NNNNNN.png``,
    ``convert``'s ``<camera>_instances.png``) or a ``.npy`` array, as ``(H, W)`` int64 ids.

    Raises:
        FileNotFoundError: no such file. ValueError: not a one-channel image or integer array.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    return decode_instances(path.read_bytes(), str(path))


def has_modality(root: str | Path, modality: str, cameras: Sequence[str] | None = None
                 ) -> bool:
    """Whether the dataset in ``root`` has files of ``modality`` for every camera of
    ``cameras`` (default: all): its folder ``<camera>/<modality>/``. False for the optional
    modalities (``instances``, ``objects``) of a dataset written before them."""
    if modality not in MODALITIES:
        raise ValueError(f"modality: expected one of {tuple(MODALITIES)}, got {modality!r}")
    root = _root(root)
    cameras = list_cameras(root) if cameras is None else list(cameras)
    return bool(cameras) and all((root / c / modality).is_dir() for c in cameras)


def _grey(image: Tensor, path: Path) -> Tensor:
    if image.dim() != 2:
        raise ValueError(f"{path}: expected a one-channel image, got shape {tuple(image.shape)}")
    return image


def read_camera_dict(root: str | Path, camera: str) -> dict:
    """``<camera>/camera.json`` as a dict (``Camera`` JSON: model, image_size, params, ...)."""
    return _json(_root(root) / camera / "camera.json")


def read_camera(root: str | Path, camera: str, **kwargs):
    """The intrinsics of ``camera``: a `omniscape_torch.Camera` (float64 by default;
    ``kwargs`` go to ``Camera.from_dict``)."""
    path = _root(root) / camera / "camera.json"
    try:
        return Camera.from_dict(_json(path), **kwargs)
    except (ValueError, TypeError) as err:
        raise type(err)(f"{path}: {err}") from None


def read_ocamcalib(root: str | Path, camera: str, **kwargs):
    """``<camera>/calib_results.txt``, the camera as OCamCalib's polynomial model: a
    ``scaramuzza`` `omniscape_torch.Camera` with the valid area (``fov``, ``blind_fov``)
    that ``camera.json``'s ``"ocamcalib"`` record gives (``kwargs`` go to
    ``Camera.from_ocamcalib``). The record's ``max_px`` is its held-out error.

    Raises:
        FileNotFoundError: no such file or record (a dataset written before they were).
    """
    root = _root(root)
    record = read_camera_dict(root, camera).get("ocamcalib")
    path = root / camera / OCAMCALIB
    if not isinstance(record, dict) or not path.is_file():
        raise FileNotFoundError(f"{path}: missing, or no 'ocamcalib' record in "
                                f"{root / camera / CAMERA} (a dataset written before "
                                f"omniscape_torch wrote OCamCalib files?)")
    return polynomial_camera(path, record, **kwargs)


def read_extrinsics(root: str | Path, camera: str) -> dict:
    """``<camera>/extrinsics.json`` with the poses as float64 tensors.

    Returns:
        ``{"T_rig_camera": (4, 4), "T_world_camera": {frame: (4, 4)}, "faces": {frame: [face
        names]}, "face_size": int, "frames": {frame name: description}}`` (camera -> rig and
        camera -> world; rig and world axes described in ``"frames"``).
    """
    data = _json(_root(root) / camera / "extrinsics.json")
    f64 = torch.float64
    return {"T_rig_camera": torch.tensor(data["T_rig_camera"], dtype=f64),
            "T_world_camera": {int(p["frame"]): torch.tensor(p["T_world_camera"], dtype=f64)
                               for p in data["poses"]},
            "faces": {int(p["frame"]): list(p["faces"]) for p in data["poses"]},
            "face_size": int(data["face_size"]),
            "frames": data.get("frames", {})}


def read_dynamics(root: str | Path) -> dict[int, dict]:
    """``dynamics.json`` by frame number: ``{frame: record}``, each record with CARLA's names
    and units (``timestamp`` s, ``location``/``velocity``/``acceleration``/``angular_velocity``
    as ``{x, y, z}``, ``rotation`` as ``{pitch, yaw, roll}`` degrees, ``speed`` m/s)."""
    recs = _json(_root(root) / DYNAMICS)
    return {int(r["frame"]): r for r in recs}
