"""Generating past one process: ``generate`` on Ray with 1 and 2 workers against ``--workers 1``.

Issue 21's scaling run, on this machine. Each timed run renders every frame of the dataset
again (the ``.done`` markers removed; the per-run files kept, so no polynomial is refitted) and
rewrites the contact sheet, as a run of the command would. Rows, timed round-robin (every row
once per round, ``--rounds`` rounds; medians):

* ``local_1``: ``generate(workers=1)``, in this process (torch on ``--threads`` threads, as the
  command runs): the peer every ratio is against;
* ``local_2``: ``generate(workers=2)``, the process pool of one machine (its workers start
  with each run: spawned, they import torch and the package);
* ``ray_1``, ``ray_2``: ``generate(ray=True)`` on a local Ray cluster of 1 and 2 CPUs (one
  task per CPU at a time, one torch thread each), started before the row's timing and warmed
  (its workers have imported the package and built a renderer once), so that the figure is
  that of a cluster that is up, as one is for a campaign; the cluster's start and the cold
  first task are reported apart.

Per-task overhead, on the warm 2-CPU cluster: the round trip of a task that does nothing
(Ray's dispatch), and of ``render_task`` with no frame (what every chunk pays before its first
frame: Ray's dispatch and building the renderer: the ride, the face sizes, the town).

What limits scaling past one node, measured where it can be on one machine:

* the driver's serial work per run (the manifest, the plan, the per-run files, listing what is
  finished: a rerun with every frame finished, timed in every round, the fastest kept; and the
  contact sheet at the end): Amdahl's bound on the speed-up is ``run time / serial time``;
* the bytes written per frame (every file of a frame; and in WebDataset shards, which hold
  them again): ``frames/s x bytes per frame`` is the bandwidth the shared output storage must
  take from all nodes at once.

Usage::

    python benchmarks/bench_scaling.py              # 16 frames of 4 cameras at 256 x 256, 3 rounds
    python benchmarks/bench_scaling.py --quick      # seconds: 4 frames at 32 x 32, 1 round

Results: a markdown table on stdout and JSON (``--out``, default
``benchmarks/results/scaling.json``, written atomically).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (begin_run, loadavg, positive_int, results_path, run_main,  # noqa: E402
                    run_record)
from omniscape_torch.data import format as fmt  # noqa: E402
from omniscape_torch.data.generate import (  # noqa: E402
    DatasetConfig, FrameRenderer, contact_sheet, generate, render_task)
from omniscape_torch.data.shards import write_shard  # noqa: E402

ROWS = ("local_1", "local_2", "ray_1", "ray_2")
PEER = "local_1"


def _noop() -> None:
    return None


def _fresh(out: Path) -> None:
    """Every frame unfinished again (the markers gone; the per-run files kept)."""
    shutil.rmtree(out / fmt.DONE, ignore_errors=True)


def _start_cluster(ray, cpus: int, config: DatasetConfig, out: Path) -> dict:
    """A local cluster of ``cpus`` CPUs, warmed: returns its start time and the time of its
    cold first round of tasks (each worker imports the package and builds a renderer)."""
    start = time.perf_counter()
    ray.init(address="local", num_cpus=cpus, include_dashboard=False,
             object_store_memory=100 * 2 ** 20,
             logging_level="WARNING")
    started = time.perf_counter() - start
    task = ray.remote(render_task).options(num_cpus=1)
    start = time.perf_counter()
    ray.get([task.remote(config, str(out), None, []) for _ in range(2 * cpus)])
    return {"start_s": started, "cold_first_tasks_s": time.perf_counter() - start}


def _first_frames(config: DatasetConfig) -> dict:
    """In a worker, what a task pays before its frames run at their steady pace: building the
    renderer, and its first frame's extra time (the camera layers, the town's caches) over the
    same frame rendered again."""
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        renderer = FrameRenderer(config)
        build = time.perf_counter() - start
        start = time.perf_counter()
        renderer.render(tmp, 0)
        first = time.perf_counter() - start
        start = time.perf_counter()
        renderer.render(tmp, 0)
        again = time.perf_counter() - start
    return {"renderer_build_s": build, "first_frame_s": first, "steady_frame_s": again,
            "task_startup_s": build + first - again}


def _overhead(ray, config: DatasetConfig, out: Path, repeats: int) -> dict:
    """Median round trip of a no-op task (Ray's dispatch), of ``render_task`` with no frame,
    and a task's start-up in the renderer (:func:`_first_frames`)."""
    noop = ray.remote(_noop).options(num_cpus=1)
    task = ray.remote(render_task).options(num_cpus=1)
    first = ray.remote(_first_frames).options(num_cpus=1)
    ray.get([noop.remote() for _ in range(4)])
    times: dict[str, list[float]] = {"noop_task_s": [], "renderer_task_s": []}
    for _ in range(repeats):
        start = time.perf_counter()
        ray.get(noop.remote())
        times["noop_task_s"].append(time.perf_counter() - start)
    for _ in range(max(3, repeats // 6)):
        start = time.perf_counter()
        ray.get(task.remote(config, str(out), None, []))
        times["renderer_task_s"].append(time.perf_counter() - start)
    starts = [ray.get(first.remote(config)) for _ in range(3)]
    medians = {k: float(np.median([s[k] for s in starts])) for k in starts[0]}
    return {k: float(np.median(v)) for k, v in times.items()} | medians | {
        "times": times, "first_frames": starts}


def _bytes_per_frame(out: Path, config: DatasetConfig) -> dict:
    plan = FrameRenderer(config).plan
    per_frame = [sum((out / f).stat().st_size for f in plan.files(k)) for k in
                 range(config.frames)]
    shard = write_shard(out, 0, [0], config.cameras)
    shard_bytes = shard.stat().st_size
    shard.unlink()
    return {"bytes_per_frame": float(np.mean(per_frame)), "shard_bytes_per_frame": shard_bytes}


def run(args: argparse.Namespace) -> dict:
    import ray

    load_start = begin_run(args.threads)
    config = DatasetConfig(frames=args.frames, image_size=(args.size, args.size),
                           max_face_size=args.max_face_size, seed=0)
    work = Path(tempfile.mkdtemp(prefix="bench-scaling-"))
    out = work / "data"
    try:
        start = time.perf_counter()
        generate(out, config, progress=False)                 # the per-run files, fitted once
        first_run_s = time.perf_counter() - start
        start = time.perf_counter()
        contact_sheet(out, config.cameras, config.frames // 2)
        sheet_s = time.perf_counter() - start
        sizes = _bytes_per_frame(out, config)

        times: dict[str, list[float]] = {row: [] for row in ROWS}
        reruns: list[float] = []
        clusters: dict[str, list[dict]] = {"ray_1": [], "ray_2": []}
        overhead = None
        from tqdm import tqdm
        for _ in tqdm(range(args.rounds), desc="rounds", unit="round", file=sys.stderr):
            for row in ROWS:
                _fresh(out)
                if row.startswith("ray"):
                    cpus = int(row[-1])
                    clusters[row].append(_start_cluster(ray, cpus, config, out))
                    try:
                        start = time.perf_counter()
                        generate(out, config, ray=True, progress=False)
                        times[row].append(time.perf_counter() - start)
                        if cpus == 2 and overhead is None:
                            overhead = _overhead(ray, config, out, args.overhead_repeats)
                    finally:
                        ray.shutdown()
                else:
                    start = time.perf_counter()
                    generate(out, config, workers=int(row[-1]), progress=False)
                    times[row].append(time.perf_counter() - start)
            start = time.perf_counter()
            generate(out, config, progress=False)             # nothing left: the serial part
            reruns.append(time.perf_counter() - start)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    rows = []
    for row in ROWS:
        median = float(np.median(times[row]))
        rows.append({"row": row, "median_s": median, "min_s": float(min(times[row])),
                     "times_s": times[row], "frames_per_s": config.frames / median,
                     "frames_per_s_best": config.frames / float(min(times[row]))})
    by = {r["row"]: r for r in rows}
    ratios = [{"row": r["row"], "peer": PEER,
               "ratio": r["frames_per_s"] / by[PEER]["frames_per_s"],
               "ratio_best": r["frames_per_s_best"] / by[PEER]["frames_per_s_best"]}
              for r in rows if r["row"] != PEER]
    # the fastest rerun: a load spike of a busy machine inflates the others
    serial_rerun_s = float(min(reruns))
    serial_s = serial_rerun_s + sheet_s
    record = run_record("scaling", torch.device("cpu"), args.threads)
    record["versions"]["ray"] = ray.__version__
    record.update({
        "setup": {"frames": config.frames, "image_size": list(config.image_size),
                  "cameras": list(config.cameras), "max_face_size": config.max_face_size,
                  "rounds": args.rounds},
        "loadavg_start": load_start, "loadavg_end": loadavg(), "rows": rows, "ratios": ratios,
        "clusters": {k: {"start_s": float(np.median([c["start_s"] for c in v])),
                         "cold_first_tasks_s": float(np.median([c["cold_first_tasks_s"]
                                                                for c in v])),
                         "all": v} for k, v in clusters.items()},
        "per_task": overhead,
        "serial": {"first_run_s": first_run_s, "rerun_nothing_left_fastest_s": serial_rerun_s,
                   "rerun_nothing_left_all_s": reruns,
                   "contact_sheet_s": sheet_s, "serial_s": serial_s,
                   "amdahl_max_speedup": by[PEER]["median_s"] / serial_s},
        "storage": sizes | {"MB_per_s_at_local_1": sizes["bytes_per_frame"]
                            * by[PEER]["frames_per_s"] / 1e6}})
    return record


def markdown(result: dict) -> str:
    s = result["setup"]
    lines = [f"generate, {s['frames']} frames of {len(s['cameras'])} cameras at "
             f"{s['image_size'][0]} x {s['image_size'][1]}, medians of {s['rounds']} rounds; "
             f"load {result['loadavg_start']} -> {result['loadavg_end']}", "",
             "| row | run s | frames/s | vs local_1 | vs local_1 (fastest runs) |",
             "|---|---|---|---|---|"]
    ratios = {q["row"]: q for q in result["ratios"]}
    for r in result["rows"]:
        q = ratios.get(r["row"])
        lines.append(f"| {r['row']} | {r['median_s']:.2f} | {r['frames_per_s']:.3f} | "
                     + (f"{q['ratio']:.2f} | {q['ratio_best']:.2f} |" if q else "1 | 1 |"))
    t, c, sr, st = result["per_task"], result["clusters"], result["serial"], result["storage"]
    lines += ["", f"per task: no-op {1e3 * t['noop_task_s']:.1f} ms, renderer build "
              f"{t['renderer_task_s']:.2f} s, start-up in all (build + first frame's extra) "
              f"{t['task_startup_s']:.2f} s against {t['steady_frame_s']:.2f} s per frame "
              f"(one thread); cluster start {c['ray_2']['start_s']:.1f} s, "
              f"cold first tasks {c['ray_2']['cold_first_tasks_s']:.1f} s (2 CPUs)",
              f"serial (driver) {sr['serial_s']:.2f} s per run (Amdahl: at most "
              f"{sr['amdahl_max_speedup']:.0f}x over local_1); {st['bytes_per_frame'] / 1e6:.2f} "
              f"MB per frame ({st['shard_bytes_per_frame'] / 1e6:.2f} MB in a shard)"]
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=positive_int, default=16)
    p.add_argument("--size", type=positive_int, default=256, help="image size (square)")
    p.add_argument("--max-face-size", type=positive_int, default=1024)
    p.add_argument("--rounds", type=positive_int, default=3)
    p.add_argument("--overhead-repeats", type=positive_int, default=30)
    p.add_argument("--threads", type=positive_int, default=2,
                   help="torch threads of this process (local_1 renders on them)")
    p.add_argument("--quick", action="store_true", help="4 frames at 32 x 32, 1 round")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("scaling.json", quick=args.quick)
    if args.quick:
        args.frames, args.size, args.rounds, args.overhead_repeats = 4, 32, 1, 6
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
