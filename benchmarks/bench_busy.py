"""Rendering on a busy machine: ``OmniProjection`` and ``cv2.remap`` while other processes hold
every core.

Users render next to other work (a training loop's main process, other jobs on a shared box).
The samplers spread a call over PyTorch's intra-op threads; a thread that the system has
descheduled then delays the whole call, and for small images waking a thread at all costs more
than the work. This benchmark starts ``--spinners`` processes (default: one per core) that spin
at normal priority, and times, round-robin in one run, on ``--threads`` threads (default 2):

* ``ours``: ``layer(cube, channels_last=True)``, a ``uint8`` channels-last cube ``(1, 6, F, F,
  3)`` into a ``2F x 2F`` equidistant fisheye of 190 degrees (cached grid);
* ``peer``: ``cv2.remap`` of the padded ``uint8`` HWC atlas with OpenCV's fixed-point maps
  (``cv2.convertMaps`` to ``CV_16SC2``, built once), ``cv2.setNumThreads(--threads)``;

for face sizes ``--faces`` (default 64, 256 and 512: 128 x 128, 512 x 512 and 1024 x 1024
images), first quiet (no spinners), then busy. Reported per size: the medians, ``ours / peer``
in each state, and how much slower each got (``busy / quiet``). Only the spinners are started
by this script: other load on the machine is recorded (``loadavg``) but not controlled.

    python benchmarks/bench_busy.py            # results/busy.json
    python benchmarks/bench_busy.py --quick    # 64 only, few repeats
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_projection import remap_maps  # noqa: E402
from common import (begin_run, loadavg, measure, results_path, run_main,  # noqa: E402
                    run_record)

import omniscape_torch as ot  # noqa: E402
from omniscape_torch import cubemap as cm  # noqa: E402

FOV = math.radians(190)
SEED = 16


def spin(stop) -> None:
    """A process that keeps one core busy until ``stop`` is set."""
    x = 0
    while not stop.is_set():
        for _ in range(100000):
            x += 1


def cases(face: int, cv2) -> list[tuple[str, callable]]:
    size = 2 * face
    focal, centre = size / FOV, (size - 1) / 2
    camera = ot.Camera("equidistant", torch.tensor([focal, focal, centre, centre]),
                       (size, size), fov=FOV)
    layer = ot.OmniProjection(camera, face)
    gen = torch.Generator().manual_seed(SEED)
    cube = torch.rand(1, 6, 3, face, face, generator=gen)
    cube_u8 = (cube * 255).round().to(torch.uint8)
    hwc = cube_u8.permute(0, 1, 3, 4, 2).contiguous()
    grid = layer.sampling_grid()[0][0]
    atlas = cm.cubemap_to_atlas(cube, layer.pad, "bilinear")[0]
    atlas_u8 = np.ascontiguousarray((atlas.permute(1, 2, 0).numpy() * 255).round()
                                    .astype(np.uint8))
    map1, map2 = cv2.convertMaps(*remap_maps(grid, atlas_u8.shape[:2]), cv2.CV_16SC2)
    with torch.no_grad():
        layer(hwc, channels_last=True)   # the lookup table, built once
    return [("ours", lambda: layer(hwc, channels_last=True)),
            ("peer", lambda: cv2.remap(atlas_u8, map1, map2, cv2.INTER_LINEAR,
                                       borderMode=cv2.BORDER_CONSTANT))]


def run(args: argparse.Namespace) -> dict:
    import cv2

    load_start = begin_run(args.threads, cv2)
    rows = []
    state = {"quiet": None, "busy": None}
    ctx = mp.get_context("spawn")
    for label in ("quiet", "busy"):
        stop = ctx.Event()
        spinners = [ctx.Process(target=spin, args=(stop,), daemon=True)
                    for _ in range(args.spinners if label == "busy" else 0)]
        for p in spinners:
            p.start()
        time.sleep(0.5 if spinners else 0)   # the spinners on their cores
        state[label] = loadavg()
        try:
            for face in args.faces:
                named = cases(face, cv2)
                with torch.no_grad():
                    stats = measure([fn for _, fn in named], args.repeats, args.warmup)
                for (name, _), stat in zip(named, stats):
                    rows.append({"state": label, "face": face, "image": 2 * face, "name": name,
                                 **stat})
        finally:
            stop.set()
            for p in spinners:
                p.join(5)
                if p.is_alive():
                    p.terminate()
    summary = []
    for face in args.faces:
        med = {(r["state"], r["name"]): r["median_s"] for r in rows if r["face"] == face}
        summary.append({
            "image": 2 * face,
            **{f"{s}_{n}_ms": med[s, n] * 1e3 for s in ("quiet", "busy") for n in ("ours", "peer")},
            "quiet_ratio": med["quiet", "ours"] / med["quiet", "peer"],
            "busy_ratio": med["busy", "ours"] / med["busy", "peer"],
            "ours_slowdown": med["busy", "ours"] / med["quiet", "ours"],
            "peer_slowdown": med["busy", "peer"] / med["quiet", "peer"],
        })
    return {**run_record("busy", torch.device("cpu"), args.threads, cv2),
            "spinners": args.spinners, "repeats": args.repeats, "warmup": args.warmup,
            "loadavg_start": load_start, "loadavg_states": state, "loadavg_end": loadavg(),
            "rows": rows, "summary": summary}


def markdown(result: dict) -> str:
    lines = [f"Busy machine: {result['spinners']} spinning processes, {result['threads']} "
             f"threads, uint8 channels-last, cached grid (medians, ms)", "",
             "| image | quiet ours | quiet cv2 | quiet ratio | busy ours | busy cv2 | busy ratio "
             "| ours busy/quiet | cv2 busy/quiet |", "|---|---|---|---|---|---|---|---|---|"]
    for s in result["summary"]:
        lines.append(f"| {s['image']} | {s['quiet_ours_ms']:.2f} | {s['quiet_peer_ms']:.2f} | "
                     f"{s['quiet_ratio']:.2f} | {s['busy_ours_ms']:.2f} | "
                     f"{s['busy_peer_ms']:.2f} | {s['busy_ratio']:.2f} | "
                     f"{s['ours_slowdown']:.1f}x | {s['peer_slowdown']:.1f}x |")
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--faces", type=int, nargs="+", default=None,
                        help="face sizes (default 64 256 512; 64 with --quick)")
    parser.add_argument("--threads", type=int, default=2, help="torch and OpenCV threads")
    parser.add_argument("--spinners", type=int, default=os.cpu_count() or 2,
                        help="busy processes (default: one per core)")
    parser.add_argument("--repeats", type=int, default=None, help="default 30; 5 with --quick")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", type=Path,
                        default=None)
    args = parser.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("busy.json", quick=args.quick)
    args.faces = args.faces or ([64] if args.quick else [64, 256, 512])
    args.repeats = args.repeats or (5 if args.quick else 30)
    if min(args.faces) < 8 or args.threads < 1 or args.spinners < 0 or args.repeats < 1:
        parser.error("--faces >= 8, --threads >= 1, --spinners >= 0 and --repeats >= 1")
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
