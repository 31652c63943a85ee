"""Proof that it helps: segmentation trained with four augmentations, tested on omni images.

Issue 17, item 7. A small segmentation network (:class:`TinyUNet`, a three-level U-Net of about
120k parameters) is trained on ``--threads`` CPU threads (default 2) with four augmentation
conditions, and each network is evaluated on fisheye and catadioptric images that the
project's own generator writes (``omniscape-torch generate``), as mIoU over their valid area,
for ``--seeds`` seeds (default 0, 1, 2). Conditions (``CONDITIONS``):

* ``none`` (a): the perspective views as they are;
* ``kornia_fisheye`` (b): kornia's ``RandomFisheye`` (center_x, center_y in [-0.3, 0.3],
  gamma in [0.9, 1.0]: the ranges of its docstring's example; p = 1), applied to the image and
  the labels with ``AugmentationSequential(data_keys=["input", "mask"])``. kornia 0.9 raises
  ``NotImplementedError`` for ``RandomFisheye`` on a mask key (kornia issue 4420), so
  :class:`KorniaFisheye` adds the mask path: the same sampling field as kornia's image path,
  read with nearest neighbour, and ``IGNORE_INDEX`` (255) where the field leaves the source
  (where the image gets kornia's zero padding). kornia draws from torch's global RNG: every
  call runs inside ``torch.random.fork_rng`` after ``torch.manual_seed`` of a seed drawn from
  the run's own generator, so its draws are reproducible and the global state is left as it was;
* ``reproject`` (c): this project's perspective -> fisheye augmentation,
  ``ot.augment.RandomReproject(image_size=(S, S), source_fov=90 deg, seed=seed,
  fisheye_models=("equidistant",))``, its other settings at their defaults (fov 160-200 deg,
  roll +-25, pitch and yaw +-10 deg), given the faces' own intrinsics (DESIGN.md:
  ``f = F / 2``, ``c = (F - 1) / 2``);
* ``omni_camera`` (d): ``ot.augment.RandomOmniCamera((S, S), F, mode="fisheye", seed=seed)``
  (its defaults: equidistant, fov 160-200 deg, roll +-25, pitch +-10 deg, any yaw) on whole
  cubemaps (``--omni-mode mixed`` adds catadioptric cameras).

Training data: ``--cubes`` cubemaps (default 48) of the built-in town ``--train-town``
(default 0, ``Town.render_cubemap``, clear noon), rendered once and cached, one ``.pt`` file per
cube written atomically (``--cache``, default ``out/bench_training`` in the repository, which git
ignores; a cube is rendered again when its file is missing or holds other settings). Cube ``i``
stands on the road at a position drawn from ``torch.Generator().manual_seed(train_town)``:
across the driving lanes (``|x| < 3.5`` m), 0.8-1.2 m above the ground (the generator's rig
puts its cameras at 0.8 and 1.0 m), anywhere along the town (``|z| < 70`` m), at a time of
0-30 s for the moving objects; the cube axes are the world axes (front looks along the road).
RGB is stored as ``uint8`` (rounded as the generator rounds its PNGs) and used as float in
[0, 1]. Conditions (a)-(c) train on the four horizontal faces of every cube (front, back, left,
right: 90-degree pinhole views, ``S x S``, upright, as a perspective dataset gives them; up and
down are left out), condition (d) on the whole cubemaps (faces ``S x S``).

Evaluation data: ``generate`` with ``DatasetConfig(frames=--eval-frames, image_size=(S, S),
seed=--eval-seed)`` (default 24 frames, seed 1: another town layout than the training one, and
the generator's motorcycle ride through it), cached in ``--cache`` too, read with
``ot.OmniDataset``. The fisheye cameras (``fisheye_left``, ``fisheye_right``: equidistant,
190 deg) and the catadioptric ones (``catadioptric_left/right``: unified, xi 0.9, 220 deg, looking
down) are reported apart. IoU per class from one confusion matrix over every valid pixel of the
camera kind (labels 0..12; ``IGNORE_INDEX`` = 255 outside the valid area is not counted); the
mIoU is the mean over the classes present in that kind's ground truth (a class absent from the
evaluation set has no IoU and is left out of the mean; the JSON lists them). ``Unlabeled`` (id 0,
the sky in the town) is a class like the others.

Training, the same for every condition: ``--steps`` steps (default 400) of ``--batch`` samples
(default 8) drawn with replacement from the training set by ``torch.Generator().manual_seed(
1000 + seed)`` (so conditions (a)-(c) see the same faces in the same order), cross-entropy
ignoring 255, AdamW (lr ``--lr`` 3e-3, weight decay 1e-4) with cosine decay to 0 over the
steps; batch statistics in training, running statistics in evaluation. The network's initial
weights are PyTorch's default initialisation after ``torch.manual_seed(seed)``, set explicitly
for every run (the only use of the global RNG, whose state the run sets; the augmentation
modules take ``seed=seed``). Augmentation runs in the training process, without gradients.

Augmentation cost: each condition's images per second on one batch (``--batch`` samples of its
source: gather + augment), ``common.measure``: ``--timing-warmup`` untimed, then
``--timing-repeats`` timed calls round-robin over the conditions, median and IQR; and the
seconds each run spent augmenting.

Usage::

    python benchmarks/bench_training.py           # 4 conditions x 3 seeds, 128 x 128 (~35 min)
    python benchmarks/bench_training.py --quick   # 32 x 32, 12 steps, seed 0, 1 thread (~10 s)

Results: ``benchmarks/results/training.json`` (``--out``; every run's losses, per-class IoU and
timings), the markdown table beside it (``training.md``) and on stdout, and a bar chart
(``training.png``: mIoU per condition, fisheye and catadioptric, each seed a dot); all written
atomically.
"""

from __future__ import annotations

import argparse
import io
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
# the checkout this script lives in, not whatever copy is installed
sys.path.insert(0, str(ROOT))

from common import (begin_run, loadavg, measure, positive_int, results_path,  # noqa: E402
                    run_record, write_json_atomic)
import omniscape_torch as ot  # noqa: E402
from omniscape_torch.cubemap import FACES  # noqa: E402
from omniscape_torch.data.generate import DatasetConfig, generate  # noqa: E402
from omniscape_torch.io import (CLASSES, IGNORE_INDEX, atomic_write_bytes,  # noqa: E402
                                 atomic_write_text)
from omniscape_torch.io.atomic import atomic_path  # noqa: E402
from omniscape_torch.render.augment import RandomOmniCamera  # noqa: E402

#: The conditions, in the order of the table, and how the table names them.
CONDITIONS = ("none", "kornia_fisheye", "reproject", "omni_camera")
LABELS = {"none": "(a) none", "kornia_fisheye": "(b) kornia RandomFisheye",
          "reproject": "(c) RandomReproject", "omni_camera": "(d) RandomOmniCamera"}
CAMERA_KINDS = ("fisheye", "catadioptric")
#: The perspective dataset: the cubes' horizontal faces.
HORIZONTAL = ("front", "back", "left", "right")
NUM_CLASSES = len(CLASSES)
#: kornia's RandomFisheye ranges (its docstring's example).
KORNIA_CENTER = (-0.3, 0.3)
KORNIA_GAMMA = (0.9, 1.0)
#: Training positions (metres): across the lanes, height above the ground, along the town;
#: time (s) of the moving objects.
TRAIN_X, TRAIN_HEIGHT, TRAIN_Z, TRAIN_T = (-3.5, 3.5), (0.8, 1.2), (-70.0, 70.0), (0.0, 30.0)
WEATHER = "clear_noon"
#: Offsets of the per-run generators: batch indices and kornia's per-call seeds.
DATA_SEED, KORNIA_SEED = 1000, 2000
#: Bumped when a cached cube's content changes meaning.
CACHE_VERSION = 1
#: Fraction of the steps averaged at each end of the loss curve (loss_start, loss_end).
LOSS_WINDOW = 0.25

# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


def train_positions(count: int, town_seed: int) -> list[tuple[list[float], float]]:
    """``count`` cube centres (world, metres) and times: cube ``i`` depends on ``town_seed``
    and ``i`` only (four draws per cube from one seeded generator), so more cubes extend
    fewer."""
    g = torch.Generator().manual_seed(town_seed)
    out = []
    for _ in range(count):
        u = torch.rand(4, generator=g, dtype=torch.float64).tolist()
        x = TRAIN_X[0] + (TRAIN_X[1] - TRAIN_X[0]) * u[0]
        h = TRAIN_HEIGHT[0] + (TRAIN_HEIGHT[1] - TRAIN_HEIGHT[0]) * u[1]
        z = TRAIN_Z[0] + (TRAIN_Z[1] - TRAIN_Z[0]) * u[2]
        t = TRAIN_T[0] + (TRAIN_T[1] - TRAIN_T[0]) * u[3]
        out.append(([x, -h, z], t))   # y is down: the camera is h above the ground
    return out


def training_cubes(cache: Path, town_seed: int, count: int, face: int,
                   log: Callable[[str], None] = print) -> dict[str, Tensor]:
    """The training cubemaps: ``rgb (N, 6, 3, F, F)`` float32 in [0, 1] (from ``uint8``),
    ``labels (N, 6, F, F)`` int64, rendered once into ``cache`` (one ``.pt`` per cube, written
    atomically) and read from there afterwards."""
    folder = cache / f"train_town{town_seed}_face{face}"
    town = None
    rgb, labels, rendered, start = [], [], 0, time.perf_counter()
    for i, (position, t) in enumerate(train_positions(count, town_seed)):
        meta = {"version": CACHE_VERSION, "town_seed": town_seed, "face_size": face,
                "position": position, "t": t, "weather": WEATHER}
        path = folder / f"cube_{i:04d}.pt"
        cube = None
        if path.is_file():
            try:
                cube = torch.load(path, weights_only=True)
            except Exception:  # a file of another torch or a foreign file: render again
                cube = None
            if cube is not None and cube.get("meta") != meta:
                cube = None
        if cube is None:
            if town is None:
                town = ot.scenes.Town(town_seed)
            with torch.no_grad():
                out = town.render_cubemap(torch.tensor(position), None, face, t=t,
                                          weather=WEATHER)
            cube = {"meta": meta,
                    "rgb": (out["rgb"][0].clamp(0, 1) * 255).round().to(torch.uint8),
                    "labels": out["labels"][0].to(torch.uint8)}
            buffer = io.BytesIO()
            torch.save(cube, buffer)
            atomic_write_bytes(path, buffer.getvalue())
            rendered += 1
        rgb.append(cube["rgb"])
        labels.append(cube["labels"])
    log(f"training cubemaps: {count} of town {town_seed}, 6 x {face}^2, {rendered} rendered "
        f"({time.perf_counter() - start:.1f} s), the others read from {folder}")
    return {"rgb": torch.stack(rgb).float() / 255, "labels": torch.stack(labels).long()}


def horizontal_faces(cubes: dict[str, Tensor]) -> dict[str, Tensor]:
    """The perspective dataset: the horizontal faces of every cube, cube-major,
    ``rgb (4N, 3, F, F)``, ``labels (4N, F, F)``."""
    index = [FACES.index(name) for name in HORIZONTAL]
    return {"rgb": cubes["rgb"][:, index].flatten(0, 1).contiguous(),
            "labels": cubes["labels"][:, index].flatten(0, 1).contiguous()}


def camera_kind(camera: str) -> str:
    for kind in CAMERA_KINDS:
        if camera.startswith(kind):
            return kind
    raise ValueError(f"camera: {camera!r} is neither a fisheye nor a catadioptric camera")


def evaluation_sets(cache: Path, seed: int, frames: int, size: int,
                    log: Callable[[str], None] = print) -> tuple[dict[str, dict[str, Tensor]],
                                                                 Path]:
    """The generator's dataset (written into ``cache`` once; ``generate`` resumes and writes
    atomically), per camera kind ``{"rgb": (n, 3, S, S) float, "labels": (n, S, S) int64}``
    with ``IGNORE_INDEX`` outside the valid area."""
    root = cache / f"eval_seed{seed}_size{size}_frames{frames}"
    start = time.perf_counter()
    done = generate(root, DatasetConfig(frames=frames, image_size=(size, size), seed=seed),
                    progress=False)
    dataset = ot.OmniDataset(root, modalities=("rgb", "labels", "valid"))
    parts: dict[str, dict[str, list[Tensor]]] = {k: {"rgb": [], "labels": []}
                                                 for k in CAMERA_KINDS}
    for item in dataset:
        part = parts[camera_kind(item["camera"])]
        part["rgb"].append(item["rgb"])
        part["labels"].append(torch.where(item["valid"], item["labels"], IGNORE_INDEX))
    log(f"evaluation set: {root} ({len(done['rendered'])} frames rendered, "
        f"{len(done['skipped'])} already there, {time.perf_counter() - start:.1f} s)")
    return {kind: {key: torch.stack(values) for key, values in part.items()}
            for kind, part in parts.items()}, root


# --------------------------------------------------------------------------------------------
# The network
# --------------------------------------------------------------------------------------------


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(True),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(True))


class TinyUNet(nn.Module):
    """A three-level U-Net (``width`` channels at full resolution; about 120k parameters at 16),
    notebook 02's network; the decoder upsamples to its skip's size, so any image size works.
    Weights: PyTorch's default initialisation (seed the global RNG before constructing)."""

    def __init__(self, classes: int, width: int = 16) -> None:
        super().__init__()
        w = width
        self.enc1, self.enc2, self.enc3 = _block(3, w), _block(w, 2 * w), _block(2 * w, 4 * w)
        self.dec2, self.dec1 = _block(6 * w, 2 * w), _block(3 * w, w)
        self.head = nn.Conv2d(w, classes, 1)

    def forward(self, x: Tensor) -> Tensor:
        e1 = self.enc1(x)
        e2 = self.enc2(F.max_pool2d(e1, 2))
        e3 = self.enc3(F.max_pool2d(e2, 2))
        d2 = self.dec2(torch.cat([F.interpolate(e3, size=e2.shape[-2:]), e2], 1))
        d1 = self.dec1(torch.cat([F.interpolate(d2, size=e1.shape[-2:]), e1], 1))
        return self.head(d1)


# --------------------------------------------------------------------------------------------
# The conditions
# --------------------------------------------------------------------------------------------


def _kornia_fisheye_class():
    """:class:`KorniaFisheye`, made on first use (kornia imports in a few seconds)."""
    import kornia.augmentation as K
    from kornia.geometry.grid import create_meshgrid
    from kornia.geometry.transform import remap

    class KorniaFisheye(K.RandomFisheye):
        """kornia's ``RandomFisheye`` with a mask path (kornia 0.9 raises
        ``NotImplementedError`` on a mask key, kornia issue 4420): the sampling field of
        ``RandomFisheye.apply_transform``, written out again, read with nearest neighbour;
        pixels whose sample leaves the source (zero padding in the image) get
        ``ignore_index``. The image path is kornia's, untouched."""

        def __init__(self, *args, ignore_index: int = IGNORE_INDEX, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self.ignore_index = ignore_index

        @staticmethod
        def field(input: Tensor, params: dict) -> tuple[Tensor, Tensor]:
            """RandomFisheye's field: output ``(x, y)`` in [-1, 1] samples the input at
            ``(x (1 + r^gamma), y (1 + r^gamma))``, ``r`` the distance to the drawn centre."""
            b, _, h, w = input.shape
            grid = create_meshgrid(h, w, normalized_coordinates=True, device=input.device,
                                   dtype=input.dtype)
            x, y = grid[..., 0], grid[..., 1]   # [1, H, W]
            cx, cy, gamma = (params[k].view(b, 1, 1).to(input) for k in
                             ("center_x", "center_y", "gamma"))
            distance = ((cx - x) ** 2 + (cy - y) ** 2) ** 0.5   # [B, H, W]
            scale = 1 + distance ** gamma
            return x * scale, y * scale

        def apply_transform_mask(self, input: Tensor, params: dict, flags: dict,
                                 transform: Tensor | None = None) -> Tensor:
            map_x, map_y = self.field(input, params)
            # labels + 1 so that zero padding (outside the source) is told apart from class 0
            out = remap(input + 1, map_x, map_y, mode="nearest", normalized_coordinates=True,
                        align_corners=True)
            return torch.where(out == 0, torch.full_like(out, self.ignore_index), out - 1)

        def apply_non_transform_mask(self, input: Tensor, params: dict, flags: dict,
                                     transform: Tensor | None = None) -> Tensor:
            return input

    return KorniaFisheye


@dataclass
class Condition:
    """One training condition: ``batch(indices)`` gathers samples of its source and augments
    them, returning ``rgb (B, 3, S, S)`` float and ``labels (B, S, S)`` int64."""

    name: str
    source: str          # "faces" or "cubes"
    size: int            # samples in the source
    batch: Callable[[Tensor], tuple[Tensor, Tensor]]
    settings: dict


def make_condition(name: str, faces: dict[str, Tensor], cubes: dict[str, Tensor], seed: int,
                   *, omni_mode: str = "fisheye") -> Condition:
    """A fresh condition (new modules and generators, seeded by ``seed``).

    Raises:
        ValueError: an unknown ``name``.
    """
    if name not in CONDITIONS:
        raise ValueError(f"name: expected one of {CONDITIONS}, got {name!r}")
    face = faces["rgb"].shape[-1]
    n_faces, n_cubes = faces["rgb"].shape[0], cubes["rgb"].shape[0]

    def gather(idx: Tensor) -> tuple[Tensor, Tensor]:
        return faces["rgb"][idx], faces["labels"][idx]

    if name == "none":
        return Condition(name, "faces", n_faces, gather, {"augmentation": None})

    if name == "kornia_fisheye":
        import kornia.augmentation as K
        module = _kornia_fisheye_class()(torch.tensor(KORNIA_CENTER), torch.tensor(KORNIA_CENTER),
                                         torch.tensor(KORNIA_GAMMA), p=1.0)
        sequence = K.AugmentationSequential(module, data_keys=["input", "mask"])
        seeds = torch.Generator().manual_seed(KORNIA_SEED + seed)

        def kornia_batch(idx: Tensor) -> tuple[Tensor, Tensor]:
            rgb, labels = gather(idx)
            call_seed = int(torch.randint(0, 2 ** 62, (), generator=seeds))
            with torch.random.fork_rng(devices=[]):   # kornia draws from the global RNG
                torch.manual_seed(call_seed)
                out, mask = sequence(rgb, labels[:, None])
            return out, mask[:, 0].long()

        return Condition(name, "faces", n_faces, kornia_batch, {
            "augmentation": "kornia.augmentation.RandomFisheye, AugmentationSequential("
                            "data_keys=['input', 'mask']), labels nearest (KorniaFisheye)",
            "center_x": list(KORNIA_CENTER), "center_y": list(KORNIA_CENTER),
            "gamma": list(KORNIA_GAMMA), "p": 1.0,
            "rng": f"torch.manual_seed(per-call seed from Generator({KORNIA_SEED} + seed)) "
                   "inside torch.random.fork_rng"})

    if name == "reproject":
        aug = ot.augment.RandomReproject(image_size=(face, face), source_fov=math.radians(90),
                                         seed=seed, fisheye_models=("equidistant",))
        f, c = face / 2, (face - 1) / 2   # the faces' own pinhole (DESIGN.md)
        intrinsics = torch.tensor([f, f, c, c])

        def reproject_batch(idx: Tensor) -> tuple[Tensor, Tensor]:
            rgb, labels = gather(idx)
            out = aug({"rgb": rgb, "labels": labels},
                      intrinsics=intrinsics.expand(len(idx), 4))
            return out["rgb"], out["labels"]

        return Condition(name, "faces", n_faces, reproject_batch, {
            "augmentation": "ot.augment.RandomReproject(image_size=(S, S), source_fov=90 deg, "
                            "seed=seed, fisheye_models=('equidistant',)), "
                            "intrinsics f = F / 2, c = (F - 1) / 2",
            "module": repr(aug)})

    aug = RandomOmniCamera((face, face), face, mode=omni_mode, seed=seed)

    def omni_batch(idx: Tensor) -> tuple[Tensor, Tensor]:
        out = aug({"rgb": cubes["rgb"][idx], "labels": cubes["labels"][idx]})
        return out["rgb"], out["labels"]

    return Condition(name, "cubes", n_cubes, omni_batch, {
        "augmentation": f"ot.augment.RandomOmniCamera((S, S), F, mode={omni_mode!r}, "
                        "seed=seed)", "module": repr(aug)})


# --------------------------------------------------------------------------------------------
# Training and evaluation
# --------------------------------------------------------------------------------------------


def confusion(pred: Tensor, truth: Tensor, classes: int = NUM_CLASSES) -> Tensor:
    """``(classes, classes)`` int64 counts, rows the truth, over pixels whose truth is not
    ``IGNORE_INDEX``."""
    keep = truth != IGNORE_INDEX
    if bool(((truth[keep] < 0) | (truth[keep] >= classes)).any()):
        raise ValueError(f"truth: labels outside 0..{classes - 1} and {IGNORE_INDEX}")
    index = truth[keep] * classes + pred[keep]
    return torch.bincount(index, minlength=classes ** 2).reshape(classes, classes)


def iou_scores(matrix: Tensor) -> dict:
    """Per-class IoU (None for a class absent from the truth) and their mean over the
    classes present."""
    matrix = matrix.double()
    tp = matrix.diag()
    truth, predicted = matrix.sum(1), matrix.sum(0)
    present = [c for c in range(matrix.shape[0]) if truth[c] > 0]
    iou = [float(tp[c] / (truth[c] + predicted[c] - tp[c])) if c in present else None
           for c in range(matrix.shape[0])]
    miou = statistics.fmean(iou[c] for c in present) if present else math.nan
    return {"miou": miou, "iou": iou, "classes_present": present,
            "pixels": int(matrix.sum())}


@torch.no_grad()
def evaluate(net: nn.Module, sets: dict[str, dict[str, Tensor]], chunk: int = 16) -> dict:
    net.eval()
    out = {}
    for kind, data in sets.items():
        total = torch.zeros(NUM_CLASSES, NUM_CLASSES, dtype=torch.long)
        for i in range(0, len(data["rgb"]), chunk):
            pred = net(data["rgb"][i:i + chunk]).argmax(1)
            total += confusion(pred, data["labels"][i:i + chunk])
        out[kind] = iou_scores(total)
    return out


def train_run(condition: Condition, sets: dict, args: argparse.Namespace, seed: int) -> dict:
    """Train a fresh network under ``condition`` and evaluate it; losses, scores, seconds."""
    data = torch.Generator().manual_seed(DATA_SEED + seed)
    torch.manual_seed(seed)   # the network's initial weights: PyTorch's default init
    net = TinyUNet(NUM_CLASSES, args.width)
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=args.steps)
    losses, augment_s, start = [], 0.0, time.perf_counter()
    net.train()
    for step in range(args.steps):
        idx = torch.randint(0, condition.size, (args.batch,), generator=data)
        t0 = time.perf_counter()
        with torch.no_grad():
            rgb, labels = condition.batch(idx)
        augment_s += time.perf_counter() - t0
        loss = F.cross_entropy(net(rgb), labels, ignore_index=IGNORE_INDEX)
        if not torch.isfinite(loss):
            raise RuntimeError(f"{condition.name}, seed {seed}: loss {float(loss)} at step "
                               f"{step} (a batch without a valid pixel?)")
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
    train_s = time.perf_counter() - start
    start = time.perf_counter()
    scores = evaluate(net, sets)
    window = max(1, int(LOSS_WINDOW * len(losses)))
    loss_start = statistics.fmean(losses[:window])
    loss_end = statistics.fmean(losses[-window:])
    return {"condition": condition.name, "seed": seed, "losses": losses,
            "loss_start": loss_start, "loss_end": loss_end,
            "loss_decreased": loss_end < loss_start, "train_s": train_s,
            "augment_s": augment_s, "eval_s": time.perf_counter() - start, "eval": scores}


def time_augmentations(conditions: dict[str, Condition], batch: int, repeats: int,
                       warmup: int) -> dict:
    """Images per second of each condition's ``batch`` (gather + augment) on one fixed set of
    indices, round-robin (``common.measure``)."""
    names = list(conditions)
    calls = [(lambda c=conditions[n]: c.batch(torch.arange(batch) % c.size)) for n in names]
    with torch.no_grad():
        results = measure(calls, repeats, warmup)
    return {n: {**r, "batch": batch, "images_per_s": batch / r["median_s"]}
            for n, r in zip(names, results)}


def summarise(runs: list[dict]) -> dict:
    """Per condition and camera kind: mIoU mean, sample std, min, max and per seed."""
    out: dict[str, dict] = {}
    for run in runs:
        for kind, scores in run["eval"].items():
            entry = out.setdefault(run["condition"], {}).setdefault(kind, {"per_seed": {}})
            entry["per_seed"][str(run["seed"])] = scores["miou"]
    for kinds in out.values():
        for entry in kinds.values():
            values = list(entry["per_seed"].values())
            entry.update(mean=statistics.fmean(values),
                         std=statistics.stdev(values) if len(values) > 1 else 0.0,
                         min=min(values), max=max(values))
    return out


def run(args: argparse.Namespace, log: Callable[[str], None] = print) -> dict:
    load_start = begin_run(args.threads)
    started = time.perf_counter()
    cache = Path(args.cache)
    cubes = training_cubes(cache, args.train_town, args.cubes, args.size, log)
    faces = horizontal_faces(cubes)
    sets, eval_root = evaluation_sets(cache, args.eval_seed, args.eval_frames, args.size, log)

    names = [n for n in CONDITIONS if n in args.conditions]

    def fresh(name: str, seed: int) -> Condition:
        return make_condition(name, faces, cubes, seed, omni_mode=args.omni_mode)

    timing = time_augmentations({n: fresh(n, 12345) for n in names}, args.batch,
                                args.timing_repeats, args.timing_warmup)
    runs, settings = [], {}
    with tqdm(total=len(names) * len(args.seeds), desc="training runs", unit="run",
              file=sys.stderr, disable=not args.progress) as bar:
        for name in names:
            for seed in args.seeds:
                bar.set_postfix_str(f"{name} seed {seed}")
                condition = fresh(name, seed)
                # the first seed's settings (a module's repr names its seed)
                settings.setdefault(name, {"source": condition.source,
                                           "samples": condition.size, **condition.settings})
                runs.append(train_run(condition, sets, args, seed))
                bar.update()

    net = TinyUNet(NUM_CLASSES, args.width)
    eval_info = {}
    for kind, data in sets.items():
        present = sorted(set((data["labels"][data["labels"] != IGNORE_INDEX]).unique().tolist()))
        eval_info[kind] = {"images": len(data["rgb"]), "classes_present": present,
                           "classes_absent": [CLASSES[c] for c in range(NUM_CLASSES)
                                              if c not in present],
                           "valid_fraction": float((data["labels"] != IGNORE_INDEX)
                                                   .double().mean())}
    return {
        **run_record("training", torch.device("cpu"), args.threads),
        "setup": {
            "quick": args.quick, "image_size": [args.size, args.size],
            "face_size": args.size, "steps": args.steps, "batch": args.batch,
            "optimizer": f"AdamW(lr={args.lr}, weight_decay=1e-4), cosine decay to 0",
            "loss": f"cross-entropy, ignore_index {IGNORE_INDEX}",
            "network": f"TinyUNet(width={args.width})",
            "parameters": sum(p.numel() for p in net.parameters()),
            "init": "PyTorch default init after torch.manual_seed(seed)",
            "batches": f"torch.Generator().manual_seed({DATA_SEED} + seed), with replacement",
            "train": {"town_seed": args.train_town, "cubes": args.cubes, "weather": WEATHER,
                      "faces_a_to_c": list(HORIZONTAL), "faces_count": len(faces["rgb"]),
                      "x_m": list(TRAIN_X), "height_m": list(TRAIN_HEIGHT),
                      "z_m": list(TRAIN_Z), "t_s": list(TRAIN_T), "rgb": "uint8 -> [0, 1]",
                      "cache": str(cache)},
            "eval": {"generator_seed": args.eval_seed, "frames": args.eval_frames,
                     "folder": str(eval_root), **eval_info},
            "miou": "mean IoU over the classes present in the camera kind's ground truth, "
                    "one confusion matrix over all its valid pixels",
            "omni_mode": args.omni_mode,
        },
        "seeds": list(args.seeds),
        "conditions": {n: {"label": LABELS[n], **settings[n]} for n in names},
        "augment_timing": timing,
        "runs": runs,
        "summary": summarise(runs),
        "timing_repeats": args.timing_repeats, "timing_warmup": args.timing_warmup,
        "timestamp_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "total_s": time.perf_counter() - started,
        "loadavg_start": load_start,
        "loadavg_end": loadavg(),
    }


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------


def markdown(result: dict) -> str:
    s = result["setup"]
    seeds = ", ".join(str(x) for x in result["seeds"])
    ev = s["eval"]
    lines = [
        f"training: {s['network']} ({s['parameters']:,} parameters), {s['steps']} steps of "
        f"batch {s['batch']}, {s['image_size'][0]} x {s['image_size'][1]}, {s['optimizer']}, "
        f"seeds {seeds}; train: {s['train']['cubes']} cubemaps of town "
        f"{s['train']['town_seed']} ({s['train']['faces_count']} horizontal faces for (a)-(c)); "
        f"eval: generate seed {ev['generator_seed']}, {ev['frames']} frames, "
        f"{ev['fisheye']['images']} fisheye + {ev['catadioptric']['images']} catadioptric "
        f"images; {result['threads']} thread{'s' if result['threads'] > 1 else ''}, commit "
        f"{result['commit'][:12]}"
        f"{' (dirty)' if result['dirty'] else ''}", "",
        "| condition | fisheye mIoU % | catadioptric mIoU % | augmentation images/s | "
        "train s / run | loss first -> last quarter |",
        "|---|---:|---:|---:|---:|---|"]

    def cell(entry: dict) -> str:
        return (f"{100 * entry['mean']:.1f} ± {100 * entry['std']:.1f} "
                f"[{100 * entry['min']:.1f}-{100 * entry['max']:.1f}]")

    for name, info in result["conditions"].items():
        summary = result["summary"][name]
        runs = [r for r in result["runs"] if r["condition"] == name]
        train_s = statistics.fmean(r["train_s"] for r in runs)
        first = statistics.fmean(r["loss_start"] for r in runs)
        last = statistics.fmean(r["loss_end"] for r in runs)
        lines.append(f"| {info['label']} | {cell(summary['fisheye'])} | "
                     f"{cell(summary['catadioptric'])} | "
                     f"{result['augment_timing'][name]['images_per_s']:.0f} | {train_s:.1f} | "
                     f"{first:.2f} -> {last:.2f} |")
    lines += ["", "mIoU: mean ± sample std [min-max] over the seeds; the mean IoU over the "
              "classes present in each camera kind's evaluation images (valid pixels only). "
              "Absent from the evaluation set, so left out: " + "; ".join(
                  f"{kind}: {', '.join(ev[kind]['classes_absent']) or 'none'}"
                  for kind in CAMERA_KINDS) + ".",
              f"augmentation images/s: one batch of {s['batch']} (gather + augment), median of "
              f"{result['timing_repeats']} calls; (a) is the gather alone."]
    return "\n".join(lines)


def chart(result: dict, path: Path) -> None:
    """Bars: mean mIoU per condition, fisheye and catadioptric groups; whiskers min-max over
    the seeds; each seed a dot. Written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["conditions"])
    fig, ax = plt.subplots(figsize=(7.5, 4), layout="constrained")
    width = 0.8 / max(len(names), 1)
    colours = plt.get_cmap("tab10")
    for i, name in enumerate(names):
        xs, means, low, high = [], [], [], []
        for k, kind in enumerate(CAMERA_KINDS):
            entry = result["summary"][name][kind]
            x = k + (i - (len(names) - 1) / 2) * width
            xs.append(x)
            means.append(100 * entry["mean"])
            low.append(100 * (entry["mean"] - entry["min"]))
            high.append(100 * (entry["max"] - entry["mean"]))
            seeds = [100 * v for v in entry["per_seed"].values()]
            ax.scatter([x] * len(seeds), seeds, color="black", s=10, zorder=3)
        ax.bar(xs, means, width * 0.9, yerr=[low, high], capsize=3, color=colours(i),
               label=result["conditions"][name]["label"])
    ax.set_xticks(range(len(CAMERA_KINDS)), [f"{k} (generated)" for k in CAMERA_KINDS])
    ax.set_ylabel("mIoU % over the valid area")
    s = result["setup"]
    ax.set_title(f"Segmentation trained on the town with each augmentation, tested on the "
                 f"generator's omni images\n"
                 f"{s['steps']} steps x batch {s['batch']}, {s['image_size'][0]} px, "
                 f"{len(result['seeds'])} seed(s): bar mean, whiskers min-max, dots seeds",
                 fontsize=9)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def write_outputs(result: dict, out: Path) -> dict[str, Path]:
    """``out`` (JSON), and beside it the table (``.md``) and the chart (``.png``), each
    atomically."""
    paths = {"json": out, "md": out.with_suffix(".md"), "png": out.with_suffix(".png")}
    write_json_atomic(result, paths["json"])
    atomic_write_text(paths["md"], markdown(result) + "\n")
    chart(result, paths["png"])
    return paths


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------

#: (full run, --quick) defaults of the flags left unset.
DEFAULTS = {"size": (128, 32), "cubes": (48, 4), "steps": (400, 12), "batch": (8, 4),
            "eval_frames": (24, 1), "seeds": ([0, 1, 2], [0]), "timing_repeats": (10, 2),
            "timing_warmup": (2, 1), "threads": (2, 1)}


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 32 x 32, 4 cubes, 12 steps of 4, 1 eval frame, seed 0, "
                             "1 thread")
    parser.add_argument("--size", type=positive_int, default=None,
                        help="face, augmented and evaluation image side (128; 32 quick)")
    parser.add_argument("--cubes", type=positive_int, default=None,
                        help="training cubemaps (48; 4 quick)")
    parser.add_argument("--steps", type=positive_int, default=None,
                        help="training steps per run (400; 12 quick)")
    parser.add_argument("--batch", type=positive_int, default=None,
                        help="samples per step (8; 4 quick)")
    parser.add_argument("--eval-frames", type=positive_int, default=None,
                        help="frames of the evaluation dataset, 4 cameras each (24; 1 quick)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None,
                        help="seeds, one run per condition each (0 1 2; 0 quick)")
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS),
                        help="conditions to run (default all)")
    parser.add_argument("--omni-mode", choices=("fisheye", "mixed", "catadioptric"),
                        default="fisheye", help="RandomOmniCamera's mode in (d) (fisheye)")
    parser.add_argument("--train-town", type=int, default=0,
                        help="seed of the training town (default 0)")
    parser.add_argument("--eval-seed", type=int, default=1,
                        help="seed of the evaluation dataset: its town and ride (default 1)")
    parser.add_argument("--width", type=positive_int, default=16,
                        help="U-Net channels at full resolution (default 16: ~120k parameters)")
    parser.add_argument("--lr", type=float, default=3e-3, help="peak learning rate (3e-3)")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch threads (2; 1 quick: a smoke run must not need a second "
                             "idle core)")
    parser.add_argument("--timing-repeats", type=positive_int, default=None,
                        help="timed augmentation calls per condition (10; 2 quick)")
    parser.add_argument("--timing-warmup", type=int, default=None,
                        help="untimed augmentation calls first (2; 1 quick)")
    parser.add_argument("--cache", type=Path, default=ROOT / "out" / "bench_training",
                        help="folder of the cached cubemaps and evaluation dataset "
                             "(default out/bench_training)")
    parser.add_argument("--out", type=Path,
                        default=None,
                        help="JSON output; the .md table and .png chart go beside it "
                             "(default benchmarks/results/training.json)")
    parser.add_argument("--no-progress", dest="progress", action="store_false",
                        help="no progress bar")
    return parser


def resolve(args: argparse.Namespace) -> argparse.Namespace:
    """Fill the defaults that depend on ``--quick`` and check the flags together.

    Raises:
        ValueError: naming the flag.
    """
    for name, (full, quick) in DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    if args.size < 8:
        raise ValueError(f"--size: expected at least 8 pixels (the generator's smallest "
                         f"image), got {args.size}")
    if args.timing_warmup < 0:
        raise ValueError(f"--timing-warmup: expected >= 0, got {args.timing_warmup}")
    if not (math.isfinite(args.lr) and args.lr > 0):
        raise ValueError(f"--lr: expected a positive number, got {args.lr}")
    if len(set(args.seeds)) != len(args.seeds) or min(args.seeds) < 0:
        raise ValueError(f"--seeds: expected distinct seeds >= 0, got {args.seeds}")
    if args.train_town < 0 or args.eval_seed < 0:
        raise ValueError("--train-town, --eval-seed: expected seeds >= 0")
    if args.train_town == args.eval_seed:
        raise ValueError(f"--train-town and --eval-seed: both {args.eval_seed}; the evaluation "
                         "town must be one the networks never saw")
    if len(set(args.conditions)) != len(args.conditions):
        raise ValueError(f"--conditions: duplicates in {args.conditions}")
    return args


def main(argv: list[str] | None = None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("training.json", quick=args.quick)
    try:
        args = resolve(args)
    except ValueError as err:
        parser.error(str(err))
    result = run(args)
    paths = write_outputs(result, args.out)
    print(markdown(result))
    print("\nwrote " + ", ".join(str(p) for p in paths.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
