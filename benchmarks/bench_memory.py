"""Does the huge-page buffer pool (``omniscape_torch.render.memory``) earn its keep?

``memory.empty`` is what the layer (``render/layer.py``), the fast sampler (``render/fast.py``)
and the augmentation (``render/augment.py``) allocate their large CPU outputs with: from
``memory.HUGE_BYTES`` (32 MB) on, an ``mmap`` advised ``MADV_HUGEPAGE``, returned to a pool of
up to ``memory.POOL_BYTES`` (1 GiB) per process once its last tensor is freed, and taken from
there by the next allocation of the same size. This script times the same renders with the
allocator swapped, in one run, round-robin (a change of load hits every variant alike):

* ``pool``: the package as shipped;
* ``plain``: ``torch.empty`` (glibc: an ``mmap`` of ordinary pages per buffer above its mmap
  threshold, unmapped on free): what the package does without ``memory.py``;
* ``huge``: a fresh huge-page ``mmap`` per buffer, unmapped on free (no reuse): the pool's
  huge pages without its pool, to tell the two effects apart.

The swap monkeypatches ``omniscape_torch.render.memory.empty`` (the layer, the fast sampler and
the augmentation call it as ``memory.empty``; any other module-level binding of the function is
patched too), in the main process and, through ``worker_init_fn``, in each ``DataLoader``
worker. The package is not edited.

Rows:

* ``layer bB``: ``OmniProjection(presets.fisheye((1024, 1024)), 512)`` (equidistant, 190
  degrees) rendering a float32 RGB cube and an int64 label cube of ``6 x 512`` with a new batch
  of random attitudes per call (``render(rgb=, labels=, rotation=)``), B = 1 and 8, the outputs
  dropped after each call (as a training step does), ``--threads`` (2) torch threads;
* ``loader S <start method>``: a ``DataLoader`` with ``--workers`` (2) workers (one torch
  thread each, DataLoader's default) whose dataset yields random cubes (``6 x 3 x F x F``
  float32 and ``6 x F x F`` int64 labels, ``F = S / 2``, seeded per index) and whose
  ``collate_fn`` -- run in the workers -- stacks 8 of them and renders the batch with
  ``RandomOmniCamera((S, S), face_size=F)`` (RGB + labels + valid), S = 512 by default
  (``--loader-sizes``); images per second over ``--loader-batches`` batches after
  ``--loader-warmup`` (worker start-up), one fresh loader per variant and repeat, for the
  default start method (``fork`` on Linux with Python < 3.14) and ``spawn``. The batches
  reach the main process through shared memory, as any DataLoader's.

Before timing, one instrumented call per row counts the ``memory.empty`` calls at or above
``HUGE_BYTES`` (the only ones the pool changes) and their sizes: a row without any cannot gain
from the pool and shows the noise floor. The JSON records the transparent huge page settings
(``/sys/kernel/mm/transparent_hugepage``), the load average before and after each part, and
every raw time.

Usage::

    python benchmarks/bench_memory.py              # a few minutes on 2 idle cores
    python benchmarks/bench_memory.py --quick      # fewer repeats (smoke run)
    python benchmarks/bench_memory.py --loader-sizes 512 1024   # also where the pool engages
    python benchmarks/bench_memory.py --start-methods fork --loader-variants pool plain huge

Results: a table on stdout (``without / with``: the median time of ``plain`` over that of
``pool``; above 1 the pool is faster) and JSON (``--out``, default
``benchmarks/results/memory.json``, written atomically).
"""

from __future__ import annotations

import argparse
import functools
import math
import mmap
import multiprocessing
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

# this folder's helpers; ``common`` puts the checkout first on sys.path
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import ROOT, loadavg, measure, positive_int, run_record, write_json_atomic  # noqa: E402
import omniscape_torch as ot  # noqa: E402
from omniscape_torch.render import memory  # noqa: E402
from omniscape_torch.render.augment import RandomOmniCamera  # noqa: E402

SEED = 20240611
VARIANTS = ("pool", "plain", "huge")
_POOLED_EMPTY = memory.empty   # the package's own, whatever a variant patches in


# --------------------------------------------------------------------------------------------
# The variants
# --------------------------------------------------------------------------------------------

def _plain_empty(shape, dtype, device=None) -> torch.Tensor:
    """``torch.empty``: what the package allocates with, without ``memory.py``."""
    return torch.empty(shape, dtype=dtype, device=device)


def _huge_empty(shape, dtype, device=None) -> torch.Tensor:
    """``memory.empty`` without its pool: from ``HUGE_BYTES`` on, a fresh huge-page mapping per
    call, unmapped when its last tensor is freed (the tensor holds the ``mmap`` object)."""
    size = math.prod(shape) * torch.empty((), dtype=dtype).element_size()
    if (size < memory.HUGE_BYTES or not hasattr(mmap, "MADV_HUGEPAGE")
            or (device is not None and torch.device(device).type != "cpu")):
        return torch.empty(shape, dtype=dtype, device=device)
    buffer = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    try:
        buffer.madvise(mmap.MADV_HUGEPAGE)
    except OSError:
        pass
    return torch.frombuffer(buffer, dtype=dtype).view(shape)


_EMPTY = {"pool": _POOLED_EMPTY, "plain": _plain_empty, "huge": _huge_empty}
#: Every (module, attribute) bound to the package's ``memory.empty``, found once.
_BINDINGS: list[tuple[object, str]] = []


def _bindings() -> list[tuple[object, str]]:
    """``(module, name)`` of every binding of ``memory.empty`` in the loaded package modules:
    ``memory.empty`` itself, and a ``from .memory import empty`` should a module ever use one
    (today the layer, the fast sampler and the augmentation call ``memory.empty``)."""
    if not _BINDINGS:
        for name, module in list(sys.modules.items()):
            if name == "omniscape_torch" or name.startswith("omniscape_torch."):
                for attr, value in list(vars(module).items()):
                    if value is _POOLED_EMPTY:
                        _BINDINGS.append((module, attr))
    return _BINDINGS


def use(variant: str) -> None:
    """Allocate the package's large outputs the ``variant`` way from now on (this process)."""
    fn = _EMPTY[variant]
    for module, attr in _bindings():
        setattr(module, attr, fn)


def _worker_init(variant: str, worker_id: int) -> None:
    """``DataLoader(worker_init_fn=)``: the variant in the worker, whatever the start method."""
    use(variant)


class _Counter:
    """Counts the calls of the variant's ``empty`` at or above ``HUGE_BYTES`` (sizes in MB)."""

    def __init__(self) -> None:
        self.sizes: list[float] = []

    def __enter__(self) -> "_Counter":
        self.inner = memory.empty

        def counting(shape, dtype, device=None):
            size = math.prod(shape) * torch.empty((), dtype=dtype).element_size()
            if size >= memory.HUGE_BYTES:
                self.sizes.append(round(size / 2 ** 20, 1))
            return self.inner(shape, dtype, device)

        for module, attr in _bindings():
            setattr(module, attr, counting)
        return self

    def __exit__(self, *exc) -> None:
        for module, attr in _bindings():
            setattr(module, attr, self.inner)


def thp_settings() -> dict:
    out = {}
    for name in ("enabled", "defrag"):
        try:
            out[name] = Path(f"/sys/kernel/mm/transparent_hugepage/{name}").read_text().strip()
        except OSError:
            out[name] = None
    return out


# --------------------------------------------------------------------------------------------
# The layer in the main process
# --------------------------------------------------------------------------------------------

def random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    """``(n, 3, 3)`` vehicle-like attitudes: any yaw, pitch and roll within 10 degrees."""
    yaw = (2 * torch.rand(n, generator=gen) - 1) * math.pi
    tilt = (2 * torch.rand(2, n, generator=gen) - 1) * math.radians(10)
    return ot.presets.yaw_pitch_roll_to_matrix(yaw, tilt[0], tilt[1])


def layer_part(args: argparse.Namespace) -> dict:
    torch.set_num_threads(args.threads)
    camera = ot.presets.fisheye((args.size, args.size))
    layer = ot.OmniProjection(camera, args.face)
    gen = torch.Generator().manual_seed(SEED)
    calls = args.warmup + args.repeats
    rows, fns = [], []
    counts = {}
    for batch in args.batches:
        rgb = torch.rand(batch, 6, 3, args.face, args.face, generator=gen)
        labels = torch.randint(0, 20, (batch, 6, args.face, args.face), generator=gen)
        pool = random_rotations(batch * (calls + 1), gen).reshape(calls + 1, batch, 3, 3)
        use("pool")
        with torch.no_grad(), _Counter() as count:
            layer.render(rgb=rgb, labels=labels, rotation=pool[-1])
        counts[batch] = count.sizes
        for variant in args.variants:
            # every variant sees the same attitudes in the same order
            state = {"i": 0}

            def fn(variant=variant, rgb=rgb, labels=labels, pool=pool, state=state):
                use(variant)
                rot = pool[state["i"] % calls]
                state["i"] += 1
                with torch.no_grad():
                    layer.render(rgb=rgb, labels=labels, rotation=rot)  # outputs dropped

            rows.append({"name": f"layer b{batch}", "batch": batch, "variant": variant})
            fns.append(fn)
    load_start = loadavg()
    start = time.perf_counter()
    stats = measure(fns, args.repeats, args.warmup, "cpu", progress=not args.no_progress)
    wall = time.perf_counter() - start
    use("pool")
    for row, s in zip(rows, stats):
        row.update(s)
        row["ms_per_image"] = 1e3 * s["median_s"] / row["batch"]
        row["pooled_allocations_per_call_mb"] = counts[row["batch"]]
    return {"setup": {"camera": f"presets.fisheye(({args.size}, {args.size})): equidistant, "
                                "190 deg", "face_size": args.face,
                      "inputs": "float32 RGB cube + int64 label cube, a new batch of random "
                                "attitudes per call", "batches": args.batches,
                      "threads": args.threads, "repeats": args.repeats,
                      "warmup": args.warmup},
            "loadavg_start": load_start, "loadavg_end": loadavg(), "wall_s": wall,
            "rows": rows}


# --------------------------------------------------------------------------------------------
# RandomOmniCamera inside a DataLoader
# --------------------------------------------------------------------------------------------

class RandomCubes(Dataset):
    """Random cubes: ``(6, 3, F, F)`` float32 RGB and ``(6, F, F)`` int64 labels, seeded per
    index (every variant and worker sees the same data)."""

    def __init__(self, length: int, face_size: int, classes: int = 20) -> None:
        self.length, self.face_size, self.classes = length, face_size, classes

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        g = torch.Generator().manual_seed(SEED + i)
        f = self.face_size
        return (torch.rand(6, 3, f, f, generator=g),
                torch.randint(0, self.classes, (6, f, f), generator=g))


class RenderCollate:
    """``collate_fn`` (runs in the workers): stack the cubes, render the batch through
    ``RandomOmniCamera`` (RGB, labels, valid)."""

    def __init__(self, image_size: tuple[int, int], face_size: int) -> None:
        self.aug = RandomOmniCamera(image_size, face_size=face_size, seed=SEED)

    def __call__(self, items):
        rgb = torch.stack([rgb for rgb, _ in items])
        labels = torch.stack([lab for _, lab in items])
        with torch.no_grad():
            out = self.aug(rgb, labels)
        return out["rgb"], out["labels"], out["valid"]


def loader_run(args: argparse.Namespace, size: int, variant: str, start_method: str) -> dict:
    """One fresh DataLoader of the variant: seconds to the first batch, images per second over
    the batches after the warm-up ones."""
    total = args.loader_warmup + args.loader_batches
    loader = DataLoader(
        RandomCubes(total * args.loader_batch, size // 2),
        batch_size=args.loader_batch, num_workers=args.workers,
        collate_fn=RenderCollate((size, size), size // 2),
        worker_init_fn=functools.partial(_worker_init, variant),
        multiprocessing_context=start_method)
    use(variant)   # the main process too (it only receives the batches)
    start = time.perf_counter()
    first = None
    for k, _ in enumerate(loader):
        if k == 0:
            first = time.perf_counter() - start
        if k + 1 == args.loader_warmup:
            steady = time.perf_counter()
    end = time.perf_counter()
    use("pool")
    images = args.loader_batches * args.loader_batch
    return {"size": size, "variant": variant, "start_method": start_method,
            "first_batch_s": first,
            "total_s": end - start, "steady_s": end - steady,
            "images_per_s": images / (end - steady)}


def loader_part(args: argparse.Namespace) -> dict:
    # what the pool can change here: the collate's large allocations, counted in this process
    counts = {}
    use("pool")
    for size in args.loader_sizes:
        collate = RenderCollate((size, size), size // 2)
        items = [RandomCubes(args.loader_batch, size // 2)[i] for i in range(args.loader_batch)]
        with _Counter() as count:
            collate(items)
        counts[size] = count.sizes
        del collate, items
    memory.release()
    load_start = loadavg()
    runs = []
    start = time.perf_counter()
    for size in args.loader_sizes:
        for method in args.start_methods:
            for r in range(args.loader_repeats):
                # round-robin, the order rotated each repeat
                k = r % len(args.loader_variants)
                for variant in args.loader_variants[k:] + args.loader_variants[:k]:
                    run = loader_run(args, size, variant, method)
                    run["repeat"] = r
                    runs.append(run)
                    if not args.no_progress:
                        print(f"# loader {size} {method} {variant} repeat {r}: "
                              f"{run['images_per_s']:.1f} images/s", file=sys.stderr)
    wall = time.perf_counter() - start
    rows = []
    for size in args.loader_sizes:
        for method in args.start_methods:
            for variant in args.loader_variants:
                ips = [x["images_per_s"] for x in runs if x["size"] == size
                       and x["start_method"] == method and x["variant"] == variant]
                q1, med, q3 = np.percentile(ips, [25, 50, 75])
                rows.append({"name": f"loader {size} {method}", "size": size,
                             "start_method": method, "variant": variant,
                             "images_per_s_median": float(med),
                             "images_per_s_iqr": float(q3 - q1),
                             "images_per_s_min": min(ips), "images_per_s_max": max(ips),
                             "images_per_s": ips,
                             "pooled_allocations_per_batch_mb": counts[size]})
    return {"setup": {"augmentation": "RandomOmniCamera((S, S), face_size=S // 2) for S in "
                                      f"{args.loader_sizes}, RGB + labels, in the collate_fn "
                                      "(in the workers)",
                      "batch": args.loader_batch, "workers": args.workers,
                      "worker_threads": 1, "batches_timed": args.loader_batches,
                      "warmup_batches": args.loader_warmup, "repeats": args.loader_repeats,
                      "default_start_method": multiprocessing.get_start_method()},
            "loadavg_start": load_start, "loadavg_end": loadavg(), "wall_s": wall,
            "runs": runs, "rows": rows}


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------

def _quartiles(values: list[float]) -> tuple[float, float, float]:
    q1, med, q3 = np.percentile(values, [25, 50, 75])
    return float(med), float(q1), float(q3)


def summary(result: dict) -> list[dict]:
    """One line per row: each variant's median and spread, and the ``without / with`` ratios:
    of the medians, paired (median and quartiles of the ratio within a round: the layer's calls
    of one round-robin round, the loader runs of one repeat, which share the machine's load of
    the moment) and of the fastest calls."""
    lines = []
    layer = result.get("layer")
    if layer:
        for name in dict.fromkeys(r["name"] for r in layer["rows"]):
            by = {r["variant"]: r for r in layer["rows"] if r["name"] == name}
            line = {"name": name, "unit": "ms / call",
                    "pooled_mb": by[next(iter(by))]["pooled_allocations_per_call_mb"]}
            for v, r in by.items():
                line[v] = (1e3 * r["median_s"], 1e3 * r["iqr_s"], 1e3 * r["min_s"])
            if "pool" in by and "plain" in by:
                line["ratio"] = by["plain"]["median_s"] / by["pool"]["median_s"]
                line["ratio_min"] = by["plain"]["min_s"] / by["pool"]["min_s"]
                line["ratio_paired"] = _quartiles([
                    a / b for a, b in zip(by["plain"]["times_s"], by["pool"]["times_s"])])
            lines.append(line)
    loader = result.get("loader")
    if loader:
        for name in dict.fromkeys(r["name"] for r in loader["rows"]):
            by = {r["variant"]: r for r in loader["rows"] if r["name"] == name}
            line = {"name": name, "unit": "images / s",
                    "pooled_mb": by[next(iter(by))]["pooled_allocations_per_batch_mb"]}
            for v, r in by.items():
                line[v] = (r["images_per_s_median"], r["images_per_s_iqr"],
                           r["images_per_s_max"])
            if "pool" in by and "plain" in by:   # time per image: without / with
                line["ratio"] = by["pool"]["images_per_s_median"] / \
                    by["plain"]["images_per_s_median"]
                line["ratio_min"] = by["pool"]["images_per_s_max"] / \
                    by["plain"]["images_per_s_max"]
                runs = {(x["repeat"], x["variant"]): x["images_per_s"]
                        for x in loader["runs"] if f"loader {x['size']} {x['start_method']}"
                        == name}
                line["ratio_paired"] = _quartiles([
                    runs[r, "pool"] / runs[r, "plain"] for r in sorted({k[0] for k in runs})])
            lines.append(line)
    return lines


def markdown(result: dict) -> str:
    variants = [v for v in VARIANTS if any(v in line for line in result["summary"])]
    head = " | ".join(f"{v} median (IQR) [best]" for v in variants)
    load = [" / ".join(f"{x:.2f}" for x in la) if la else "?"
            for la in (result["loadavg_start"], result["loadavg_end"])]
    machine = result["machine"]
    out = [f"Huge-page buffer pool: {result['threads']} threads, {machine.get('cpu_model')}, "
           f"{machine['cpu_count']} CPUs; THP {result['thp']['enabled']}; commit "
           f"{result['commit'][:12]}{' (dirty)' if result['dirty'] else ''}; load average "
           f"(1 / 5 / 15 min) {load[0]} -> {load[1]}.", "",
           "without / with: plain's time over pool's, above 1 the pool is faster: of the "
           "medians; paired: median (quartiles) of the ratio within one round-robin round "
           "(layer) or repeat (loader); best: of the fastest calls (layer) or runs (loader). "
           "pooled MB: the allocations per call or batch at or above "
           f"{memory.HUGE_BYTES // 2 ** 20} MB, the only ones the pool changes.", "",
           f"| row | unit | {head} | without / with | paired | best | pooled MB |",
           "|---|---|" + "---|" * len(variants) + "---|---|---|---|"]
    for line in result["summary"]:
        cells = " | ".join(f"{line[v][0]:.1f} ({line[v][1]:.1f}) [{line[v][2]:.1f}]"
                           if v in line else "" for v in variants)
        ratio = f"{line['ratio']:.2f}" if "ratio" in line else ""
        best = f"{line['ratio_min']:.2f}" if "ratio_min" in line else ""
        paired = ("{:.2f} ({:.2f}-{:.2f})".format(*line["ratio_paired"])
                  if "ratio_paired" in line else "")
        pooled = ", ".join(f"{s:g}" for s in line["pooled_mb"]) or "none"
        out.append(f"| {line['name']} | {line['unit']} | {cells} | {ratio} | {paired} | "
                   f"{best} | {pooled} |")
    return "\n".join(out) + "\n"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=positive_int, default=2, help="torch threads (2)")
    p.add_argument("--size", type=positive_int, default=1024, help="layer image side (1024)")
    p.add_argument("--face", type=positive_int, default=512, help="layer face size (512)")
    p.add_argument("--batches", type=positive_int, nargs="+", default=[1, 8])
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS),
                   help="allocators of the layer rows (pool plain huge)")
    p.add_argument("--repeats", type=positive_int, default=None,
                   help="timed calls per layer row (25; 5 with --quick)")
    p.add_argument("--warmup", type=int, default=3, help="untimed calls per layer row first")
    p.add_argument("--workers", type=positive_int, default=2, help="DataLoader workers (2)")
    p.add_argument("--start-methods", nargs="*", default=None,
                   choices=multiprocessing.get_all_start_methods(),
                   help="DataLoader start methods (the default one, and spawn); none: no "
                        "loader rows")
    p.add_argument("--loader-variants", nargs="+", choices=VARIANTS, default=["pool", "plain"])
    p.add_argument("--loader-sizes", type=positive_int, nargs="+", default=[512],
                   help="loader image sides S (512); face size S // 2")
    p.add_argument("--loader-batch", type=positive_int, default=8)
    p.add_argument("--loader-batches", type=positive_int, default=None,
                   help="batches timed per loader run (16; 4 with --quick)")
    p.add_argument("--loader-warmup", type=positive_int, default=2,
                   help="batches per loader run before the clock starts (worker start-up)")
    p.add_argument("--loader-repeats", type=positive_int, default=None,
                   help="loader runs per variant and start method (5; 2 with --quick)")
    p.add_argument("--no-layer", action="store_true", help="skip the layer rows")
    p.add_argument("--quick", action="store_true", help="smoke run: few repeats")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "memory.json")
    args = p.parse_args(argv)
    if args.repeats is None:
        args.repeats = 5 if args.quick else 25
    if args.loader_batches is None:
        args.loader_batches = 4 if args.quick else 16
    if args.loader_repeats is None:
        args.loader_repeats = 2 if args.quick else 5
    if args.start_methods is None:
        default = multiprocessing.get_start_method()
        args.start_methods = list(dict.fromkeys([default, "spawn"]))
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    load_start = loadavg()
    print(f"# load average at the start: {load_start}", file=sys.stderr)
    if load_start is not None and load_start[0] > 0.5:
        print(f"# warning: 1-minute load average {load_start[0]:.2f} > 0.5: timings are "
              "unreliable on a busy machine", file=sys.stderr)
    torch.set_num_threads(args.threads)
    result = run_record("memory", torch.device("cpu"), args.threads)
    result.update({"thp": thp_settings(), "huge_bytes": memory.HUGE_BYTES,
                   "pool_bytes": memory.POOL_BYTES, "seed": SEED,
                   "package": str(Path(ot.__file__).parent),
                   "patched": [f"{m.__name__}.{a}" for m, a in _bindings()],
                   "variants": {"pool": "memory.empty as shipped",
                                "plain": "torch.empty",
                                "huge": "a fresh MADV_HUGEPAGE mmap per buffer >= HUGE_BYTES, "
                                        "unmapped on free (no pool)"},
                   "timer": "layer: common.measure (time.perf_counter around single calls "
                            "after warm-up, all rows round-robin, 10 ms settle pause); loader: "
                            "wall time of the batches after the warm-up ones, one fresh "
                            "DataLoader per run, variants round-robin",
                   "loadavg_start": load_start})
    if not args.no_layer:
        result["layer"] = layer_part(args)
    memory.release()   # forked workers would inherit the layer's pooled buffers
    if args.start_methods:
        result["loader"] = loader_part(args)
    result["loadavg_end"] = loadavg()
    result["timestamp_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    result["summary"] = summary(result)
    write_json_atomic(result, args.out)
    print(markdown(result))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
