"""Convert cubemap captures made in a simulator (CARLA) into fisheye and catadioptric images.

Folder layout read (what ``examples/carla_capture.py`` writes)::

    CUBEMAPS/
      <capture_id>/                     one folder per capture (one point, one instant)
        front_rgb.png    front_depth.png    front_labels.png
        back_rgb.png     back_depth.png     back_labels.png
        left_...  right_...  up_...  down_...

``CUBEMAPS`` may also be a single capture folder itself. Each face is the square image of a
90-degree camera at the ``DESIGN.md`` rig rotation (front none, back yaw 180, left yaw -90,
right yaw +90, up pitch +90, down pitch -90). Per face and modality:

* ``<face>_rgb.png``: 8-bit colour (grey is repeated to three channels).
* ``<face>_depth.png``: CARLA's depth camera saved with the ``Raw`` converter: planar depth
  packed in 24 bits of R, G, B (`omniscape_torch.io.carla.decode_depth`); or
  ``<face>_depth.exr``: planar depth in metres, one float channel (the PNG wins if both exist).
* ``<face>_labels.png``: CARLA's semantic camera saved with the ``Raw`` converter: the tag in
  the red channel (a one-channel PNG is read as the tags themselves), mapped to the 13 classes
  of the paper from ``label_set`` (`omniscape_torch.io.carla.to_13`).
* ``<face>_instances.png`` (optional): CARLA's instance-segmentation camera
  (``sensor.camera.instance_segmentation``) saved as it comes: the tag in red, the object's
  id in green and blue, ``G + 256 B`` (`omniscape_torch.io.carla.decode_instances`). An
  object's id is kept where its tag maps to a class of
  `omniscape_torch.data.format.INSTANCE_CLASSES` (vehicles, pedestrians, poles, traffic
  signs; CARLA numbers every mesh, roads and buildings too), 0 elsewhere; a capture without
  label faces takes its labels from the instance faces' red channel (the same tags).

A modality may be absent (no face file of it), but a modality with some faces and not others,
faces of different sizes, an unreadable (corrupt) image or an unknown tag is an error that
names the file.

Bad captures do not stop a conversion: `convert_captures` converts every capture it can,
writes nothing for a capture that fails (its files are rendered into a hidden staging folder
and moved into place only once all of them are written), and at the end raises
`ConvertError` listing the failures (``omniscape-torch convert`` prints them and exits
with status 1).

Written per capture and camera (``fisheye``, ``catadioptric``)::

    OUT/<capture_id>/<camera>_rgb.png          8-bit RGB (sampled from the 8-bit faces as read)
    OUT/<capture_id>/<camera>_depth.exr        float32 metres: range (default) or z; 0 invalid
    OUT/<capture_id>/<camera>_labels.png       8-bit class ids, 255 outside the valid area
    OUT/<capture_id>/<camera>_labels_color.png the ids in CARLA's palette
    OUT/<capture_id>/<camera>_valid.png        255 where the pixel sees the scene
    OUT/<capture_id>/<camera>_instances.png    with instance faces: 16-bit object ids, 0 none
                                               and outside the valid area
    OUT/<capture_id>/<camera>_objects.json     with instance faces: the objects' classes,
                                               tight boxes (XYXY corners) and pixel counts
                                               (`objects`)
    OUT/cameras.json                           the cameras (Camera JSON), their rotations
                                               and, under "ocamcalib", the record of their
                                               OCamCalib file (degree, errors, fov_deg,
                                               blind_fov_deg: `ocamcalib`)
    OUT/<camera>_calib_results.txt             the camera as OCamCalib's polynomial model

The polynomial models are fitted once per run, before the captures are read, and not at all
when ``OUT`` holds them already for the same cameras (a rerun).

Every file is written atomically (temporary file then rename).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from ..cubemap.faces import FACES
from ..io.atomic import (atomic_write_text, folder_lock, remove_stale_temporaries,
                        temporary_prefix)
from ..io.carla import LABEL_SETS, decode_depth, decode_instances, decode_labels, to_13
from ..io.exr import read_exr, write_exr
from ..io.images import read_image, write_image
from ..io.labels import CLASSES, colorize
from ..render.sizing import MEMORY_PER_PIXEL, PROCESS_MEMORY, available_memory
from . import distributed, ocamcalib
from .format import INSTANCE_CLASSES
from .objects import (encode_objects, instance_image, instance_objects, pack_instances,
                      unpack_instances)

__all__ = ["MODALITIES", "CAMERAS", "ConvertError", "build_cameras", "calib_file",
           "check_pixels", "convert_captures", "convert_chunk", "find_captures", "load_capture",
           "render_capture"]

MODALITIES = ("rgb", "depth", "labels", "instances")
CAMERAS = ("fisheye", "catadioptric")


class ConvertError(RuntimeError):
    """Some captures failed to convert; the others were converted.

    Attributes:
        failures: ``{capture_id: message}`` of the captures that failed (each message names the
            offending file where there is one); nothing was written for them.
        results: ``{capture_id: [paths written]}`` of the captures converted.
    """

    def __init__(self, failures: dict[str, str], results: dict[str, list[Path]]):
        self.failures = dict(failures)
        self.results = dict(results)
        lines = [f"{len(failures)} of {len(failures) + len(results)} captures failed to "
                 "convert:"]
        lines += [f"  {capture}: {message}" for capture, message in failures.items()]
        super().__init__("\n".join(lines))


def calib_file(camera: str) -> str:
    """The name, in ``OUT``, of camera ``camera``'s OCamCalib file (module docstring)."""
    return f"{camera}_calib_results.txt"


def _face_file(capture: Path, face: str, modality: str) -> Path:
    png = capture / f"{face}_{modality}.png"
    if modality == "depth" and not png.is_file():
        exr = png.with_suffix(".exr")
        if exr.is_file():
            return exr
    return png


def _is_capture(folder: Path) -> bool:
    return any(_face_file(folder, f, m).is_file() for f in FACES for m in MODALITIES)


def find_captures(cubemaps_dir: str | Path) -> list[Path]:
    """The capture folders under ``cubemaps_dir`` (sorted), or ``[cubemaps_dir]`` if it is one.

    Raises:
        FileNotFoundError: no such folder. ValueError: no capture in it.
    """
    root = Path(cubemaps_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder of captures")
    if _is_capture(root):
        return [root]
    captures = sorted(p for p in root.iterdir() if p.is_dir() and _is_capture(p))
    if not captures:
        raise ValueError(f"{root}: no capture found (expected folders holding "
                         f"{{{','.join(FACES)}}}_{{{','.join(MODALITIES)}}}.png)")
    return captures


def load_capture(path: str | Path, *, label_set: str = "13",
                 modalities: Sequence[str] | None = None,
                 unknown_label: int | None = None,
                 rgb_uint8: bool = False) -> dict[str, Tensor | int]:
    """Read one capture folder into cubemaps, faces in ``FACES`` order, batch of one.

    Args:
        path: the capture folder (layout in the module docstring).
        label_set: the simulator's tag set, ``"13"`` (CARLA <= 0.9.9), ``"23"`` (0.9.10 to
            0.9.13) or ``"new"`` (Cityscapes-ordered tags of later versions).
        modalities: those required (default: whichever are there; at least one).
        unknown_label: class given to tags outside ``label_set`` (default: an error).
        rgb_uint8: keep the RGB faces as the files give them, ``uint8`` levels 0..255 with the
            channels innermost in memory (no float copy; ``OmniProjection.render`` samples them
            as they are), instead of float32 in [0, 1].

    Returns:
        dict with ``face_size`` and, for each modality found: ``rgb (1, 6, 3, F, F)`` float32 in
        [0, 1] (``rgb_uint8``: ``uint8``, a view of a contiguous ``(1, 6, F, F, 3)`` tensor),
        ``depth (1, 6, F, F)`` float32 planar metres, ``labels (1, 6, F, F)`` int64 class ids
        0..12, ``instances (1, 6, F, F)`` int64 object ids (0: none; also ``labels``, from
        the instance faces, where there are no label faces).

    Raises:
        ValueError: a face missing (names the file), faces not square or of different sizes,
            an unreadable image, no face image at all, an unknown tag. Every message about one
            face names its file.
    """
    capture = Path(path)
    if not capture.is_dir():
        raise FileNotFoundError(f"{capture}: no such capture folder")
    if label_set not in LABEL_SETS:
        raise ValueError(f"label_set: expected one of {tuple(LABEL_SETS)}, got {label_set!r}")
    if not isinstance(rgb_uint8, bool):
        raise TypeError(f"rgb_uint8: expected a bool, got {rgb_uint8!r}")
    wanted = MODALITIES if modalities is None else tuple(modalities)
    for m in wanted:
        if m not in MODALITIES:
            raise ValueError(f"modalities: expected some of {MODALITIES}, got {m!r}")
    out: dict[str, Tensor | int] = {}
    size: tuple[int, Path] | None = None
    for modality in wanted:
        files = [_face_file(capture, face, modality) for face in FACES]
        present = [f.is_file() for f in files]
        if not any(present):
            if modalities is not None:
                raise ValueError(f"{capture}: no {modality} faces (expected {files[0].name}, "
                                 f"...)")
            continue
        if not all(present):
            missing = [f for f, ok in zip(files, present) if not ok]
            raise ValueError(f"{capture}: missing face image {missing[0]}"
                             + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
        faces, tags = [], []
        for file in files:
            try:
                if file.suffix == ".exr":
                    face_image = read_exr(file).float()
                    if not bool(torch.isfinite(face_image).all()) or \
                            bool((face_image < 0).any()):
                        raise ValueError("depth must be finite and >= 0 metres")
                    image = face_image.numpy()
                else:
                    image = read_image(file).numpy()
            except Exception as err:   # corrupt file: name it whatever the reader said
                message = str(err)
                raise ValueError(message if str(file) in message else f"{file}: {message}") \
                    from err
            h, w = image.shape[:2]
            if h != w:
                raise ValueError(f"{file}: a cube face must be square, got {w} x {h} (W x H)")
            if size is None:
                size = (h, file)
            elif h != size[0]:
                raise ValueError(f"{file}: face of {h} x {h} pixels, but {size[1]} is "
                                 f"{size[0]} x {size[0]}")
            if file.suffix == ".exr":
                faces.append(face_image)
            elif modality == "instances":
                classes, ids = _decode_instances(image, file, label_set, unknown_label)
                faces.append(ids)
                tags.append(classes)
            else:
                faces.append(_decode(image, modality, file, label_set, unknown_label,
                                     rgb_uint8))
        if tags and "labels" not in out:
            out["labels"] = torch.stack(tags).unsqueeze(0)
        stacked = torch.stack(faces).unsqueeze(0)
        if modality == "rgb" and rgb_uint8:   # (1, 6, F, F, 3) seen as (1, 6, 3, F, F)
            stacked = stacked.permute(0, 1, 4, 2, 3)
        out[modality] = stacked
    if size is None:
        raise ValueError(f"{capture}: no face image (expected files like "
                         f"{_face_file(capture, FACES[0], 'rgb').name})")
    out["face_size"] = size[0]
    return out


#: The class ids whose objects keep their instance ids.
_INSTANCE_IDS = torch.tensor([CLASSES.index(name) for name in INSTANCE_CLASSES])


def _decode_instances(image: np.ndarray, file: Path, label_set: str,
                      unknown_label: int | None) -> tuple[Tensor, Tensor]:
    """An instance face as ``(classes, ids)``, two ``(F, F)`` int64 tensors: the red
    channel's tags as classes, and the object ids of the pixels of an instance class (0
    elsewhere)."""
    if image.dtype != np.uint8 or image.ndim != 3:
        raise ValueError(f"{file}: expected an 8-bit colour image (CARLA's instance camera: "
                         f"tag in red, id in green and blue), got {image.dtype} of shape "
                         f"{image.shape}")
    tags, ids = decode_instances(image, "RGB")
    try:
        classes = to_13(tags, label_set, unknown=unknown_label)
    except ValueError as err:
        raise ValueError(f"{file}: {err}") from None
    return classes, torch.where(torch.isin(classes, _INSTANCE_IDS), ids, 0)


def _decode(image: np.ndarray, modality: str, file: Path, label_set: str,
            unknown_label: int | None, rgb_uint8: bool = False) -> Tensor:
    """One face as a tensor: rgb ``(3, F, F)`` float32 in [0, 1] (``rgb_uint8``: ``(F, F, 3)``
    ``uint8`` as read), depth ``(F, F)`` metres, labels ``(F, F)`` int64 classes."""
    if image.dtype != np.uint8:
        raise ValueError(f"{file}: expected 8-bit pixels, got {image.dtype}")
    if modality == "rgb":
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=-1)
        face = torch.from_numpy(np.ascontiguousarray(image))
        return face if rgb_uint8 else face.permute(2, 0, 1).float() / 255.0
    if modality == "depth":
        if image.ndim != 3:
            raise ValueError(f"{file}: a CARLA depth image has 3 channels (24-bit depth), got "
                             "a one-channel image")
        return decode_depth(image, "RGB")
    tags = torch.from_numpy(image.astype(np.int64)) if image.ndim == 2 \
        else decode_labels(image, "RGB")
    try:
        return to_13(tags, label_set, unknown=unknown_label)
    except ValueError as err:
        raise ValueError(f"{file}: {err}") from None


def build_cameras(cameras: Sequence[str] = CAMERAS, *, image_size: tuple[int, int] = (1024, 1024),
                  fisheye_model: str = "equidistant", fisheye_fov: float = math.radians(190),
                  catadioptric_xi: float | None = None,
                  catadioptric_fov: float = math.radians(220),
                  catadioptric_blind_fov: float | None = math.radians(40),
                  catadioptric_looking: str = "down") -> dict[str, tuple]:
    """``{name: (Camera, rotation (3, 3) or None)}`` from the presets (angles in radians)."""
    from ..cameras import presets

    built: dict[str, tuple] = {}
    for name in cameras:
        if name == "fisheye":
            built[name] = (presets.fisheye(image_size, fov=fisheye_fov, model=fisheye_model),
                           None)
        elif name == "catadioptric":
            built[name] = presets.catadioptric(image_size, xi=catadioptric_xi,
                                               fov=catadioptric_fov,
                                               blind_fov=catadioptric_blind_fov,
                                               looking=catadioptric_looking)
        else:
            raise ValueError(f"cameras: expected some of {CAMERAS}, got {name!r}")
    if not built:
        raise ValueError("cameras: none given")
    return built


def render_capture(cube: dict, cameras: dict[str, tuple], out_dir: str | Path, *,
                   depth_output: str = "range", interpolation: str = "bilinear",
                   device: str | torch.device = "cpu", min_object_pixels: int = 1,
                   _layers: dict | None = None) -> list[Path]:
    """Render the cubemaps of `load_capture` through each camera and write the files
    (layout in the module docstring) into ``out_dir``. Returns the paths written.
    ``min_object_pixels``: the objects files list the objects of at least so many pixels.

    A ``uint8`` RGB cube (``load_capture(rgb_uint8=True)``, what `convert_captures`
    reads) is sampled as it is into the 8-bit image written (blended in float32, rounded to
    nearest, half up); a float cube in [0, 1] is rendered in floats and rounded after.

    All or nothing: the files are written into a hidden staging folder beside ``out_dir`` and
    moved into it (each with ``os.replace``) only once every one is written; on an error the
    staging folder is removed and ``out_dir`` is left as it was.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=temporary_prefix(out_dir), suffix=".partial",
                                    dir=out_dir.parent))
    try:
        staged = _render_into(cube, cameras, staging, depth_output=depth_output,
                              interpolation=interpolation, device=device, _layers=_layers,
                              min_object_pixels=min_object_pixels)
        out_dir.mkdir(parents=True, exist_ok=True)
        written = []
        for path in staged:
            target = out_dir / path.name
            os.replace(path, target)
            written.append(target)
        return written
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _render_into(cube: dict, cameras: dict[str, tuple], out_dir: Path, *, depth_output: str,
                 interpolation: str, device: str | torch.device,
                 _layers: dict | None, min_object_pixels: int = 1) -> list[Path]:
    from ..render.layer import OmniProjection

    face_size = int(cube["face_size"])
    written: list[Path] = []
    for name, (camera, rotation) in cameras.items():
        key = (name, face_size)
        layer = None if _layers is None else _layers.get(key)
        if layer is None:
            layer = OmniProjection(camera.to(device), face_size, interpolation=interpolation,
                                   fused_grid=False)
            if _layers is not None:
                _layers[key] = layer
        kwargs = {m: cube[m].to(device) for m in ("rgb", "depth", "labels") if m in cube}
        if "instances" in cube:   # labels and instance ids in one nearest pass
            if "labels" not in kwargs:
                raise ValueError("cube: 'instances' without 'labels' (the objects' classes)")
            kwargs["labels"] = pack_instances(kwargs["labels"], cube["instances"].to(device))
        # 8-bit faces are sampled as they are, into an 8-bit image with the channels innermost,
        # as the PNG holds them (no float copy of the cube or the image)
        levels = "rgb" in kwargs and kwargs["rgb"].dtype == torch.uint8
        if levels:
            kwargs["rgb"] = kwargs["rgb"].permute(0, 1, 3, 4, 2)   # (1, 6, F, F, 3)
        rot = None if rotation is None else rotation.to(device)
        with torch.no_grad():
            result = layer.render(**kwargs, rotation=rot, depth_output=depth_output,
                                  channels_last=levels)
        valid = result["valid"][0, 0].cpu()
        written.append(write_image(out_dir / f"{name}_valid.png",
                                   valid.to(torch.uint8) * 255))
        if "rgb" in result:
            if levels:   # (H, W, 3) uint8, rounded to nearest by the sampler
                rgb = result["rgb"][0]
            else:
                rgb = (result["rgb"][0].clamp(0, 1) * 255).round().to(torch.uint8) \
                    .permute(1, 2, 0)
            written.append(write_image(out_dir / f"{name}_rgb.png", rgb.cpu()))
        if "depth" in result:
            written.append(write_exr(out_dir / f"{name}_depth.exr",
                                     result["depth"][0, 0].float().cpu().contiguous()))
        if "labels" in result:
            labels = result["labels"][0].cpu()
            if "instances" in cube:
                labels, instances = unpack_instances(labels)
                written.append(write_image(out_dir / f"{name}_instances.png",
                                           instance_image(instances)))
                path = out_dir / f"{name}_objects.json"
                atomic_write_text(path, encode_objects(
                    instance_objects(instances, labels, min_pixels=min_object_pixels)))
                written.append(path)
            written.append(write_image(out_dir / f"{name}_labels.png",
                                       labels.clamp(0, 255).to(torch.uint8)))
            written.append(write_image(out_dir / f"{name}_labels_color.png", colorize(labels)))
    return written


def convert_captures(cubemaps_dir: str | Path, out_dir: str | Path, *, label_set: str = "13",
                     cameras: Sequence[str] = CAMERAS,
                     image_size: tuple[int, int] = (1024, 1024),
                     fisheye_model: str = "equidistant", fisheye_fov: float = math.radians(190),
                     catadioptric_xi: float | None = None,
                     catadioptric_fov: float = math.radians(220),
                     catadioptric_blind_fov: float | None = math.radians(40),
                     catadioptric_looking: str = "down", depth_output: str = "range",
                     interpolation: str = "bilinear", unknown_label: int | None = None,
                     device: str | torch.device = "cpu", ray: str | bool | None = None,
                     progress: bool | None = None,
                     min_object_pixels: int = 1) -> dict[str, list[Path]]:
    """Convert every capture under ``cubemaps_dir`` into omni images under ``out_dir``.

    Angles are radians. Cameras come from `omniscape_torch.cameras.presets.fisheye` (optical
    axis forward) and `catadioptric` (axis down or up); their
    JSON and rotations go to ``out_dir/cameras.json``.

    A capture that fails (missing, corrupt or mismatched face, unknown tag, an error while
    rendering or writing) is skipped with nothing written for it, and the others are still
    converted; the failures are raised together at the end.

    ``ray``: convert chunks of captures as Ray tasks (`distributed.run_on_ray`: the
    address of a cluster, or True for the one `distributed.ray_cluster` finds or
    starts; on CPUs, ``device="cpu"``), with the same files as without; ``cubemaps_dir`` and
    ``out_dir`` must be at the same path on every node. ``progress``: a tqdm bar over the
    captures on stderr (default: when stderr is a terminal). ``min_object_pixels``: with
    instance faces, the objects files list the objects of at least so many pixels (default 1:
    all).

    Returns:
        ``{capture_id: [paths written]}``.

    Raises:
        ConvertError: some captures failed (``.failures`` ``{capture_id: message}``, each
            message naming the file at fault; ``.results`` the captures converted).
        FileNotFoundError, ValueError: no captures at all, or bad arguments (before anything
            is converted).
        ImportError: ``ray`` without Ray installed (at once).
    """
    use_ray = ray is not None and ray is not False
    if use_ray:
        if torch.device(device).type != "cpu":   # a usage error first, Ray installed or not
            raise ValueError(f"device: with ray, captures are converted on the cluster's CPUs; "
                             f"got {device!r}")
        distributed.import_ray()
    if depth_output not in ("range", "z"):
        raise ValueError(f"depth_output: expected 'range' or 'z', got {depth_output!r}")
    if label_set not in LABEL_SETS:
        raise ValueError(f"label_set: expected one of {tuple(LABEL_SETS)}, got {label_set!r}")
    if isinstance(min_object_pixels, bool) or not isinstance(min_object_pixels, int) or \
            min_object_pixels < 1:
        raise ValueError(f"min_object_pixels: expected a positive integer, got "
                         f"{min_object_pixels!r}")
    captures = find_captures(cubemaps_dir)
    built = build_cameras(cameras, image_size=image_size, fisheye_model=fisheye_model,
                          fisheye_fov=fisheye_fov, catadioptric_xi=catadioptric_xi,
                          catadioptric_fov=catadioptric_fov,
                          catadioptric_blind_fov=catadioptric_blind_fov,
                          catadioptric_looking=catadioptric_looking)
    out_dir = Path(out_dir)
    check_pixels(image_size)
    meta = {name: {"camera": cam.to_dict(),
                   "rotation": None if rot is None else rot.double().tolist(),
                   "depth": depth_output}
            for name, (cam, rot) in built.items()}
    created = not out_dir.exists()
    layers: dict = {}
    results: dict[str, list[Path]] = {}
    failures: dict[str, str] = {}
    options = {"label_set": label_set, "unknown_label": unknown_label,
               "depth_output": depth_output, "interpolation": interpolation,
               "min_object_pixels": min_object_pixels}
    with folder_lock(out_dir):
        remove_stale_temporaries(out_dir)
        records, fits = _polynomial_models(built, meta, out_dir)
        if use_ray:
            h, w = image_size
            done, failed = distributed.run_on_ray(
                convert_chunk, (str(out_dir.resolve()), built, options),
                [str(c.resolve()) for c in captures], address=ray,
                memory=PROCESS_MEMORY + MEMORY_PER_PIXEL * h * w, progress=progress,
                desc="convert", unit="capture")
            results = {Path(c).name: paths for c, paths in done.items()}
            failures = {Path(c).name: message for c, message in failed.items()}
        else:
            from tqdm import tqdm
            if progress is None:
                progress = sys.stderr.isatty()
            for capture in tqdm(captures, disable=not progress, file=sys.stderr,
                                unit="capture", desc="convert"):
                done, failed = convert_chunk(out_dir, built, options, [capture],
                                             device=device, layers=layers)
                results.update({Path(c).name: paths for c, paths in done.items()})
                failures.update({Path(c).name: message for c, message in failed.items()})
        results = {c.name: results[c.name] for c in captures if c.name in results}
        failures = {c.name: failures[c.name] for c in captures if c.name in failures}
        if results:
            for name, fit in fits.items():     # the files before the records that name them
                records[name] = ocamcalib.write_calib_results(fit, out_dir / calib_file(name))
            for name in meta:
                meta[name]["ocamcalib"] = records[name]
            atomic_write_text(out_dir / "cameras.json", json.dumps(meta, indent=2) + "\n")
    if created and not results:   # nothing converted: nothing left behind either
        with contextlib.suppress(OSError):
            out_dir.rmdir()
    if failures:
        raise ConvertError(failures, results)
    return results


def convert_chunk(out_dir: str | Path, cameras: dict[str, tuple], options: dict,
                  captures: list[str | Path], *, device: str | torch.device = "cpu",
                  layers: dict | None = None) -> tuple[dict, dict]:
    """Convert ``captures`` (capture folders) into ``out_dir``, each on its own: a plain
    function of its arguments, which a local run and a Ray task
    (`distributed.run_on_ray`) call alike.

    Args:
        cameras: `build_cameras`' dict. options: ``label_set``, ``unknown_label``,
            ``depth_output``, ``interpolation``, ``min_object_pixels`` (as for
            `convert_captures`).
        layers: a dict that keeps the layers across calls (default: this call's).

    Returns:
        ``({capture: [paths written]}, {capture: message})``, keyed by the captures as given;
        a failed capture has nothing written, and its message names the file at fault.
    """
    out_dir = Path(out_dir)
    layers = {} if layers is None else layers
    done: dict = {}
    failures: dict = {}
    for capture in captures:
        try:
            cube = load_capture(capture, label_set=options["label_set"],
                                unknown_label=options["unknown_label"], rgb_uint8=True)
            done[capture] = render_capture(
                cube, cameras, out_dir / Path(capture).name,
                depth_output=options["depth_output"], interpolation=options["interpolation"],
                device=device, min_object_pixels=options.get("min_object_pixels", 1),
                _layers=layers)
        except Exception as err:   # noqa: BLE001 - reported per capture
            failures[capture] = distributed.describe_error(err)
    return done, failures


def _polynomial_models(built: dict[str, tuple], meta: dict, out_dir: Path
                       ) -> tuple[dict[str, dict], dict]:
    """``(records, fits)``: the OCamCalib record of each camera whose file ``out_dir`` holds
    already for the same camera (``cameras.json`` of an earlier run), and the polynomial
    model fitted to each other camera (``ocamcalib.fit_polynomial``), to write."""
    try:
        old = json.loads((out_dir / "cameras.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        old = None
    records, fits = {}, {}
    for name, (camera, _) in built.items():
        prev = old.get(name) if isinstance(old, dict) else None
        prev = prev if isinstance(prev, dict) else {}
        record = ocamcalib.cached_record(prev.get("ocamcalib"), out_dir / calib_file(name),
                                         meta[name]["camera"], prev.get("camera"))
        if record is None:
            fits[name] = ocamcalib.fit_polynomial(camera)
        else:
            records[name] = record
    return records, fits


def check_pixels(image_size: tuple[int, int]) -> None:
    """Refuse output images too large for this machine's memory, before any work (the faces'
    size is known only once a capture is read).

    Raises:
        MemoryError: with the estimate, the memory available and the largest square size that
            fits.
    """
    h, w = image_size
    need = PROCESS_MEMORY + MEMORY_PER_PIXEL * h * w
    available = available_memory()
    if need > available:
        side = int(math.sqrt(max(0.0, available - PROCESS_MEMORY) / MEMORY_PER_PIXEL))
        raise MemoryError(f"images of {h} x {w} pixels need about {need / 1e9:.1f} GB of memory, "
                          f"but {available / 1e9:.1f} GB are available; the largest square "
                          f"size that fits is about {side} x {side}")
