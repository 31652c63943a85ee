"""What every export shares: the samples (a dataset's frames, or a stream of augmented
samples) as plain arrays, the class subset, the train/val split by frame, and the settings
file that keeps a rerun consistent with the run it completes."""

from __future__ import annotations

import json
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np
import torch
from torch import Tensor

from ...io.atomic import atomic_write_text
from ...io.labels import IGNORE_INDEX
from .. import format as fmt
from ..objects import instance_objects

#: The splits an export writes, in this order.
SPLITS = ("train", "val")
#: The file in the export folder that records the export's settings.
SETTINGS = "export.json"
SETTINGS_FORMAT = "omniscape_torch export"


@dataclass
class Sample:
    """One image to export, as plain arrays.

    ``name``: the file stem (without extension); ``number``: the image's number in names
    that take one (a dataset's frame, a stream's position); ``frame``, ``camera``: where it
    comes from (None where a stream does not say); ``rgb``: ``(H, W, 3)`` uint8, or
    ``rgb_png``: the PNG's bytes (copied as they are); ``labels`` ``(H, W)`` int64 class
    ids (255 not valid); ``instances`` ``(H, W)`` int64 ids (0 none); ``objects``: the
    objects to export, each
    ``{"instance_id" (or None), "label", "box": [x0, y0, x1, y1], "pixels" (or None),
    "keypoints": (K, 3) [x, y, v] or None}``, boxes in XYXY corners.
    """

    name: str
    number: int
    size: tuple[int, int]
    frame: int | None = None
    camera: str | None = None
    rgb: np.ndarray | None = None
    rgb_png: bytes | None = None
    labels: np.ndarray | None = None
    instances: np.ndarray | None = None
    objects: list[dict] = field(default_factory=list)

    def png(self) -> bytes:
        """The RGB image as PNG bytes."""
        if self.rgb_png is not None:
            return self.rgb_png
        from ...io.images import encode_image

        return encode_image(self.rgb, ".png")


def class_ids(classes: Sequence[str | int] | None, class_names: Sequence[str],
              default: Sequence[str]) -> list[int]:
    """The class ids of a user's subset (names or ids, in the user's order; default:
    ``default``, those of ``class_names`` that are in it, in id order).

    Raises:
        ValueError: an unknown name or id, or a class given twice (names ``classes``).
    """
    names = list(class_names)
    if classes is None:
        return [i for i, n in enumerate(names) if n in default]
    if isinstance(classes, str):
        classes = [c for c in classes.split(",") if c.strip()]
    out = []
    for c in classes:
        if isinstance(c, str) and c.strip() in names:
            i = names.index(c.strip())
        elif isinstance(c, str) and c.strip().isdigit() and int(c) < len(names):
            i = int(c)
        elif isinstance(c, int) and not isinstance(c, bool) and 0 <= c < len(names):
            i = c
        else:
            raise ValueError(f"classes: expected names or ids of {', '.join(names)}, got {c!r}")
        if i in out:
            raise ValueError(f"classes: {names[i]} given twice")
        out.append(i)
    if not out:
        raise ValueError("classes: expected at least one class")
    return out


def check_fraction(val_fraction) -> float:
    """``val_fraction`` as a float in [0, 1).

    Raises:
        ValueError: anything else, naming ``val_fraction``.
    """
    if isinstance(val_fraction, bool) or not isinstance(val_fraction, (int, float)) or \
            not 0.0 <= float(val_fraction) < 1.0:
        raise ValueError(f"val_fraction: expected a number in [0, 1), got {val_fraction!r}")
    return float(val_fraction)


def check_seed(seed) -> int:
    """``seed`` as an int.

    Raises:
        ValueError: anything else, naming ``seed``.
    """
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"seed: expected an integer, got {seed!r}")
    return seed


def split_frames(frames: Sequence[int], val_fraction: float = 0.1, seed: int = 0) -> set[int]:
    """The frames of the validation split: ``round(val_fraction * len(frames))`` of them, at
    least one when ``val_fraction > 0`` and there are two frames or more, and never all,
    drawn by a permutation seeded with ``seed`` (the same frames for the same frames, fraction
    and seed, on any machine). Every camera of a frame goes to the frame's split, so that
    no view of a validation frame is trained on.

    Raises:
        ValueError: ``val_fraction`` outside [0, 1), a seed that is not an integer.
    """
    val_fraction, seed = check_fraction(val_fraction), check_seed(seed)
    frames = sorted(set(int(k) for k in frames))
    n = len(frames)
    if val_fraction == 0.0 or n < 2:
        return set()
    count = min(max(1, round(val_fraction * n)), n - 1)
    order = np.random.default_rng(seed).permutation(n)
    return {frames[i] for i in order[:count].tolist()}


def stream_split(frame: int, val_fraction: float, seed: int) -> str:
    """The split of a streamed sample of ``frame``: ``val`` with probability
    ``val_fraction``, decided by ``(seed, frame)`` alone (a stream's length is not known
    ahead, so the count is not exact)."""
    if val_fraction == 0.0:
        return "train"
    return "val" if random.Random(f"{seed}/{frame}").random() < val_fraction else "train"


# --------------------------------------------------------------------------------------------
# A dataset folder's frames
# --------------------------------------------------------------------------------------------

def dataset_samples(root: Path, cameras: Sequence[str], frames: Sequence[int],
                    modalities: Sequence[str]) -> Iterator[Sample]:
    """The dataset's images, frame-major, with the maps ``modalities`` asks for (some of
    ``labels``, ``instances``) and, with ``instances``, the objects its objects file lists.

    Raises:
        ValueError: an objects file naming an id its instance map lacks.
    """
    from ..readers import read_frame

    for k in frames:
        for c in cameras:
            rgb = (root / fmt.frame_file(c, "rgb", k)).read_bytes()
            # the objects as objects/NNNNNN.json lists them (checked when read): the tight
            # boxes and classes of the instance map, written beside it
            item = read_frame(root, c, k, tuple(modalities)
                              + (("objects",) if "instances" in modalities else ()))
            labels = item["labels"].numpy() if "labels" in item else None
            instances = item["instances"].numpy() if "instances" in item else None
            size = next((a.shape for a in (labels, instances) if a is not None), None)
            if size is None:
                from ...io.images import decode_image

                size = decode_image(rgb).shape[:2]
            s = Sample(name=f"{fmt.frame_name(k)}_{c}", number=k, size=tuple(size), frame=k,
                       camera=c, rgb_png=rgb, labels=labels, instances=instances)
            if instances is not None:
                ids, counts = np.unique(instances[instances > 0], return_counts=True)
                pixels = dict(zip(ids.tolist(), counts.tolist()))
                for box, label, i in zip(item["boxes"].tolist(), item["box_labels"].tolist(),
                                         item["box_instance_ids"].tolist()):
                    if i not in pixels:
                        raise ValueError(f"{root / fmt.frame_file(c, 'objects', k)}: instance "
                                         f"{i} is not in {fmt.frame_file(c, 'instances', k)}")
                    s.objects.append({"instance_id": i, "label": label,
                                      "box": [int(v) for v in box], "pixels": pixels[i],
                                      "keypoints": None})
            yield s


def _map_objects(instances: Tensor, labels: Tensor | None, label_of: dict) -> list[dict]:
    """The objects of an instance map: classes from ``labels`` (the most frequent), else
    from ``label_of`` (id -> class; ids it lacks are left out)."""
    if labels is None:
        labels = torch.zeros_like(instances)
    objects = instance_objects(instances, labels)
    out = []
    for o in objects:
        label = o["label"] if not label_of else label_of.get(o["instance_id"])
        if label is None:
            continue
        out.append({"instance_id": o["instance_id"], "label": int(label), "box": o["box"],
                    "pixels": o["pixels"], "keypoints": None})
    return out


# --------------------------------------------------------------------------------------------
# A stream of samples (the augmentation's outputs, a dataset's items)
# --------------------------------------------------------------------------------------------

def _plain(t) -> Tensor:
    return t.as_subclass(Tensor) if isinstance(t, Tensor) and type(t) is not Tensor else t


def _unbatch(sample: dict, where: str) -> list[dict]:
    """A sample dict, or a batched one (``rgb (B, 3, H, W)``) split into its B samples."""
    if not isinstance(sample, dict):
        raise TypeError(f"{where}: expected a dict with rgb (and labels, instances, boxes), got "
                        f"{type(sample).__name__}")
    if "rgb" not in sample:
        raise ValueError(f"{where}: no 'rgb' (the image to export)")
    rgb = sample["rgb"]
    if not isinstance(rgb, Tensor) or rgb.dim() not in (3, 4):
        raise ValueError(f"{where}: rgb: expected a (3, H, W) or (B, 3, H, W) tensor, got "
                         f"{getattr(rgb, 'shape', type(rgb).__name__)}")
    if rgb.dim() == 3:
        return [sample]
    b = rgb.shape[0]
    out = []
    for i in range(b):
        one = {}
        for key, value in sample.items():
            if isinstance(value, Tensor) and value.dim() >= 1 and value.shape[0] == b and \
                    key != "params":
                one[key] = value[i]
            elif isinstance(value, (list, tuple)) and len(value) == b:
                one[key] = value[i]
            elif key in ("frame", "camera", "split"):
                if isinstance(value, (list, tuple, Tensor)) and \
                        not (isinstance(value, Tensor) and value.dim() == 0):
                    raise ValueError(f"{where}: {key}: expected one per sample ({b}), got "
                                     f"{len(value)}")
                one[key] = value   # one for the whole batch
        out.append(one)
    return out


def _array(sample: dict, key: str, where: str, dims: int) -> np.ndarray | None:
    value = sample.get(key)
    if value is None:
        return None
    value = _plain(value)
    if not isinstance(value, Tensor) or value.dim() != dims:
        raise ValueError(f"{where}: {key}: expected a tensor of {dims} dimensions, got "
                         f"{getattr(value, 'shape', type(value).__name__)}")
    return value.detach().cpu().numpy()


def _rgb_uint8(rgb: Tensor, where: str) -> np.ndarray:
    rgb = _plain(rgb).detach().cpu()
    if rgb.shape[0] != 3:
        raise ValueError(f"{where}: rgb: expected (3, H, W), got {tuple(rgb.shape)}")
    if rgb.is_floating_point():
        rgb = (rgb.clamp(0, 1) * 255).round().to(torch.uint8)
    elif rgb.dtype != torch.uint8:
        raise TypeError(f"{where}: rgb: expected floats in [0, 1] or uint8, got {rgb.dtype}")
    return rgb.permute(1, 2, 0).contiguous().numpy()


def _keypoints(sample: dict, rows: int, where: str) -> np.ndarray | None:
    """``keypoints`` as ``(rows, K, 3)`` [x, y, v] (v = 2 visible, 0 not; COCO's), or None."""
    kp = sample.get("keypoints")
    if kp is None:
        return None
    kp = _plain(kp).detach().cpu().double()
    if kp.dim() == 2:
        kp = kp.unsqueeze(0)
    if kp.dim() != 3 or kp.shape[-1] != 2 or kp.shape[0] != rows:
        raise ValueError(f"{where}: keypoints: expected (N, K, 2), a row per object (N = "
                         f"{rows}: box_instance_ids' or boxes' length), got {tuple(kp.shape)}")
    ok = torch.isfinite(kp).all(-1)
    if sample.get("keypoints_valid") is not None:
        valid = _plain(sample["keypoints_valid"]).detach().cpu().bool().reshape(ok.shape)
        ok = ok & valid
    xy = torch.where(ok[..., None], kp, torch.zeros_like(kp))
    v = torch.where(ok, 2.0, 0.0)[..., None].to(xy.dtype)
    return torch.cat((xy, v), -1).numpy()


def stream_samples(samples: Iterable[dict], val_fraction: float, seed: int
                   ) -> Iterator[tuple[Sample, str]]:
    """Plain samples of a stream and the split of each (a sample's ``split``, else by its
    ``frame``, else by its position in the stream)."""
    index = 0
    for n, batch in enumerate(samples):
        for sample in _unbatch(batch, f"samples[{n}]"):
            where = f"samples[{n}]" + ("" if sample is batch else f" (image {index})")
            rgb = _rgb_uint8(sample["rgb"], where)
            labels = _array(sample, "labels", where, 2)
            instances = _array(sample, "instances", where, 2)
            size = rgb.shape[:2]
            for key, a in (("labels", labels), ("instances", instances)):
                if a is not None and a.shape != size:
                    raise ValueError(f"{where}: {key}: expected {size} (rgb's size), got "
                                     f"{a.shape}")
            frame = sample.get("frame")
            frame = None if frame is None else int(frame)
            camera = sample.get("camera")
            s = Sample(name=fmt.frame_name(index), number=index, size=tuple(size), frame=frame,
                       camera=None if camera is None else str(camera), rgb=rgb,
                       labels=None if labels is None else labels.astype(np.int64),
                       instances=None if instances is None else instances.astype(np.int64))
            s.objects = _stream_objects(sample, s, where)
            split = sample.get("split") or stream_split(index if frame is None else frame,
                                                        val_fraction, seed)
            if split not in SPLITS:
                raise ValueError(f"{where}: split: expected one of {SPLITS}, got {split!r}")
            yield s, split
            index += 1


def _ids(sample: dict, key: str, where: str) -> list[int] | None:
    value = sample.get(key)
    if value is None:
        return None
    value = _plain(value)
    if not isinstance(value, Tensor) or value.dim() != 1 or value.is_floating_point():
        raise ValueError(f"{where}: {key}: expected a (N,) integer tensor, got "
                         f"{getattr(value, 'shape', type(value).__name__)}")
    return value.tolist()


def _stream_objects(sample: dict, s: Sample, where: str) -> list[dict]:
    """A streamed sample's objects: those of its instance map (masks, tight boxes), else its
    ``boxes`` with their ``box_labels`` (by position, or through ``box_index``)."""
    box_labels = _ids(sample, "box_labels", where)
    box_ids = _ids(sample, "box_instance_ids", where)
    if s.instances is not None:
        label_of = {}
        if s.labels is None:
            if box_ids is None or box_labels is None or len(box_ids) != len(box_labels):
                raise ValueError(f"{where}: instances without labels: expected box_instance_ids "
                                 f"and box_labels of one length (the class of each id)")
            label_of = dict(zip(box_ids, box_labels))
        objects = _map_objects(torch.from_numpy(s.instances),
                               None if s.labels is None else torch.from_numpy(s.labels),
                               label_of)
        if sample.get("keypoints") is not None:
            if box_ids is None:
                raise ValueError(f"{where}: keypoints: expected box_instance_ids beside them "
                                 f"(the object of each row)")
            kp = _keypoints(sample, len(box_ids), where)
            row = {i: r for r, i in enumerate(box_ids)}
            for o in objects:
                if o["instance_id"] in row:
                    o["keypoints"] = kp[row[o["instance_id"]]]
        return objects
    boxes = sample.get("boxes")
    if boxes is None:
        return []
    boxes = _plain(boxes)
    if not isinstance(boxes, Tensor) or boxes.dim() != 2 or boxes.shape[-1] != 4:
        raise ValueError(f"{where}: boxes: expected (N, 4) XYXY corners, got "
                         f"{getattr(boxes, 'shape', type(boxes).__name__)}")
    m = boxes.shape[0]
    if box_labels is None:
        raise ValueError(f"{where}: boxes: expected box_labels (the class of each box)")
    if len(box_labels) != m:
        index = _ids(sample, "box_index", where)
        if index is None or len(index) != m:
            raise ValueError(f"{where}: box_labels: expected one per box ({m}), or the input's "
                             f"with box_index (the augmentation's), got {len(box_labels)}")
        box_labels = [box_labels[i] for i in index]
    kp = _keypoints(sample, m, where)
    out = []
    for r, (box, label) in enumerate(zip(boxes.detach().cpu().double().tolist(), box_labels)):
        if not all(np.isfinite(box)) or box[2] <= box[0] or box[3] <= box[1]:
            continue
        out.append({"instance_id": None, "label": int(label), "box": box, "pixels": None,
                    "keypoints": None if kp is None else kp[r]})
    return out


def remap(labels: np.ndarray, table: np.ndarray) -> np.ndarray:
    """``table[labels]`` for class ids 0..255 (uint8); ids outside map to ``table[255]``."""
    lab = np.where((labels >= 0) & (labels < 256), labels, IGNORE_INDEX)
    return table[lab]


# --------------------------------------------------------------------------------------------
# The settings of an export folder
# --------------------------------------------------------------------------------------------

def check_settings(out: Path, settings: dict) -> None:
    """Write ``out/export.json`` (``finished`` false), or, where it is there, check that it
    records the same settings (a rerun completes the export it records).

    Raises:
        ValueError: the folder holds an export with other settings (names each).
    """
    path = out / SETTINGS
    if path.is_file():
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except ValueError:
            old = None
        if not isinstance(old, dict) or old.get("format") != SETTINGS_FORMAT:
            raise ValueError(f"{path}: not an export's settings file; export to another "
                             f"folder")
        differ = [f"{k}: the folder has {old['settings'].get(k)!r}, this run {v!r}"
                  for k, v in settings.items() if old.get("settings", {}).get(k) != v]
        if differ:
            raise ValueError(f"{out}: holds an export with other settings ({'; '.join(differ)}); "
                             f"rerun with the folder's settings to complete it, or export to "
                             f"another folder or remove it")
    else:
        write_settings(out, settings, finished=False)


def write_settings(out: Path, settings: dict, *, finished: bool, summary: dict | None = None
                   ) -> None:
    """``out/export.json``: the settings, whether the export finished, and its summary."""
    record = {"format": SETTINGS_FORMAT, "settings": settings, "finished": finished}
    if summary is not None:
        record["summary"] = summary
    atomic_write_text(out / SETTINGS, json.dumps(record, indent=2) + "\n")

