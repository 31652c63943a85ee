"""Proof that it helps: segmentation trained with six conditions, tested on ray-traced omni images.

Issue 36, item 5 (issue 17, item 7, redesigned). A U-Net (:class:`UNet`, four levels of
``--width`` 16 channels at full resolution: 488,909 parameters, 4.1x the 119,117 of the
three-level ``TinyUNet`` this benchmark used before) is trained on ``--threads`` CPU threads
(default 2) under each condition, for ``--seeds`` seeds (default 0, 1, 2), until its loss is
flat (the stopping rule below), and evaluated on fisheye and catadioptric images traced ray by
ray in a town and weather it never saw. Conditions (``CONDITIONS``):

* ``none`` (a): the perspective views as they are;
* ``kornia_fisheye`` (b): kornia's ``RandomFisheye`` (p = 1) at the ranges that scored best on
  the validation split among ``KORNIA_GRID`` (centre ranges x gamma ranges: the search runs in
  the benchmark, one training of seed 0 per setting, capped at ``--search-max-steps``; every
  setting's score is in the JSON), on the image and the labels with
  ``AugmentationSequential(data_keys=["input", "mask"])``. kornia 0.9 raises
  ``NotImplementedError`` for ``RandomFisheye`` on a mask key (kornia issue 4420), so
  :class:`KorniaFisheye` adds the mask path: the same sampling field as kornia's image path,
  read with nearest neighbour, and ``IGNORE_INDEX`` (255) where the field leaves the source
  (where the image gets kornia's zero padding). kornia draws from torch's global RNG: every
  call runs inside ``torch.random.fork_rng`` after ``torch.manual_seed`` of a seed drawn from
  the run's own generator, so its draws are reproducible and the global state is left as it was;
* ``albumentations`` (c): ``A.Compose([A.Resize(S, S), A.OpticalDistortion(mode="fisheye",
  p=1, fill_mask=255)], seed=seed)`` per sample on ``uint8`` HWC arrays, image and mask (its
  other settings at their defaults: distort limit +-0.05, linear image, nearest mask, zero
  border; ``fill_mask=255`` so that the border is ignored, not labelled ``Unlabeled``).
  albumentations is optional (installed ``--no-deps``, see ``bench_reproject.py``): where it
  cannot be imported the row is skipped and the JSON says why (``skipped``);
* ``reproject`` (d): ``ot.augment.RandomReproject(image_size=(S, S), source_fov=90 deg,
  seed=seed)`` at its defaults (equidistant, fov 160-200 deg, roll +-25, pitch and yaw
  +-10 deg, antialiasing on, framing ``coverage_range`` (0.5, 0.9)), given the faces' own
  intrinsics (DESIGN.md: ``f = F / 2``, ``c = (F - 1) / 2``);
* ``omni_camera`` (e): ``ot.augment.RandomOmniCamera((S, S), F, mode="fisheye", seed=seed)``
  (its defaults) on whole cubemaps (``--omni-mode mixed`` adds catadioptric cameras);
* ``fisheye_upper`` (f), the upper bound: no augmentation, trained on omni images of the
  training town rendered as the test images are (below), the same number of images as (a)-(d)
  have faces: per training cube position two views (yaws drawn), each a fisheye and a
  catadioptric image.

Training data: ``--cubes`` cubemaps (default 96) of the built-in town ``--train-town``
(default 0, layout 1, main street, ``Town.render_cubemap``, clear noon), rendered once and
cached, one ``.pt`` file per cube written atomically (``--cache``, default
``out/bench_training`` in the repository, which git ignores; a file is rendered again when it is
missing or holds other settings). Cube ``i`` stands on the road at a position drawn from
``torch.Generator().manual_seed(train_town)``: across the driving lanes (``|x| < 3.5`` m),
0.8-1.2 m above the ground, anywhere along the town (``|z| < 70`` m), at a time of 0-30 s for
the moving objects; the cube axes are the world axes. RGB is stored as ``uint8`` and used as
float in [0, 1]. Conditions (a)-(d) train on the four horizontal faces of every cube (90-degree
pinhole views, ``S x S``, upright, as a perspective dataset gives them), (e) on the whole
cubemaps.

Traced images (:func:`traced_set`), the test set, the validation split and the upper bound's
training set: every pixel's own ray through the camera model (``Camera.unproject`` of the
pixel centre and of ``--trace-aa`` x ``--trace-aa`` sub-pixel points, default 2 x 2), traced by
``Town.render_rays``, never through a layer under test: RGB the mean of the sub-pixel rays
(those inside the camera's field), labels the centre ray's, ``IGNORE_INDEX`` outside the
camera's valid area. Cameras: the generator's (``presets.fisheye``: equidistant, 190 deg,
looking forward; ``presets.catadioptric(looking="down")``: unified, xi 0.9, 220 deg), turned
by a yaw drawn in [-180, 180) deg about the vertical, at positions drawn as the cubes' are.

* test: ``--test-frames`` positions (default 48; a fisheye and a catadioptric image each) in
  the town ``--test-town`` (default seed 1) of layout ``--test-layout`` (default 2, the
  crossroads), in the weathers ``--test-weathers`` (in turn; default ``TEST_WEATHERS``:
  cloudy, wet, and wet cloudy noon, none of which the networks saw, of clear noon's light:
  see ``TEST_WEATHERS`` for why not the sunsets);
* validation (the kornia search only): ``--val-frames`` positions (default 16) of the
  training town after the cubes' (``train_positions`` extends), clear noon;
* upper bound: the cubes' positions, clear noon.

Scores: IoU per class from one confusion matrix over every valid pixel of the camera kind
(labels 0..12; 255 is not counted); the mIoU is the mean over the classes present in that kind's
ground truth (an absent class has no IoU and is left out; the JSON lists them). The markdown
gives the per-class IoU of every condition and calls out the small classes
(``SMALL_CLASSES``: pole, traffic sign, pedestrian).

Training, the same for every condition: batches of ``--batch`` (default 8) samples drawn with
replacement by ``torch.Generator().manual_seed(1000 + seed)``, cross-entropy ignoring 255,
AdamW (weight decay 1e-4) at ``--lr`` (1e-3) after a linear warm-up of ``WARMUP_STEPS``,
batch statistics in training, running statistics in evaluation. The network's initial weights
are PyTorch's default initialisation after ``torch.manual_seed(seed)`` (the only use of the
global RNG outside kornia's fork). Stopping rule (:func:`flat`): the run trains in chunks of
``--chunk`` steps (default 100); after each chunk, once it has run ``--min-steps`` (400), it
stops when the mean loss of the last quarter of its steps is within ``--flat-tol`` (2%) of the
previous quarter's (``(previous - last) / previous <= tol``: flat, or rising), or at
``--max-steps`` (1000; a kornia search run at ``--search-max-steps``, 500). Each run records
its steps, why it stopped (``flat`` or ``cap``) and the two quarters' means.

Augmentation cost: each condition's images per second on one batch (gather + augment,
``common.measure`` round-robin, median), and the seconds each run spent augmenting.

Cost: ``--estimate`` times ``--estimate-steps`` training steps of every condition at the full
settings (on random data of the full shapes) and the tracing of one image and one cube, and
prints the projected cost of the whole table (every run at ``--min-steps``, every run at the
cap), without running it. Measured at commit bee583f on this project's shared 2-core VM
(not yet the full run): with 2 threads at load 1.2-2.1, 0.43-0.52 s a step for 5 of the 6
conditions (the sixth, timed first, 3.2 s: the process's warm-up, untimed since), so the 18
runs and 6 search runs at the cap (21,000 steps) plus data (1.6 min) and evaluation (2.8 min)
project to about 2.8 h, and 1.3 h if every run were flat at 400 steps; with 1 thread at load
about 2, 0.52-0.79 s a step: 4.05 h at the cap, 1.86 h at 400 steps. Two threads on a busy
machine collapse (load 1.7-3.2: 2.1-3.5 s a step, 19 h projected): run the table on idle
cores, or with ``--threads 1`` where others share them. One full-size run (``--conditions
reproject --seeds 0 --threads 1 --max-steps 800``, load 1.2-4) was not flat at 800 steps
(the last quarter's mean loss 0.176, 19.7 % under the previous quarter's 0.219; 799 s), so
at these defaults most runs may stop at the cap (the table says which). The committed table
(commit d96cef1) took 7,670 s (2.1 h) in two one-thread processes sharing the runs, on the
2-core VM with other work beside it for part of the time (0.54-1.04 s a step, medians per
run); 15 of its 18 runs stopped at the cap, their loss 7-30 % lower in the last quarter of
their steps than in the one before.

Every finished run (and search run) is saved in ``<cache>/runs/`` under its settings
(:func:`cached_run`), so an interrupted table resumes where it stopped, and one command started
in two processes shares the runs between them (each claims a run before it trains it; the
table is written by each once every run is saved): on 2 cores, two one-thread processes
(``--threads 1``) use them better than one two-thread process.

Usage::

    python benchmarks/bench_training.py             # the full table (~2.8 h at the cap, above)
    python benchmarks/bench_training.py --threads 1 & python benchmarks/bench_training.py --threads 1
    python benchmarks/bench_training.py --estimate  # its projected cost on this machine
    python benchmarks/bench_training.py --quick     # 32 x 32, 8-12 steps, seed 0 (~15 s)

Results: ``benchmarks/results/training.json`` (``--out``; every run's losses, stopping, per-class
IoU and timings; the kornia search), the markdown tables beside it (``training.md``) and on
stdout, and a bar chart (``training.png``: mIoU per condition, fisheye and catadioptric, each
seed a dot); all written atomically. ``--quick`` writes under ``benchmarks/results/quick/``.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
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
from omniscape_torch.cameras.presets import catadioptric, fisheye  # noqa: E402
from omniscape_torch.cubemap import FACES  # noqa: E402
from omniscape_torch.io import (CLASSES, IGNORE_INDEX, atomic_write_bytes,  # noqa: E402
                                 atomic_write_text)
from omniscape_torch.io.atomic import atomic_path  # noqa: E402
from omniscape_torch.augment import RandomOmniCamera  # noqa: E402

#: The conditions, in the order of the table, and how the table names them.
CONDITIONS = ("none", "kornia_fisheye", "albumentations", "reproject", "omni_camera",
              "fisheye_upper")
LABELS = {"none": "(a) none", "kornia_fisheye": "(b) kornia RandomFisheye (searched)",
          "albumentations": "(c) albumentations fisheye",
          "reproject": "(d) RandomReproject", "omni_camera": "(e) RandomOmniCamera",
          "fisheye_upper": "(f) upper bound: traced omni images"}
CAMERA_KINDS = ("fisheye", "catadioptric")
#: The perspective dataset: the cubes' horizontal faces.
HORIZONTAL = ("front", "back", "left", "right")
NUM_CLASSES = len(CLASSES)
#: The small classes the markdown calls out.
SMALL_CLASSES = ("Pole", "TrafficSign", "Pedestrian")
#: kornia's RandomFisheye ranges searched on the validation split: centre (x and y alike) x
#: gamma. The first setting is its docstring's example, the design before the search.
KORNIA_GRID = tuple({"center": c, "gamma": g} for c in ((-0.3, 0.3), (-0.1, 0.1))
                    for g in ((0.9, 1.0), (0.5, 0.7), (1.5, 2.0)))
#: Training positions (metres): across the lanes, height above the ground, along the town;
#: time (s) of the moving objects.
TRAIN_X, TRAIN_HEIGHT, TRAIN_Z, TRAIN_T = (-3.5, 3.5), (0.8, 1.2), (-70.0, 70.0), (0.0, 30.0)
WEATHER = "clear_noon"
#: The test set's weathers (in turn, ``--test-weathers``), none of them the training's, and of
#: its light: no condition augments colour, so a darker test (the sunsets: a fisheye image's
#: mean RGB 0.15-0.17 against clear noon's 0.32, town 1) would test photometric robustness,
#: not the lens (one full-size reproject network, seed 0, 400 steps, scored 31.7 % fisheye and
#: 15.3 % catadioptric mIoU on these, 20.7 % and 8.7 % on wet_cloudy_noon, clear_sunset and
#: soft_rain_sunset in turn: the same positions). Their means: 0.33, 0.30, 0.31.
TEST_WEATHERS = ("cloudy_noon", "wet_noon", "wet_cloudy_noon")
#: The training town's layout (main street); the test town's is --test-layout.
TRAIN_LAYOUT = 1
#: Offsets of the per-run generators: batch indices, kornia's per-call seeds; of the yaws.
DATA_SEED, KORNIA_SEED, YAW_SEED = 1000, 2000, 3000
#: Linear learning-rate warm-up (steps), then constant.
WARMUP_STEPS = 50
#: Bumped when a cached file's content changes meaning.
CACHE_VERSION = 2

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


def _cached(path: Path, meta: dict, make: Callable[[], dict[str, Tensor]]) -> tuple[dict, bool]:
    """The tensors saved at ``path`` if its ``meta`` is ``meta``, else ``make()``'s, saved
    there atomically; and whether they were made."""
    if path.is_file():
        try:
            saved = torch.load(path, weights_only=True)
        except Exception:  # a file of another torch or a foreign file: make it again
            saved = None
        if saved is not None and saved.get("meta") == meta:
            return saved, False
    saved = {"meta": meta, **make()}
    buffer = io.BytesIO()
    torch.save(saved, buffer)
    atomic_write_bytes(path, buffer.getvalue())
    return saved, True


def _to_uint8(rgb: Tensor) -> Tensor:
    return (rgb.clamp(0, 1) * 255).round().to(torch.uint8)


#: The flags a run's record depends on (with ``RUN_VERSION``, a finished run's cache key).
RUN_FLAGS = ("size", "cubes", "batch", "width", "levels", "lr", "warmup", "chunk", "min_steps",
             "flat_tol", "train_town", "test_town", "test_layout", "test_weathers",
             "test_frames", "val_frames", "trace_aa", "omni_mode")
#: Bumped when a run's record changes meaning.
RUN_VERSION = 1


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def cached_run(cache: Path, key: str, meta: dict, train: Callable[[], dict],
               log: Callable[[str], None] = print, *, wait: bool = True,
               poll_s: float = 10.0) -> dict | None:
    """A finished run's record from ``cache/runs/<key>.json`` if its ``meta`` is ``meta``,
    else ``train()``'s, saved there atomically.

    Several processes may share one cache (``--cache``): the one that first creates
    ``<key>.claim`` (``O_EXCL``, holding its pid) trains the run; for another the run is
    None (``wait=False``: it goes on to other runs) or, with ``wait``, the record once the
    claiming process has saved it (polled every ``poll_s`` seconds). A dead process's claim
    is taken over. So the table's runs can be spread over processes started with the same
    command (:func:`cached_runs`), and an interrupted table resumes where it stopped."""
    meta = json.loads(json.dumps(meta))   # as it reads back: tuples are lists
    folder = Path(cache) / "runs"
    folder.mkdir(parents=True, exist_ok=True)
    path, claim = folder / f"{key}.json", folder / f"{key}.claim"
    waiting = False
    while True:
        if path.is_file():
            try:
                saved = json.loads(path.read_text())
            except ValueError:   # not ours: train again
                saved = None
            if saved is not None and saved.get("meta") == meta:
                return saved["run"]
        try:
            fd = os.open(claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                pid = int(claim.read_text() or 0)
            except (OSError, ValueError):
                pid = 0
            if pid and pid != os.getpid() and _pid_alive(pid):
                if not wait:
                    return None
                if not waiting:
                    log(f"{key}: trained by process {pid}, waiting for its record")
                    waiting = True
                time.sleep(poll_s)
                continue
            claim.unlink(missing_ok=True)   # a dead process's claim
            continue
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        try:
            record = train()
            write_json_atomic({"meta": meta, "run": record}, path)
        finally:
            claim.unlink(missing_ok=True)
        return record


def cached_runs(cache: Path, jobs: list[tuple[str, dict, Callable[[], dict]]],
                log: Callable[[str], None] = print, done: Callable[[], None] = lambda: None,
                poll_s: float = 10.0) -> list[dict]:
    """:func:`cached_run` of every ``(key, meta, train)`` job, in order: first those no other
    process is training, then the others' once they are saved; ``done()`` after each."""
    records: list[dict | None] = []
    for key, meta, train in jobs:
        records.append(cached_run(cache, key, meta, train, log, wait=False))
        if records[-1] is not None:
            done()
    for i, (key, meta, train) in enumerate(jobs):
        if records[i] is None:
            records[i] = cached_run(cache, key, meta, train, log, poll_s=poll_s)
            done()
    return records


def training_cubes(cache: Path, town_seed: int, count: int, face: int,
                   log: Callable[[str], None] = print) -> dict[str, Tensor]:
    """The training cubemaps: ``rgb (N, 6, 3, F, F)`` float32 in [0, 1] (from ``uint8``),
    ``labels (N, 6, F, F)`` int64, rendered once into ``cache`` (one ``.pt`` per cube, written
    atomically) and read from there afterwards."""
    folder = cache / f"train_town{town_seed}_face{face}"
    town = None
    rgb, labels, rendered, start = [], [], 0, time.perf_counter()
    for i, (position, t) in enumerate(train_positions(count, town_seed)):
        def render() -> dict[str, Tensor]:
            nonlocal town
            town = town or ot.scenes.Town(town_seed, layout=TRAIN_LAYOUT)
            with torch.no_grad():
                out = town.render_cubemap(torch.tensor(position), None, face, t=t,
                                          weather=WEATHER)
            return {"rgb": _to_uint8(out["rgb"][0]), "labels": out["labels"][0].to(torch.uint8)}

        meta = {"version": CACHE_VERSION, "town_seed": town_seed, "layout": TRAIN_LAYOUT,
                "face_size": face, "position": position, "t": t, "weather": WEATHER}
        cube, made = _cached(folder / f"cube_{i:04d}.pt", meta, render)
        rendered += made
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


def test_camera(kind: str, size: int) -> tuple[ot.Camera, Tensor]:
    """The generator's camera of ``kind`` at ``size x size`` and its attitude (camera ->
    rig: the fisheye looks forward, the catadioptric camera down)."""
    if kind == "fisheye":
        return fisheye((size, size)), torch.eye(3)
    if kind == "catadioptric":
        return catadioptric((size, size), looking="down")
    raise ValueError(f"kind: expected one of {CAMERA_KINDS}, got {kind!r}")


def yaw_matrix(yaw: float) -> Tensor:
    """Rotation by ``yaw`` about the world's vertical (y, down): rig -> world."""
    c, s = math.cos(yaw), math.sin(yaw)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def trace_image(town: ot.scenes.Town, camera: ot.Camera, rotation: Tensor, position: list,
                t: float, weather: str, samples: int) -> tuple[Tensor, Tensor]:
    """The image of ``camera`` (camera -> world ``rotation``) at ``position``: every pixel's
    own rays traced by ``Town.render_rays``; RGB ``(3, H, W)`` ``uint8``, the mean of
    ``samples x samples`` sub-pixel rays (those inside the camera's field); labels ``(H, W)``
    ``uint8``, the centre ray's, ``IGNORE_INDEX`` outside the camera's valid area."""
    centre = camera.pixel_grid()
    origin = torch.tensor(position, dtype=torch.float32)
    rays, valid = camera.unproject(centre)
    labels = town.render_rays(origin, rays.float() @ rotation.T, t=t, weather=weather)["labels"]
    total = torch.zeros(*centre.shape[:2], 3)
    count = torch.zeros(centre.shape[:2])
    offsets = (torch.arange(samples, dtype=centre.dtype) + 0.5) / samples - 0.5
    for dv in offsets:
        for du in offsets:
            sub, ok = camera.unproject(centre + torch.stack((du, dv)))
            sub = torch.where(ok[..., None], sub, rays)   # outside the field: not counted
            rgb = town.render_rays(origin, sub.float() @ rotation.T, t=t, weather=weather)["rgb"]
            total += torch.where(ok[..., None], rgb, 0.0)
            count += ok
    rgb = torch.where(valid[..., None], total / count.clamp(min=1)[..., None], 0.0)
    return (_to_uint8(rgb.permute(2, 0, 1)),
            torch.where(valid, labels, IGNORE_INDEX).to(torch.uint8))


def traced_set(cache: Path, name: str, town_seed: int, layout: int,
               positions: list[tuple[list[float], float]], weathers: tuple[str, ...],
               views: int, size: int, samples: int, log: Callable[[str], None] = print
               ) -> dict[str, dict[str, Tensor]]:
    """Per camera kind ``{"rgb": (n, 3, S, S) float, "labels": (n, S, S) int64}``, the set
    ``name`` (``test``, ``val``, ``upper``) of ``town_seed``: at every position ``views`` yaws
    in [-pi, pi) (drawn from a generator seeded by ``YAW_SEED``, ``town_seed`` and ``name``),
    each seen by a fisheye and a catadioptric camera (:func:`trace_image`), position ``i`` in
    ``weathers[i % len(weathers)]``; cached in ``cache`` (one ``.pt`` a set and size)."""
    g = torch.Generator().manual_seed(YAW_SEED + 100 * town_seed + sum(map(ord, name)))
    yaws = (torch.rand(len(positions) * views, generator=g, dtype=torch.float64) * 2 - 1) \
        * math.pi
    meta = {"version": CACHE_VERSION, "name": name, "town_seed": town_seed, "layout": layout,
            "positions": positions, "weathers": list(weathers), "views": views, "size": size,
            "samples": samples, "yaws": yaws.tolist()}
    start = time.perf_counter()

    def render() -> dict[str, Tensor]:
        town = ot.scenes.Town(town_seed, layout=layout)
        out: dict[str, list[Tensor]] = {f"{k}_{m}": [] for k in CAMERA_KINDS
                                        for m in ("rgb", "labels")}
        for kind in CAMERA_KINDS:
            camera, attitude = test_camera(kind, size)
            for j, yaw in enumerate(yaws.tolist()):
                position, t = positions[j // views]
                rgb, labels = trace_image(town, camera, yaw_matrix(yaw) @ attitude, position, t,
                                          weathers[(j // views) % len(weathers)], samples)
                out[f"{kind}_rgb"].append(rgb)
                out[f"{kind}_labels"].append(labels)
        return {k: torch.stack(v) for k, v in out.items()}

    saved, made = _cached(cache / f"{name}_town{town_seed}_size{size}.pt", meta, render)
    log(f"{name}: {len(yaws)} fisheye + {len(yaws)} catadioptric images of town {town_seed} "
        f"(layout {layout}), {'traced' if made else 'read'} in "
        f"{time.perf_counter() - start:.1f} s")
    return {kind: {"rgb": saved[f"{kind}_rgb"].float() / 255,
                   "labels": saved[f"{kind}_labels"].long()} for kind in CAMERA_KINDS}


def merged(sets: dict[str, dict[str, Tensor]]) -> dict[str, Tensor]:
    """The camera kinds of a traced set as one training set, interleaved (fisheye 0,
    catadioptric 0, fisheye 1, ...)."""
    return {key: torch.stack([sets[k][key] for k in CAMERA_KINDS], 1).flatten(0, 1)
            for key in ("rgb", "labels")}


# --------------------------------------------------------------------------------------------
# The network
# --------------------------------------------------------------------------------------------


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(True),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.BatchNorm2d(cout), nn.ReLU(True))


class UNet(nn.Module):
    """A U-Net of ``levels`` levels, ``width * 2**i`` channels at level ``i`` (488,909
    parameters at width 16 and 4 levels; 119,117 at 3 levels, notebook 02's ``TinyUNet``); the
    decoder upsamples (nearest) to its skip's size, so any image size works. Weights:
    PyTorch's default initialisation (seed the global RNG before constructing)."""

    def __init__(self, classes: int, width: int = 16, levels: int = 4) -> None:
        super().__init__()
        ch = [width * 2 ** i for i in range(levels)]
        self.encoders = nn.ModuleList(_block(3 if i == 0 else ch[i - 1], ch[i])
                                      for i in range(levels))
        self.decoders = nn.ModuleList(_block(ch[i] + ch[i + 1], ch[i])
                                      for i in range(levels - 1))
        self.head = nn.Conv2d(width, classes, 1)

    def forward(self, x: Tensor) -> Tensor:
        skips = []
        for i, encoder in enumerate(self.encoders):
            x = encoder(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        x = skips.pop()
        for decoder in reversed(self.decoders):
            skip = skips.pop()
            x = decoder(torch.cat([F.interpolate(x, size=skip.shape[-2:]), skip], 1))
        return self.head(x)


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
    source: str          # "faces", "cubes" or "traced"
    size: int            # samples in the source
    batch: Callable[[Tensor], tuple[Tensor, Tensor]]
    settings: dict


def albumentations_or_reason():
    """``albumentations``, or why it cannot be imported (a string)."""
    try:
        import albumentations
    except Exception as err:  # not installed, or its requirements missing (--no-deps)
        return (f"albumentations cannot be imported ({type(err).__name__}: {err}); it is not "
                "a dependency: see bench_reproject.py's docstring for the command")
    return albumentations


def make_condition(name: str, faces: dict[str, Tensor], cubes: dict[str, Tensor], seed: int,
                   *, omni_mode: str = "fisheye", kornia: dict | None = None,
                   traced: dict[str, Tensor] | None = None) -> Condition:
    """A fresh condition (new modules and generators, seeded by ``seed``). ``kornia``: the
    ``{"center", "gamma"}`` ranges of (b) (default ``KORNIA_GRID[0]``); ``traced``: the upper
    bound's training images (``merged(traced_set(...))``).

    Raises:
        ValueError: an unknown ``name``, or ``fisheye_upper`` without ``traced``.
        ImportError: ``albumentations`` where it cannot be imported.
    """
    if name not in CONDITIONS:
        raise ValueError(f"name: expected one of {CONDITIONS}, got {name!r}")
    face = faces["rgb"].shape[-1]
    n_faces, n_cubes = faces["rgb"].shape[0], cubes["rgb"].shape[0]

    def gather(idx: Tensor) -> tuple[Tensor, Tensor]:
        return faces["rgb"][idx], faces["labels"][idx]

    if name == "none":
        return Condition(name, "faces", n_faces, gather, {"augmentation": None})

    if name == "fisheye_upper":
        if traced is None:
            raise ValueError("traced: the upper bound needs its traced training images")
        return Condition(name, "traced", len(traced["rgb"]),
                         lambda idx: (traced["rgb"][idx], traced["labels"][idx]),
                         {"augmentation": None, "images": "traced fisheye and catadioptric "
                          "images of the training town (traced_set 'upper')"})

    if name == "kornia_fisheye":
        import kornia.augmentation as K
        ranges = kornia or KORNIA_GRID[0]
        center, gamma = torch.tensor(ranges["center"]), torch.tensor(ranges["gamma"])
        module = _kornia_fisheye_class()(center, center, gamma, p=1.0)
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
            "center_x": list(ranges["center"]), "center_y": list(ranges["center"]),
            "gamma": list(ranges["gamma"]), "p": 1.0,
            "rng": f"torch.manual_seed(per-call seed from Generator({KORNIA_SEED} + seed)) "
                   "inside torch.random.fork_rng"})

    if name == "albumentations":
        A = albumentations_or_reason()
        if isinstance(A, str):
            raise ImportError(A)
        compose = A.Compose([A.Resize(face, face),
                             A.OpticalDistortion(mode="fisheye", p=1.0,
                                                 fill_mask=IGNORE_INDEX)], seed=seed)

        def album_batch(idx: Tensor) -> tuple[Tensor, Tensor]:
            rgb, labels = gather(idx)
            images = _to_uint8(rgb).permute(0, 2, 3, 1).numpy()   # the stored uint8, HWC
            masks = labels.to(torch.uint8).numpy()
            out = [compose(image=i, mask=m) for i, m in zip(images, masks)]
            return (torch.stack([torch.from_numpy(o["image"]) for o in out])
                    .permute(0, 3, 1, 2).float() / 255,
                    torch.stack([torch.from_numpy(o["mask"]) for o in out]).long())

        return Condition(name, "faces", n_faces, album_batch, {
            "augmentation": "A.Compose([A.Resize(S, S), A.OpticalDistortion(mode='fisheye', "
                            f"p=1, fill_mask={IGNORE_INDEX})], seed=seed), per sample, uint8 HWC",
            "version": A.__version__})

    if name == "reproject":
        aug = ot.augment.RandomReproject(image_size=(face, face), source_fov=math.radians(90),
                                         seed=seed)
        f, c = face / 2, (face - 1) / 2   # the faces' own pinhole (DESIGN.md)
        intrinsics = torch.tensor([f, f, c, c])

        def reproject_batch(idx: Tensor) -> tuple[Tensor, Tensor]:
            rgb, labels = gather(idx)
            out = aug({"rgb": rgb, "labels": labels},
                      intrinsics=intrinsics.expand(len(idx), 4))
            return out["rgb"], out["labels"]

        return Condition(name, "faces", n_faces, reproject_batch, {
            "augmentation": "ot.augment.RandomReproject(image_size=(S, S), source_fov=90 deg, "
                            "seed=seed) at its defaults (antialias, coverage_range), "
                            "intrinsics f = F / 2, c = (F - 1) / 2",
            "module": repr(aug), "antialias": aug.antialias,
            "coverage_range": list(aug.coverage_range or ())})

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


def flat(losses: list[float], tol: float) -> dict:
    """The stopping rule's test: the mean loss of the last quarter of ``losses`` against the
    previous quarter's (a quarter of at least one step); flat when ``(previous - last) /
    previous <= tol``."""
    q = max(1, len(losses) // 4)
    previous = statistics.fmean(losses[-2 * q:-q])
    last = statistics.fmean(losses[-q:])
    change = (previous - last) / previous
    return {"flat": change <= tol, "loss_previous_quarter": previous,
            "loss_last_quarter": last, "quarter_change": change}


def run_meta(args: argparse.Namespace, **extra) -> dict:
    """A run's cache key: the flags it depends on and ``extra`` (its condition, seed, cap and
    ranges)."""
    return {"version": RUN_VERSION, **{f: (list(getattr(args, f)) if isinstance(
        getattr(args, f), tuple) else getattr(args, f)) for f in RUN_FLAGS}, **extra}


def train_run(condition: Condition, sets: dict | None, args: argparse.Namespace, seed: int,
              *, max_steps: int | None = None) -> dict:
    """Train a fresh network under ``condition`` by the stopping rule (chunks of
    ``args.chunk`` steps; from ``args.min_steps`` on, stop when :func:`flat`, or at
    ``max_steps``, default ``args.max_steps``) and evaluate it on ``sets`` (None: not
    evaluated); losses, stopping, scores, seconds."""
    max_steps = max_steps or args.max_steps
    data = torch.Generator().manual_seed(DATA_SEED + seed)
    torch.manual_seed(seed)   # the network's initial weights: PyTorch's default init
    net = UNet(NUM_CLASSES, args.width, args.levels)
    opt = torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=1e-4)
    warmup = max(args.warmup, 1)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: min(1.0, (step + 1) / warmup))
    losses, step_s, augment_s, start = [], [], 0.0, time.perf_counter()
    stop = None
    net.train()
    while stop is None:
        for _ in range(args.chunk):
            t0 = time.perf_counter()
            idx = torch.randint(0, condition.size, (args.batch,), generator=data)
            with torch.no_grad():
                rgb, labels = condition.batch(idx)
            augment_s += time.perf_counter() - t0
            loss = F.cross_entropy(net(rgb), labels, ignore_index=IGNORE_INDEX)
            if not torch.isfinite(loss):
                raise RuntimeError(f"{condition.name}, seed {seed}: loss {float(loss)} at step "
                                   f"{len(losses)} (a batch without a valid pixel?)")
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
            step_s.append(time.perf_counter() - t0)
        if len(losses) >= args.min_steps:
            test = flat(losses, args.flat_tol)
            if test["flat"] or len(losses) >= max_steps:
                stop = {"stopped": "flat" if test["flat"] else "cap", **test}
    train_s = time.perf_counter() - start
    start = time.perf_counter()
    scores = evaluate(net, sets) if sets is not None else None
    window = max(1, len(losses) // 4)
    loss_start = statistics.fmean(losses[:window])
    loss_end = statistics.fmean(losses[-window:])
    return {"condition": condition.name, "seed": seed, "steps": len(losses), **stop,
            "max_steps": max_steps, "losses": losses, "loss_start": loss_start,
            "loss_end": loss_end, "loss_decreased": loss_end < loss_start, "train_s": train_s,
            "step_s_median": statistics.median(step_s), "step_s_min": min(step_s),
            "augment_s": augment_s,
            "eval_s": time.perf_counter() - start, "eval": scores}


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
    """Per condition and camera kind: mIoU mean, sample std, min, max and per seed; per class
    the IoU's mean over the seeds (None for a class absent from the truth)."""
    out: dict[str, dict] = {}
    for run in runs:
        for kind, scores in run["eval"].items():
            entry = out.setdefault(run["condition"], {}).setdefault(
                kind, {"per_seed": {}, "iou_per_seed": []})
            entry["per_seed"][str(run["seed"])] = scores["miou"]
            entry["iou_per_seed"].append(scores["iou"])
    for kinds in out.values():
        for entry in kinds.values():
            values = list(entry["per_seed"].values())
            per_class = list(zip(*entry.pop("iou_per_seed")))
            entry.update(mean=statistics.fmean(values),
                         std=statistics.stdev(values) if len(values) > 1 else 0.0,
                         min=min(values), max=max(values),
                         iou_mean={CLASSES[c]: (None if None in v else statistics.fmean(v))
                                   for c, v in enumerate(per_class)})
    return out


def search_kornia(faces: dict, cubes: dict, val: dict, args: argparse.Namespace,
                  log: Callable[[str], None] = print) -> dict:
    """(b)'s ranges: every ``KORNIA_GRID`` setting trained with seed 0 (capped at
    ``args.search_max_steps``) and scored on the validation split (the mean of its camera
    kinds' mIoU); the best."""
    jobs = [(f"kornia_search{i}",
             run_meta(args, condition="kornia_search", seed=0, kornia=ranges,
                      max_steps=args.search_max_steps),
             lambda ranges=ranges: train_run(
                 make_condition("kornia_fisheye", faces, cubes, 0, kornia=ranges), val, args,
                 0, max_steps=args.search_max_steps))
            for i, ranges in enumerate(KORNIA_GRID)]
    rows = []
    for ranges, run in zip(KORNIA_GRID, cached_runs(args.cache, jobs, log)):
        score = statistics.fmean(run["eval"][k]["miou"] for k in CAMERA_KINDS)
        rows.append({**ranges, "val_miou": score, "steps": run["steps"],
                     "stopped": run["stopped"], "train_s": run["train_s"],
                     "per_kind": {k: run["eval"][k]["miou"] for k in CAMERA_KINDS}})
        log(f"kornia search: center {ranges['center']}, gamma {ranges['gamma']}: validation "
            f"mIoU {100 * score:.1f} % ({run['steps']} steps, {run['stopped']})")
    best = max(rows, key=lambda r: r["val_miou"])
    return {"grid": rows, "best": {"center": best["center"], "gamma": best["gamma"]},
            "rule": "highest mean of the camera kinds' mIoU on the validation split, seed 0, "
                    f"at most {args.search_max_steps} steps"}


def load_data(args: argparse.Namespace, log: Callable[[str], None] = print) -> dict:
    """The cubes, the faces, the test set, and (where a condition needs them) the validation
    split and the upper bound's images."""
    cache = Path(args.cache)
    cubes = training_cubes(cache, args.train_town, args.cubes, args.size, log)
    size, aa = args.size, args.trace_aa
    data = {"cubes": cubes, "faces": horizontal_faces(cubes)}
    data["test"] = traced_set(cache, "test", args.test_town, args.test_layout,
                              train_positions(args.test_frames, args.test_town),
                              tuple(args.test_weathers),
                              1, size, aa, log)
    if "kornia_fisheye" in args.conditions:
        positions = train_positions(args.cubes + args.val_frames, args.train_town)[args.cubes:]
        data["val"] = traced_set(cache, "val", args.train_town, TRAIN_LAYOUT, positions,
                                 (WEATHER,), 1, size, aa, log)
    if "fisheye_upper" in args.conditions:
        data["upper"] = merged(traced_set(cache, "upper", args.train_town, TRAIN_LAYOUT,
                                          train_positions(args.cubes, args.train_town),
                                          (WEATHER,), 2, size, aa, log))
    return data


def set_info(sets: dict[str, dict[str, Tensor]]) -> dict:
    out = {}
    for kind, data in sets.items():
        labels = data["labels"]
        present = sorted(set(labels[labels != IGNORE_INDEX].unique().tolist()))
        out[kind] = {"images": len(data["rgb"]), "classes_present": present,
                     "classes_absent": [CLASSES[c] for c in range(NUM_CLASSES)
                                        if c not in present],
                     "valid_fraction": float((labels != IGNORE_INDEX).double().mean())}
    return out


def run(args: argparse.Namespace, log: Callable[[str], None] = print) -> dict:
    load_start = begin_run(args.threads)
    started = time.perf_counter()
    skipped = {}
    if "albumentations" in args.conditions and isinstance(albumentations_or_reason(), str):
        skipped["albumentations"] = albumentations_or_reason()
        log(f"skipping (c): {skipped['albumentations']}")
    names = [n for n in CONDITIONS if n in args.conditions and n not in skipped]
    args.conditions = names
    data = load_data(args, log)
    faces, cubes = data["faces"], data["cubes"]
    data_s = time.perf_counter() - started

    search = (search_kornia(faces, cubes, data["val"], args, log)
              if "kornia_fisheye" in names else None)

    def fresh(name: str, seed: int) -> Condition:
        return make_condition(name, faces, cubes, seed, omni_mode=args.omni_mode,
                              kornia=search and search["best"], traced=data.get("upper"))

    jobs = [(f"{name}_seed{seed}",
             run_meta(args, condition=name, seed=seed, max_steps=args.max_steps,
                      kornia=(search["best"] if name == "kornia_fisheye" else None)),
             lambda name=name, seed=seed: train_run(fresh(name, seed), data["test"], args,
                                                    seed))
            for name in names for seed in args.seeds]
    with tqdm(total=len(jobs), desc="training runs", unit="run", file=sys.stderr,
              disable=not args.progress) as bar:
        runs = cached_runs(args.cache, jobs, log, bar.update)
    settings = {}
    for name in names:   # the first seed's settings (a module's repr names its seed)
        condition = fresh(name, args.seeds[0])
        settings[name] = {"source": condition.source, "samples": condition.size,
                          **condition.settings}
    timing = time_augmentations({n: fresh(n, 12345) for n in names}, args.batch,
                                args.timing_repeats, args.timing_warmup)

    net = UNet(NUM_CLASSES, args.width, args.levels)
    return {
        **run_record("training", torch.device("cpu"), args.threads),
        "setup": {
            "quick": args.quick, "image_size": [args.size, args.size],
            "face_size": args.size, "batch": args.batch,
            "optimizer": f"AdamW(lr={args.lr}, weight_decay=1e-4), linear warm-up over "
                         f"{args.warmup} steps, then constant",
            "stopping": {"chunk": args.chunk, "min_steps": args.min_steps,
                         "max_steps": args.max_steps, "flat_tol": args.flat_tol,
                         "rule": "after each chunk, from min_steps on: stop when (mean loss "
                                 "of the previous quarter - the last quarter's) / the "
                                 "previous quarter's <= flat_tol, or at max_steps"},
            "loss": f"cross-entropy, ignore_index {IGNORE_INDEX}",
            "network": f"UNet(width={args.width}, levels={args.levels})",
            "parameters": sum(p.numel() for p in net.parameters()),
            "init": "PyTorch default init after torch.manual_seed(seed)",
            "batches": f"torch.Generator().manual_seed({DATA_SEED} + seed), with replacement",
            "train": {"town_seed": args.train_town, "layout": TRAIN_LAYOUT,
                      "cubes": args.cubes, "weather": WEATHER,
                      "faces_a_to_d": list(HORIZONTAL), "faces_count": len(faces["rgb"]),
                      "upper_images": len(data["upper"]["rgb"]) if "upper" in data else None,
                      "x_m": list(TRAIN_X), "height_m": list(TRAIN_HEIGHT),
                      "z_m": list(TRAIN_Z), "t_s": list(TRAIN_T), "rgb": "uint8 -> [0, 1]",
                      "cache": str(args.cache)},
            "test": {"town_seed": args.test_town, "layout": args.test_layout,
                     "frames": args.test_frames, "weathers": list(args.test_weathers),
                     "trace_aa": args.trace_aa,
                     "render": "Town.render_rays of every pixel's rays (Camera.unproject)",
                     **set_info(data["test"])},
            "validation": ({"town_seed": args.train_town, "frames": args.val_frames,
                            "weather": WEATHER, **set_info(data["val"])}
                           if "val" in data else None),
            "data_s": data_s,
            "miou": "mean IoU over the classes present in the camera kind's ground truth, "
                    "one confusion matrix over all its valid pixels",
            "small_classes": list(SMALL_CLASSES),
            "omni_mode": args.omni_mode,
        },
        "seeds": list(args.seeds),
        "skipped": skipped,
        "kornia_search": search,
        "conditions": {n: {"label": LABELS[n], **settings[n]} for n in names},
        "augment_timing": timing,
        "runs": runs,
        "summary": summarise(runs),
        "timing_repeats": args.timing_repeats, "timing_warmup": args.timing_warmup,
        "timestamp_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "total_s": time.perf_counter() - started,
        "cost": {"runs": len(runs), "steps": sum(r["steps"] for r in runs),
                 "runs_s": sum(r["train_s"] + r["eval_s"] for r in runs),
                 "search_runs": len(search["grid"]) if search else 0,
                 "search_steps": sum(r["steps"] for r in search["grid"]) if search else 0,
                 "search_s": sum(r["train_s"] for r in search["grid"]) if search else 0.0,
                 "data_s": data_s,
                 "note": "seconds of training and evaluation summed over the runs, each on "
                         "--threads threads; runs spread over processes (cached_run) overlap "
                         "in wall time"},
        "loadavg_start": load_start,
        "loadavg_end": loadavg(),
    }


def estimate(args: argparse.Namespace, log: Callable[[str], None] = print) -> dict:
    """The projected cost of the table at ``args``' settings on this machine: ``args.
    estimate_steps + 1`` training steps of every condition (after an untimed run of
    condition (a)'s, the process's warm-up), median and fastest, on random data of
    the full shapes, the tracing of one image of each kind and of one cube, and the
    evaluation of one batch; the whole table's training at the cap (every run and search run
    at its ``max_steps``) and at ``min_steps`` (every run flat at once)."""
    load_start = begin_run(args.threads)
    g = torch.Generator().manual_seed(0)
    s, n = args.size, 4 * args.batch
    faces = {"rgb": (torch.randint(0, 256, (n, 3, s, s), generator=g) / 255).float(),
             "labels": torch.randint(0, NUM_CLASSES, (n, s, s), generator=g)}
    cubes = {"rgb": (torch.randint(0, 256, (n, 6, 3, s, s), generator=g) / 255).float(),
             "labels": torch.randint(0, NUM_CLASSES, (n, 6, s, s), generator=g)}
    skipped = {}
    if isinstance(albumentations_or_reason(), str):
        skipped["albumentations"] = albumentations_or_reason()
    names = [c for c in CONDITIONS if c in args.conditions and c not in skipped]
    timed = argparse.Namespace(**{**vars(args), "chunk": args.estimate_steps + 1,
                                  "min_steps": 1, "max_steps": args.estimate_steps + 1})
    step_s, step_s_min = {}, {}
    # untimed: the process's first steps (allocator, kernels' first use) are slower
    train_run(make_condition("none", faces, cubes, 0), None, timed, 0)
    for name in names:
        condition = make_condition(name, faces, cubes, 0, omni_mode=args.omni_mode,
                                   traced=faces)
        timed_run = train_run(condition, None, timed, 0)
        step_s[name], step_s_min[name] = timed_run["step_s_median"], timed_run["step_s_min"]
        log(f"{name}: {step_s[name]:.3f} s a step (median of {args.estimate_steps + 1}; "
            f"fastest {step_s_min[name]:.3f} s)")
    town = ot.scenes.Town(args.train_town, layout=TRAIN_LAYOUT)
    t0 = time.perf_counter()
    town.render_cubemap(torch.tensor([0.0, -1.0, 0.0]), None, s, weather=WEATHER)
    cube_s = time.perf_counter() - t0
    image_s = 0.0
    for kind in CAMERA_KINDS:
        camera, attitude = test_camera(kind, s)
        t0 = time.perf_counter()
        trace_image(town, camera, attitude, [0.0, -1.0, 0.0], 0.0, WEATHER, args.trace_aa)
        image_s += (time.perf_counter() - t0) / len(CAMERA_KINDS)
    torch.manual_seed(0)
    net = UNet(NUM_CLASSES, args.width, args.levels)
    t0 = time.perf_counter()
    evaluate(net, {"fisheye": {"rgb": faces["rgb"][:16], "labels": faces["labels"][:16]}})
    eval_image_s = (time.perf_counter() - t0) / 16

    seeds = len(args.seeds)
    search = len(KORNIA_GRID) if "kornia_fisheye" in names else 0
    images = 2 * args.test_frames + (2 * args.val_frames if search else 0) + \
        (4 * args.cubes if "fisheye_upper" in names else 0)
    data_s = args.cubes * cube_s + images * image_s
    eval_s = eval_image_s * (len(names) * seeds * 2 * args.test_frames +
                             search * 2 * args.val_frames)

    def total(steps: int, search_steps: int, per_step: dict[str, float]) -> float:
        return (sum(seeds * steps * per_step[n] for n in names) + data_s + eval_s +
                search * search_steps * per_step.get("kornia_fisheye", 0.0))

    at_cap = total(args.max_steps, args.search_max_steps, step_s)
    at_min = total(args.min_steps, args.min_steps, step_s)
    at_cap_fastest = total(args.max_steps, args.search_max_steps, step_s_min)
    return {**run_record("training_estimate", torch.device("cpu"), args.threads),
            "settings": {k: (v if isinstance(v, (int, float, str, list)) else str(v))
                         for k, v in vars(args).items()},
            "step_s": step_s, "step_s_min": step_s_min, "skipped": skipped,
            "cube_s": cube_s, "traced_image_s": image_s,
            "eval_image_s": eval_image_s, "runs": len(names) * seeds,
            "search_runs": search, "data_s": data_s, "eval_s": eval_s,
            "total_at_cap_s": at_cap, "total_at_min_steps_s": at_min,
            "total_at_cap_fastest_steps_s": at_cap_fastest,
            "loadavg_start": load_start, "loadavg_end": loadavg(),
            "timestamp_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def estimate_markdown(est: dict) -> str:
    st = est["settings"]
    lines = [f"projected cost of the training table ({st['size']} px, {est['runs']} runs + "
             f"{est['search_runs']} search runs, {est['threads']} threads, load "
             f"{est['loadavg_start']} -> {est['loadavg_end']}):", "",
             "| condition | s / step (median) | fastest | a run at min_steps | "
             "a run at the cap |", "|---|---:|---:|---:|---:|"]
    for name, s in est["step_s"].items():
        lines.append(f"| {LABELS[name]} | {s:.3f} | {est['step_s_min'][name]:.3f} | "
                     f"{s * st['min_steps'] / 60:.1f} min | {s * st['max_steps'] / 60:.1f} min |")
    lines += ["", f"data (cubes + traced images, once, cached): {est['data_s'] / 60:.1f} min; "
              f"evaluation: {est['eval_s'] / 60:.1f} min",
              f"whole table: {est['total_at_min_steps_s'] / 3600:.2f} h if every run is flat "
              f"at min_steps ({st['min_steps']}), {est['total_at_cap_s'] / 3600:.2f} h if every "
              f"run reaches the cap ({st['max_steps']}; search runs {st['search_max_steps']}), "
              f"{est['total_at_cap_fastest_steps_s'] / 3600:.2f} h at the cap at every "
              "condition's fastest step (the machine's own speed when nothing else runs)"]
    if est["skipped"]:
        lines.append("skipped: " + "; ".join(f"{k}: {v}" for k, v in est["skipped"].items()))
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def markdown(result: dict) -> str:
    s = result["setup"]
    seeds = ", ".join(str(x) for x in result["seeds"])
    te, st = s["test"], s["stopping"]
    lines = [
        f"training: {s['network']} ({s['parameters']:,} parameters), batch {s['batch']}, "
        f"{s['image_size'][0]} x {s['image_size'][1]}, {s['optimizer']}, until flat (chunks "
        f"of {st['chunk']}, {st['min_steps']}-{st['max_steps']} steps, tol "
        f"{100 * st['flat_tol']:g} %), seeds {seeds}; train: {s['train']['cubes']} cubemaps "
        f"of town {s['train']['town_seed']} ({s['train']['faces_count']} horizontal faces for "
        f"(a)-(d)); test: traced in town {te['town_seed']} (layout {te['layout']}), "
        f"{', '.join(te['weathers'])}, {te['fisheye']['images']} fisheye + "
        f"{te['catadioptric']['images']} catadioptric images; {result['threads']} "
        f"thread{'s' if result['threads'] > 1 else ''}, commit {result['commit'][:12]}"
        f"{' (dirty)' if result['dirty'] else ''}", "",
        "| condition | fisheye mIoU % | catadioptric mIoU % | fisheye pole / sign / pedestrian "
        "IoU % | steps (stopped, %) | augmentation images/s | train s / run |",
        "|---|---:|---:|---:|---:|---:|---:|"]

    def cell(entry: dict) -> str:
        return (f"{100 * entry['mean']:.1f} ± {100 * entry['std']:.1f} "
                f"[{100 * entry['min']:.1f}-{100 * entry['max']:.1f}]")

    for name, info in result["conditions"].items():
        summary = result["summary"][name]
        runs = [r for r in result["runs"] if r["condition"] == name]
        small = " / ".join(_pct(summary["fisheye"]["iou_mean"][c]) for c in SMALL_CLASSES)
        steps = ", ".join(f"{r['steps']} ({r['stopped']}, {-100 * r['quarter_change']:+.1f} %)"
                          for r in runs)
        lines.append(f"| {info['label']} | {cell(summary['fisheye'])} | "
                     f"{cell(summary['catadioptric'])} | {small} | {steps} | "
                     f"{result['augment_timing'][name]['images_per_s']:.0f} | "
                     f"{statistics.fmean(r['train_s'] for r in runs):.1f} |")
    for kind in CAMERA_KINDS:
        header = [f"**{c}**" if c in SMALL_CLASSES else c for c in CLASSES]
        lines += ["", f"IoU % per class, {kind} test images (mean over the seeds; small "
                  "classes in bold; - absent from the test images):", "",
                  "| condition | " + " | ".join(header) + " |",
                  "|---|" + "---:|" * NUM_CLASSES]
        for name, info in result["conditions"].items():
            iou = result["summary"][name][kind]["iou_mean"]
            lines.append(f"| {info['label']} | " + " | ".join(
                f"**{_pct(iou[c])}**" if c in SMALL_CLASSES else _pct(iou[c])
                for c in CLASSES) + " |")
    if result["kornia_search"]:
        search = result["kornia_search"]
        lines += ["", f"kornia RandomFisheye ranges searched on the validation split "
                  f"({search['rule']}):", "",
                  "| center | gamma | validation mIoU % | steps |", "|---|---|---:|---:|"]
        for row in search["grid"]:
            best = " (best)" if {"center": row["center"], "gamma": row["gamma"]} == \
                search["best"] else ""
            lines.append(f"| {row['center']} | {row['gamma']}{best} | "
                         f"{100 * row['val_miou']:.1f} | {row['steps']} ({row['stopped']}) |")
    lines += ["", "mIoU: mean ± sample std [min-max] over the seeds; the mean IoU over the "
              "classes present in each camera kind's test images (valid pixels only). "
              "Absent from the test set, so left out: " + "; ".join(
                  f"{kind}: {', '.join(te[kind]['classes_absent']) or 'none'}"
                  for kind in CAMERA_KINDS) + ".",
              f"steps (stopped, %): each seed's steps, why it stopped (flat or the cap) and "
              f"the change of its mean loss from the previous quarter of its steps to the last "
              f"(flat: at most -{100 * st['flat_tol']:g} %).",
              f"augmentation images/s: one batch of {s['batch']} (gather + augment), median of "
              f"{result['timing_repeats']} calls; (a) and (f) are the gather alone."]
    cost = result.get("cost")
    if cost:
        lines.append(
            f"cost: {cost['runs']} runs ({cost['steps']:,} steps) and {cost['search_runs']} "
            f"search runs ({cost['search_steps']:,} steps) trained and evaluated in "
            f"{(cost['runs_s'] + cost['search_s']) / 3600:.2f} h of {result['threads']} "
            f"thread{'s' if result['threads'] > 1 else ''} each (summed over the runs; this "
            f"process read the runs it found saved), the data made or read in "
            f"{cost['data_s'] / 60:.1f} min.")
    if result["skipped"]:
        lines.append("skipped: " + "; ".join(f"{LABELS[k]}: {v}"
                                             for k, v in result["skipped"].items()))
    return "\n".join(lines)


def chart(result: dict, path: Path) -> None:
    """Bars: mean mIoU per condition, fisheye and catadioptric groups; whiskers min-max over
    the seeds; each seed a dot. Written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result["conditions"])
    fig, ax = plt.subplots(figsize=(9, 4.5), layout="constrained")
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
    ax.set_xticks(range(len(CAMERA_KINDS)), [f"{k} (traced, held-out town)" for k in CAMERA_KINDS])
    ax.set_ylabel("mIoU % over the valid area")
    s = result["setup"]
    ax.set_title(f"Segmentation trained on town {s['train']['town_seed']} under each condition, "
                 f"tested on omni images traced in town {s['test']['town_seed']}\n"
                 f"until flat or {s['stopping']['max_steps']} steps, batch {s['batch']}, "
                 f"{s['image_size'][0]} px, {len(result['seeds'])} seed(s): bar mean, whiskers "
                 "min-max, dots seeds",
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
DEFAULTS = {"size": (128, 32), "cubes": (96, 4), "batch": (8, 4), "width": (16, 8),
            "levels": (4, 3), "lr": (1e-3, 3e-3), "warmup": (WARMUP_STEPS, 2),
            "chunk": (100, 4), "min_steps": (400, 8), "max_steps": (1000, 12),
            "search_max_steps": (500, 8), "flat_tol": (0.02, 0.02), "test_frames": (48, 2),
            "val_frames": (16, 2), "trace_aa": (2, 1), "seeds": ([0, 1, 2], [0]),
            "timing_repeats": (10, 2), "timing_warmup": (2, 1), "threads": (2, 1)}


def make_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 32 x 32, 4 cubes, a 3-level UNet of width 8, 8-12 "
                             "steps of 4 (search 8), 2 test and 2 validation positions, "
                             "seed 0, 1 thread")
    parser.add_argument("--estimate", action="store_true",
                        help="no table: time a few training steps of every condition at the "
                             "settings given (the full run's by default) and print the "
                             "whole table's projected cost")
    parser.add_argument("--estimate-steps", type=positive_int, default=5,
                        help="timed steps per condition for --estimate (5)")
    parser.add_argument("--size", type=positive_int, default=None,
                        help="face, augmented and test image side (128; 32 quick)")
    parser.add_argument("--cubes", type=positive_int, default=None,
                        help="training cubemaps (96; 4 quick)")
    parser.add_argument("--batch", type=positive_int, default=None,
                        help="samples per step (8; 4 quick)")
    parser.add_argument("--chunk", type=positive_int, default=None,
                        help="steps between two tests of the stopping rule (100; 4 quick)")
    parser.add_argument("--min-steps", type=positive_int, default=None,
                        help="steps before the first test of the stopping rule (400; 8 quick)")
    parser.add_argument("--max-steps", type=positive_int, default=None,
                        help="the cap on a run's steps (1000; 12 quick)")
    parser.add_argument("--search-max-steps", type=positive_int, default=None,
                        help="the cap on a kornia search run's steps (500; 8 quick)")
    parser.add_argument("--flat-tol", type=float, default=None,
                        help="flat: the last quarter's mean loss at most this fraction below "
                             "the previous quarter's (0.02)")
    parser.add_argument("--test-frames", type=positive_int, default=None,
                        help="test positions, a fisheye and a catadioptric image each "
                             "(48; 2 quick)")
    parser.add_argument("--val-frames", type=positive_int, default=None,
                        help="validation positions of the training town (16; 2 quick)")
    parser.add_argument("--trace-aa", type=positive_int, default=None,
                        help="sub-pixel rays per side of a traced pixel's RGB (2; 1 quick)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None,
                        help="seeds, one run per condition each (0 1 2; 0 quick)")
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS),
                        help="conditions to run (default all)")
    parser.add_argument("--omni-mode", choices=("fisheye", "mixed", "catadioptric"),
                        default="fisheye", help="RandomOmniCamera's mode in (e) (fisheye)")
    parser.add_argument("--train-town", type=int, default=0,
                        help="seed of the training town (default 0, layout 1)")
    parser.add_argument("--test-town", type=int, default=1,
                        help="seed of the test town (default 1)")
    parser.add_argument("--test-layout", type=int, choices=sorted(ot.scenes.town.LAYOUTS),
                        default=2, help="layout of the test town (default 2, crossroads)")
    parser.add_argument("--test-weathers", nargs="+", choices=list(ot.scenes.town.WEATHERS),
                        default=list(TEST_WEATHERS),
                        help="the test images' weathers, in turn (default: "
                             f"{' '.join(TEST_WEATHERS)}); never the training's {WEATHER}")
    parser.add_argument("--width", type=positive_int, default=None,
                        help="UNet channels at full resolution (16; 8 quick)")
    parser.add_argument("--levels", type=positive_int, default=None,
                        help="UNet levels (4: 488,909 parameters at width 16; 3 quick)")
    parser.add_argument("--lr", type=float, default=None,
                        help="learning rate after the warm-up (1e-3; 3e-3 quick)")
    parser.add_argument("--warmup", type=int, default=None,
                        help=f"linear warm-up steps ({WARMUP_STEPS}; 2 quick)")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch threads (2; 1 quick: a smoke run must not need a second "
                             "idle core)")
    parser.add_argument("--timing-repeats", type=positive_int, default=None,
                        help="timed augmentation calls per condition (10; 2 quick)")
    parser.add_argument("--timing-warmup", type=int, default=None,
                        help="untimed augmentation calls first (2; 1 quick)")
    parser.add_argument("--cache", type=Path, default=ROOT / "out" / "bench_training",
                        help="folder of the cached cubemaps and traced images "
                             "(default out/bench_training)")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON output; the .md table and .png chart go beside it "
                             "(default benchmarks/results/training.json; quick/ for --quick, "
                             "quick/training_estimate.json for --estimate)")
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
        raise ValueError(f"--size: expected at least 8 pixels, got {args.size}")
    if args.size % 2 ** (args.levels - 1):
        raise ValueError(f"--size: expected a multiple of 2^(levels - 1) = "
                         f"{2 ** (args.levels - 1)}, got {args.size}")
    if args.timing_warmup < 0 or args.warmup < 0:
        raise ValueError("--timing-warmup, --warmup: expected >= 0")
    if not (math.isfinite(args.lr) and args.lr > 0):
        raise ValueError(f"--lr: expected a positive number, got {args.lr}")
    if not (math.isfinite(args.flat_tol) and 0 <= args.flat_tol < 1):
        raise ValueError(f"--flat-tol: expected a fraction in [0, 1), got {args.flat_tol}")
    if args.min_steps < 8:
        raise ValueError(f"--min-steps: expected at least 8 (two quarters of 2), got "
                         f"{args.min_steps}")
    for flag in ("min_steps", "max_steps", "search_max_steps"):
        if getattr(args, flag) % args.chunk:
            raise ValueError(f"--{flag.replace('_', '-')}: expected a multiple of --chunk "
                             f"({args.chunk}), got {getattr(args, flag)}")
    if args.max_steps < args.min_steps or args.search_max_steps < args.min_steps:
        raise ValueError("--max-steps, --search-max-steps: expected at least --min-steps")
    if len(set(args.seeds)) != len(args.seeds) or min(args.seeds) < 0:
        raise ValueError(f"--seeds: expected distinct seeds >= 0, got {args.seeds}")
    if args.train_town < 0 or args.test_town < 0:
        raise ValueError("--train-town, --test-town: expected seeds >= 0")
    if args.train_town == args.test_town:
        raise ValueError(f"--train-town and --test-town: both {args.test_town}; the test "
                         "town must be one the networks never saw")
    if WEATHER in args.test_weathers:
        raise ValueError(f"--test-weathers: {WEATHER} is the training's weather; the test "
                         "weathers must be held out")
    if len(set(args.conditions)) != len(args.conditions):
        raise ValueError(f"--conditions: duplicates in {args.conditions}")
    return args


def main(argv: list[str] | None = None) -> int:
    parser = make_parser()
    args = parser.parse_args(argv)
    if args.out is None:   # a --quick or --estimate run never overwrites the full run's
        args.out = (results_path("training_estimate.json", quick=True) if args.estimate else
                    results_path("training.json", quick=args.quick))
    try:
        args = resolve(args)
    except ValueError as err:
        parser.error(str(err))
    if args.estimate:
        result = estimate(args)
        write_json_atomic(result, args.out)
        print(estimate_markdown(result))
        print(f"\nwrote {args.out}")
        return 0
    result = run(args)
    paths = write_outputs(result, args.out)
    print(markdown(result))
    print("\nwrote " + ", ".join(str(p) for p in paths.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
