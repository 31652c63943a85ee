"""PyTorch datasets over what this package writes and reads.

* `OmniDataset`: a dataset written by ``omniscape-torch generate`` (layout in
  `omniscape_torch.data.generate`), one item per (finished frame, camera).
* `OmniShardDataset`: the same items streamed from WebDataset shards
  (`omniscape_torch.data.shards`; local files or URLs), an iterable dataset.
* `CubemapCaptureDataset`: simulator cubemap captures (layout in
  `omniscape_torch.data.captures`), one item per capture folder.

All hold only plain data (paths, tensors, dicts): they pickle, so they work with
``DataLoader(num_workers=N)``; items with objects (boxes) or of several camera models need
``collate_fn=collate``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import torch
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from ..cameras import Camera
from .format import MODALITIES, OPTIONAL_MODALITIES
from .readers import (has_modality, list_cameras, list_frames, read_camera_dict, read_dynamics,
                      read_extrinsics, read_frame, read_manifest)

__all__ = ["CubemapCaptureDataset", "OmniDataset", "OmniShardDataset", "PER_SAMPLE_KEYS",
           "collate"]

_DEFAULT = ("rgb", "depth", "labels", "valid")


#: Item keys with one value per object (a sample's own number of them): `collate` keeps
#: them as a list of B tensors, the structure the augmentation takes and returns.
PER_SAMPLE_KEYS = ("boxes", "box_labels", "box_instance_ids", "box_index", "box_visible",
                   "polygons", "polygon_box", "polygon_index")


def collate(batch: list[dict]) -> dict:
    """Collate items of these datasets (or augmented samples) into a batch:
    ``default_collate`` key by key, except that the per-object keys
    (`PER_SAMPLE_KEYS`: ``boxes``, ``box_labels``, ``box_instance_ids``, ...) stay a
    list of B tensors, whatever their sizes (``default_collate`` stacks equal sizes into one
    tensor and stops on different ones with torch's ``stack expects each tensor to be equal
    size``), and a key whose values do not stack (``intrinsics`` of cameras of different
    models, images of different sizes) becomes a plain list. Use as
    ``DataLoader(..., collate_fn=collate)`` for items with ``objects`` or a mix of cameras.

    Raises:
        ValueError: an empty batch, or items with different keys (names the key).
    """
    from torch.utils.data import default_collate

    if not batch:
        raise ValueError("batch: expected at least one item")
    keys = list(batch[0])
    for i, b in enumerate(batch):
        if set(b) != set(keys):
            odd = sorted(set(b) ^ set(keys))
            raise ValueError(f"batch: item {i} has other keys than item 0 ({', '.join(odd)})")
    out = {}
    for key in keys:
        values = [b[key] for b in batch]
        if key in PER_SAMPLE_KEYS:
            out[key] = values
            continue
        try:
            out[key] = default_collate(values)
        except (RuntimeError, TypeError):
            out[key] = values
    return out


def _check_modalities(modalities: tuple) -> None:
    for m in modalities:
        if m not in MODALITIES:
            raise ValueError(f"modalities: expected some of {tuple(MODALITIES)}, got {m!r}")


class OmniDataset(Dataset):
    """The finished frames of a generated dataset, one item per (frame, camera).

    Items are ordered frame-major: ``(frame 0, camera 0), (frame 0, camera 1), ...``
    (`items` lists them). Each item is a dict::

        frame          int
        camera         str
        rgb, depth, labels, labels_color, valid, instances
                       as in `omniscape_torch.data.readers.read_frame` (those of
                       ``modalities``; ``valid`` is ``(1, H, W)``, as the augmentation's)
        boxes, box_labels, box_instance_ids
                       with ``"objects"`` in ``modalities``: the objects' tight boxes
                       ``(N, 4)`` float32 (XYXY corners), class ids and instance ids
                       ``(N,)`` int64 (`omniscape_torch.data.objects`)
        model          str, the camera model's name
        intrinsics     (P,) float64, the model's parameters (``camera.json``'s params)
        image_size     (2,) int64, (H, W)
        T_world_camera (4, 4) float64, camera -> world at this frame
        T_rig_camera   (4, 4) float64, camera -> rig
        dynamics       the frame's record of ``dynamics.json`` (nested dict of floats)
        weather        str (when ``dataset.json`` names it)

    `camera` gives the `omniscape_torch.Camera` of a camera name. Batches of
    cameras of different models (or sizes) need ``collate_fn=```collate`: their
    ``intrinsics`` differ in length; so do batches with ``objects``: each item has its own
    number of boxes (`collate` keeps them as lists of B, as the augmentation takes
    them).

    Args:
        root: the dataset folder.
        cameras: the cameras to serve (default: all, in the writer's order).
        modalities: the images to read, some of ``rgb, depth, labels, labels_color, valid,
            instances, objects`` (the last two where the dataset has them:
            `has_modality`).
        frames: the frames to serve (default: all the finished ones, listed once here).
        rgb_uint8: rgb as ``(3, H, W)`` uint8 rather than float in [0, 1].
    """

    def __init__(self, root: str | Path, cameras: Sequence[str] | None = None,
                 modalities: Sequence[str] = _DEFAULT, *, frames: Sequence[int] | None = None,
                 rgb_uint8: bool = False):
        self.root = Path(root)
        available = list_cameras(self.root)
        self.cameras = list(available if cameras is None else cameras)
        for name in self.cameras:
            if name not in available:
                raise ValueError(f"cameras: {name!r} is not in {self.root} (has "
                                 f"{', '.join(available)})")
        self.modalities = tuple(modalities)
        _check_modalities(self.modalities)
        for m in self.modalities:
            if m in OPTIONAL_MODALITIES and not has_modality(self.root, m, self.cameras):
                raise ValueError(f"modalities: {self.root} has no {m!r} (a dataset written "
                                 f"before generate wrote them; a rerun of generate with its "
                                 f"options adds them)")
        finished = list_frames(self.root, self.cameras, modalities=self.modalities)
        if frames is None:
            self.frames = finished
        else:
            self.frames = [int(k) for k in frames]
            missing = sorted(set(self.frames) - set(finished))
            if missing:
                raise ValueError(f"frames: {missing} not finished in {self.root}")
        self.rgb_uint8 = bool(rgb_uint8)
        self._intrinsics = {c: read_camera_dict(self.root, c) for c in self.cameras}
        self._extrinsics = {c: read_extrinsics(self.root, c) for c in self.cameras}
        self._dynamics = read_dynamics(self.root)
        try:
            weather = read_manifest(self.root).get("weather_per_frame")
        except FileNotFoundError:
            weather = None
        self._weather = weather
        self.items = [(k, c) for k in self.frames for c in self.cameras]

    def __len__(self) -> int:
        return len(self.items)

    def camera(self, name: str, **kwargs):
        """The `omniscape_torch.Camera` of ``name`` (float64 unless ``dtype=``)."""
        return Camera.from_dict(self._intrinsics[name], **kwargs)

    def __getitem__(self, index: int) -> dict:
        if index < 0:
            index += len(self)
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} items")
        k, name = self.items[index]
        item = {"frame": k, "camera": name}
        item.update(read_frame(self.root, name, k, self.modalities, rgb_uint8=self.rgb_uint8))
        intr = self._intrinsics[name]
        extr = self._extrinsics[name]
        item["model"] = intr["model"]
        item["intrinsics"] = torch.tensor(list(intr["params"].values()), dtype=torch.float64)
        item["image_size"] = torch.tensor(intr["image_size"], dtype=torch.int64)
        item["T_world_camera"] = extr["T_world_camera"][k].clone()
        item["T_rig_camera"] = extr["T_rig_camera"].clone()
        item["dynamics"] = self._dynamics[k]
        if self._weather is not None and k < len(self._weather):
            item["weather"] = self._weather[k]
        return item


class OmniShardDataset(IterableDataset):
    """The items of `OmniDataset`, streamed from WebDataset shards with ``webdataset``
    (``pip install -e ".[webdataset]"``): for training where the dataset's folder is not, from
    shards on a shared disk, a web server or an object store.

    Each item is the dict `OmniDataset` gives for the same frame and camera (same keys,
    types and values). Shards are split between ``torch.distributed`` ranks and then between
    ``DataLoader`` workers (each reads whole shards: use at least as many shards as ranks times
    workers), so ``DataLoader(OmniShardDataset(...), batch_size=B, num_workers=N)`` reads each
    sample once per epoch.

    Args:
        source: a dataset folder (its ``shards/``), a shard folder, a list of shard paths or
            URLs, or one WebDataset URL (``".../shard-{000000..000063}.tar"``, ``"pipe:curl -s
            URL"``, ...): `omniscape_torch.data.shards.shard_urls`.
        cameras: the cameras to serve (default: all).
        modalities: the images to read, some of ``rgb, depth, labels, labels_color, valid,
            instances, objects`` (the last two where the shards hold them: a sample without
            them raises ValueError).
        rgb_uint8: rgb as ``(3, H, W)`` uint8 rather than float in [0, 1].
        shuffle: 0 (default) reads shards and samples in order; ``n > 0`` shuffles the shards,
            and the samples in a buffer of ``n``, from ``seed`` and the epoch
            (`set_epoch`): the same order for the same seed, epoch and worker count.
        seed: the shuffle's seed.
    """

    def __init__(self, source, cameras: Sequence[str] | None = None,
                 modalities: Sequence[str] = _DEFAULT, *, rgb_uint8: bool = False,
                 shuffle: int = 0, seed: int = 0):
        from .shards import shard_urls

        self.urls = shard_urls(source)
        self.cameras = None if cameras is None else list(cameras)
        self.modalities = tuple(modalities)
        _check_modalities(self.modalities)
        if isinstance(shuffle, bool) or not isinstance(shuffle, int) or shuffle < 0:
            raise ValueError(f"shuffle: expected a buffer size >= 0, got {shuffle!r}")
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise TypeError(f"seed: expected an integer, got {seed!r}")
        self.rgb_uint8 = bool(rgb_uint8)
        self.shuffle, self.seed, self.epoch = shuffle, seed, 0

    def set_epoch(self, epoch: int) -> None:
        """Shuffle the next pass differently (call before each epoch, as with
        ``DistributedSampler``)."""
        self.epoch = int(epoch)

    def __iter__(self):
        import random

        import webdataset as wds

        from .shards import decode_sample

        worker = get_worker_info()
        stages = [wds.SimpleShardList(self.urls)]
        if self.shuffle:
            stages.append(wds.detshuffle(len(self.urls), seed=self.seed, epoch=self.epoch - 1))
        stages += [wds.split_by_node, wds.split_by_worker, wds.tarfile_to_samples()]
        if self.shuffle:
            rng = random.Random(f"{self.seed}/{self.epoch}/{0 if worker is None else worker.id}")
            stages.append(wds.shuffle(self.shuffle, rng=rng))
        for sample in wds.DataPipeline(*stages):
            if self.cameras is not None and \
                    json.loads(sample["camera.json"])["camera"] not in self.cameras:
                continue
            yield decode_sample(sample, self.modalities, rgb_uint8=self.rgb_uint8)


class CubemapCaptureDataset(Dataset):
    """Simulator cubemap captures (``convert`` layout), one item per capture folder.

    Each item is `omniscape_torch.data.captures.load_capture`'s dict without its batch
    dimension (``rgb (6, 3, F, F)`` float32 in [0, 1], ``depth (6, F, F)`` float32 planar
    metres, ``labels (6, F, F)`` int64, ``instances (6, F, F)`` int64 object ids, those
    present), plus ``face_size`` (int) and
    ``capture`` (the folder's name). Faces in ``cubemap.FACES`` order.

    Args:
        root: a folder of capture folders, or one capture folder.
        label_set: the simulator's tag set, ``"13"``, ``"23"`` or ``"new"``.
        modalities: those required (default: whichever are there).
        unknown_label: class given to tags outside ``label_set`` (default: an error).
    """

    def __init__(self, root: str | Path, label_set: str = "13", *,
                 modalities: Sequence[str] | None = None, unknown_label: int | None = None):
        from .captures import find_captures
        from ..io.carla import LABEL_SETS
        if label_set not in LABEL_SETS:
            raise ValueError(f"label_set: expected one of {tuple(LABEL_SETS)}, got {label_set!r}")
        self.root = Path(root)
        self.captures = find_captures(self.root)
        self.label_set = label_set
        self.modalities = None if modalities is None else tuple(modalities)
        self.unknown_label = unknown_label

    def __len__(self) -> int:
        return len(self.captures)

    def __getitem__(self, index: int) -> dict:
        from .captures import load_capture
        path = self.captures[index]
        cube = load_capture(path, label_set=self.label_set, modalities=self.modalities,
                            unknown_label=self.unknown_label)
        item = {k: (v[0] if isinstance(v, torch.Tensor) else v) for k, v in cube.items()}
        item["capture"] = path.name
        return item
