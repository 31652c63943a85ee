"""Exports to the formats training tools read: COCO, mmsegmentation, Cityscapes and YOLO.

``omniscape-torch export {coco,mmseg,cityscapes,yolo} DATASET --out DIR`` writes a generated
dataset's frames ([`export_dataset`][omniscape_torch.data.export.export_dataset]); the same
formats from a stream of samples, such as the augmentation modules' outputs
([`export_samples`][omniscape_torch.data.export.export_samples]). Each format's layout is in
its module: `coco` (instances JSON, RLE masks), `segyolo` (mmsegmentation's `img_dir`/`ann_dir`
and YOLO's `images`/`labels`/`data.yaml`), `cityscapes` (`leftImg8bit`/`gtFine` in Cityscapes'
label ids).

Every export takes a class subset (`classes`: names or ids; default: the instance classes for
`coco` and `yolo`, all classes for `mmseg` and `cityscapes`) and splits the images into
`train` and `val` by frame ([`split_frames`][omniscape_torch.data.export.split_frames]: every
camera of a frame in one split, the same frames for the same seed). Every file is written
atomically (temporary file + rename); `OUT/export.json` records the settings (and, at the
end, `"finished": true` and the counts), so an interrupted export is completed by the same
call again, and one with other settings into the same folder is refused, naming them.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from ...io.atomic import check_writable, folder_lock
from ...io.labels import CLASSES, PALETTE
from ..format import INSTANCE_CLASSES
from ._samples import (SETTINGS, SPLITS, check_fraction, check_seed, check_settings,
                       class_ids, dataset_samples, split_frames, stream_samples, write_settings)
from .coco import coco_rle

__all__ = ["FORMATS", "SETTINGS", "SPLITS", "coco_rle", "export_dataset", "export_samples",
           "split_frames"]

#: The formats, in the command line's order.
FORMATS = ("coco", "mmseg", "cityscapes", "yolo")
#: The maps each format reads from a dataset.
_NEEDS = {"coco": ("labels", "instances"), "mmseg": ("labels",),
          "cityscapes": ("labels", "instances"), "yolo": ("labels", "instances")}


def _check_format(format: str) -> str:
    if format not in FORMATS:
        raise ValueError(f"format: expected one of {', '.join(FORMATS)}, got {format!r}")
    return format


def _writer(format: str, out: Path, ids: list[int], names: list[str], palette):
    if format == "coco":
        from .coco import CocoWriter
        return CocoWriter(out, ids, names)
    if format == "cityscapes":
        from .cityscapes import CityscapesWriter
        return CityscapesWriter(out, ids, names)
    from .segyolo import MmsegWriter, YoloWriter
    if format == "mmseg":
        return MmsegWriter(out, ids, names, palette)
    return YoloWriter(out, ids, names)


def _default_classes(format: str, names: Sequence[str]) -> Sequence[str]:
    if format in ("coco", "yolo"):
        default = [n for n in names if n in INSTANCE_CLASSES]
        return default or [n for i, n in enumerate(names) if i > 0]
    return list(names)


def _run(format, out, settings, ids, names, palette, items, total, progress, log) -> dict:
    from tqdm import tqdm

    out = Path(out)
    writer = _writer(format, out, ids, names, palette)   # its checks, before any file
    check_writable(out)
    with folder_lock(out):
        check_settings(out, settings)
        if progress is None:
            progress = sys.stderr.isatty()
        for sample, split in tqdm(items, total=total, disable=not progress, file=sys.stderr,
                                  unit="image", desc=f"export {format}"):
            writer.add(sample, split)
        summary = writer.finish()
        summary = {"format": format, "out": str(out), **summary}
        write_settings(out, settings, finished=True,
                       summary={k: v for k, v in summary.items() if k != "files"})
    log(f"{format}: {summary['images']['train']} train and {summary['images']['val']} val "
        f"image(s) in {out}")
    return summary


def export_dataset(format: str, root: str | Path, out: str | Path, *,
                   classes: Sequence[str | int] | None = None, val_fraction: float = 0.1,
                   seed: int = 0, cameras: Sequence[str] | None = None,
                   progress: bool | None = None,
                   log: Callable[[str], None] | None = None) -> dict:
    """Export a generated dataset's finished frames (``omniscape-torch export``).

    Args:
        format: ``coco``, ``mmseg``, ``cityscapes`` or ``yolo`` (layouts in the modules
            `coco`, `segyolo` and `cityscapes` of this package).
        root: the dataset folder (``generate``'s layout; ``coco``, ``cityscapes`` and
            ``yolo`` need its instance maps, which datasets written before them lack).
        out: the export folder (created).
        classes: the class subset, names or ids of the dataset's classes (default: its
            instance classes for ``coco`` and ``yolo``, all for ``mmseg`` and
            ``cityscapes``); for ``coco`` and ``yolo``, instance classes only.
        val_fraction: the share of the frames in the ``val`` split ([`split_frames`]
            [omniscape_torch.data.export.split_frames]).
        seed: the split's seed.
        cameras: the cameras to export (default: all).
        progress: a progress bar on stderr (default: when it is a terminal).
        log: called with a line when done.

    Returns:
        ``{"format", "out", "images": {"train": n, "val": n}, "files": [...]}`` and, for
        ``coco`` and ``yolo``, ``"annotations": {"train": n, "val": n}`` (objects written).

    Raises:
        ValueError: an unknown format, class, camera; a dataset without the instance maps
            the format needs; a folder holding an export with other settings.
        FileNotFoundError: not a dataset folder.
        omniscape_torch.io.atomic.FolderBusyError: another export is writing ``out``.
    """
    from ..readers import has_modality, list_cameras, list_frames, read_manifest

    format = _check_format(format)
    val_fraction, seed = check_fraction(val_fraction), check_seed(seed)
    root = Path(root)
    manifest = read_manifest(root)
    names = list(manifest.get("classes", CLASSES))
    palette = np.asarray(manifest.get("palette", PALETTE.tolist()), dtype=np.uint8)
    available = list_cameras(root)
    cameras = list(available if cameras is None else cameras)
    for c in cameras:
        if c not in available:
            raise ValueError(f"cameras: {c!r} is not in {root} (has {', '.join(available)})")
    if Path(out).resolve() == root.resolve() or root.resolve() in Path(out).resolve().parents:
        raise ValueError(f"out: {out} is inside the dataset {root}; export to another folder")
    modalities = _NEEDS[format]
    if "instances" in modalities and not has_modality(root, "instances", cameras):
        if format != "cityscapes":
            raise ValueError(f"{root}: has no instance maps (a dataset written before generate "
                             f"wrote them; a rerun of generate with its options adds them): "
                             f"the {format} export needs them")
        modalities = ("labels",)
    ids = class_ids(classes, names, _default_classes(format, names))
    if format in ("coco", "yolo"):
        stuff = [names[i] for i in ids if names[i] not in INSTANCE_CLASSES]
        if stuff:
            raise ValueError(f"classes: {', '.join(stuff)}: no objects (the objects are "
                             f"those of the instance classes: {', '.join(INSTANCE_CLASSES)})")
    frames = list_frames(root, cameras, modalities=modalities)
    if not frames:
        raise ValueError(f"{root}: no finished frames to export (run generate first)")
    val = split_frames(frames, val_fraction, seed)
    settings = {"export": format, "source": str(root.resolve()), "cameras": cameras,
                "classes": [names[i] for i in ids], "val_fraction": val_fraction,
                "seed": seed, "frames": frames}
    items = ((s, "val" if s.frame in val else "train")
             for s in dataset_samples(root, cameras, frames, modalities))
    return _run(format, out, settings, ids, names, palette, items, len(frames) * len(cameras),
                progress, log or (lambda msg: None))


def export_samples(format: str, samples: Iterable[dict], out: str | Path, *,
                   classes: Sequence[str | int] | None = None,
                   class_names: Sequence[str] = CLASSES, palette=PALETTE,
                   val_fraction: float = 0.1, seed: int = 0, progress: bool | None = False,
                   log: Callable[[str], None] | None = None) -> dict:
    """Export a stream of samples: the augmentation modules' outputs, a dataset's items.

    A sample is a dict (one image, or a batch of B, as the augmentation returns them: then
    split into its B images) with:

    - ``rgb``: ``(3, H, W)`` (or ``(B, 3, H, W)``) floats in [0, 1] or uint8 (required);
    - ``labels``: ``(H, W)`` class ids, 255 not valid (``mmseg`` and ``cityscapes`` need it);
    - ``instances``: ``(H, W)`` instance ids, 0 none: the objects, each id one, its class the
      label most of its pixels have (without ``labels``: ``box_labels`` of its position in
      ``box_instance_ids``), its box and mask from its pixels;
    - else ``boxes`` ``(N, 4)`` XYXY corners with ``box_labels`` ``(N,)`` (or the input's
      ``box_labels`` with the augmentation's ``box_index``): objects with a box only;
    - ``keypoints`` ``(N, K, 2)`` corner coordinates, a row per object (of
      ``box_instance_ids``, else of ``boxes``), with ``keypoints_valid`` ``(N, K)``
      optionally (NaN coordinates count as not valid): COCO's keypoints;
    - ``frame``, ``camera`` (optional): recorded, and ``frame`` decides the split;
      ``split`` (``"train"`` or ``"val"``) sets it.

    Images are named by their position in the stream (``000000``, ...). Without ``split``,
    a sample is in ``val`` with probability ``val_fraction``, decided by ``(seed, frame)``
    (its position where it has no ``frame``): a stream's length is not known ahead. A rerun
    into the same folder rewrites the images of the same positions (a shorter stream leaves
    the later ones there): export another stream into another folder.

    Args:
        format: ``coco``, ``mmseg``, ``cityscapes`` or ``yolo``.
        samples: an iterable of such dicts.
        out: the export folder (created).
        classes: the class subset, names or ids of ``class_names`` (default: the instance
            classes for ``coco`` and ``yolo``, all for ``mmseg`` and ``cityscapes``).
        class_names: the name of each class id (default CARLA's 13).
        palette: ``(C, 3)`` uint8 colours of the classes (``mmseg``'s metadata).
        val_fraction: the share of the samples in the validation split (above).
        seed: the seed of the split (above).
        progress: a progress bar on stderr. log: called with a line when done.

    Returns:
        As [`export_dataset`][omniscape_torch.data.export.export_dataset].

    Raises:
        ValueError, TypeError: a sample without what the format needs, or of the wrong shapes
            (names the sample and the key); an unknown format or class.
    """
    format = _check_format(format)
    val_fraction, seed = check_fraction(val_fraction), check_seed(seed)
    names = [str(n) for n in class_names]
    ids = class_ids(classes, names, _default_classes(format, names))
    settings = {"export": format, "source": "samples", "classes": [names[i] for i in ids],
                "val_fraction": val_fraction, "seed": seed}
    items = stream_samples(samples, val_fraction, seed)
    return _run(format, out, settings, ids, names, np.asarray(palette, dtype=np.uint8), items,
                None, progress, log or (lambda msg: None))
