"""Where the time of ``omniscape-torch generate`` goes: a stage breakdown of one run.

Runs :func:`omniscape_torch.data.generate.generate` (what the command runs) on a fresh folder
with the stages' functions wrapped in timers, and writes the breakdown as JSON: the wall time,
and per stage the CPU time of the threads in it (``time.thread_time``; each thread's time goes
to the innermost stage it is in, so nested stages are not counted twice, and a thread waiting
for others costs nothing; summed over the threads, so the stages add up to the process's CPU
time, up to twice the wall time on 2 cores when threads trace, shade and encode at once).
Stages:

* ``casting``: tracing the rays through the scene (the torch caster's ``Town._closest`` and
  its tile culling, or Embree's queries, ``omniscape_torch.scenes.mesh.MeshScene.intersect``
  and ``occluded``);
* ``shading``: ``Town._shade`` (labels, colour, light, fog, sky) less the shadow rays it casts
  (``casting``);
* ``cubemap (rest)``: the rest of ``Town.render_cubemap`` (rays, tiles, assembling the faces);
* ``projection``: ``OmniProjection.render`` (the cubemap -> camera layer);
* ``png encode``: ``omniscape_torch.io.images.encode_image`` (Pillow); ``exr encode + write``:
  ``write_exr``;
* ``write``: ``atomic_write_bytes`` / ``atomic_write_text`` (temporary file + rename);
* ``scene build``: Embree's scene of the meshes at a frame's time (``Town.scene``; Embree's
  own build threads count in ``other``); ``texels in view``: the texels each camera reads
  (``_Plan.texels``, ``FrameRenderer.texels``); ``image conversion``: the images to bytes'
  types before encoding (``_to_uint8``, ``_write_labels`` less its encoding and writing) and the labels
  packed with the instance ids before the layer (``pack_instances``);
* per run: ``town build`` (``Town.__init__``), ``face sizes``, ``calibration files`` (the
  OCamCalib polynomial fit, and the faces of every frame), ``contact sheet``;
* ``other``: the process's CPU time not inside any stage (and the threads torch and OpenCV
  run on their own).

One-time builds (the fast sampler's C++ extension, the town's C shading: once per machine and
source) are done before the clock starts.

Usage::

    python benchmarks/profile_generate.py --label after              # 1024 x 1024, 2 frames
    python benchmarks/profile_generate.py --image-size 256 --frames 8 --label default

Results: ``benchmarks/results/profile_generate.json`` (``--out``), one entry per ``--label``
(a rerun with the same label replaces it; the other labels are kept), with the commit, the
machine, its load at the start and end, the wall and CPU time of the run, each frame's wall
time (``frame_walls_s``; the first carries the per-camera set-up: rays, layers, cones) and
per stage the CPU seconds per run and per frame.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import begin_run, loadavg, run_record, write_json_atomic  # noqa: E402

#: (stage, module, attribute path): the functions timed. Missing ones are skipped, so the same
#: script profiles the engine before and after a change.
TARGETS = [
    ("casting", "omniscape_torch.scenes.town", "Town._closest"),
    ("casting", "omniscape_torch.scenes.town", "Town._trace"),
    ("casting", "omniscape_torch.scenes.town", "Town._tile_candidates"),
    ("casting", "omniscape_torch.scenes.mesh", "MeshScene.intersect"),
    ("casting", "omniscape_torch.scenes.mesh", "MeshScene.occluded"),
    ("shading", "omniscape_torch.scenes.town", "Town._shade"),
    ("cubemap (rest)", "omniscape_torch.scenes.town", "Town.render_cubemap"),
    ("projection", "omniscape_torch.render.layer", "OmniProjection.render"),
    ("png encode", "omniscape_torch.io.images", "encode_image"),
    ("exr encode + write", "omniscape_torch.io.exr", "write_exr"),
    ("exr encode + write", "omniscape_torch.io", "write_exr"),
    ("exr encode + write", "omniscape_torch.data.generate", "write_exr"),
    ("write", "omniscape_torch.io.atomic", "atomic_write_bytes"),
    ("write", "omniscape_torch.io.atomic", "atomic_write_text"),
    ("write", "omniscape_torch.io.images", "atomic_write_bytes"),
    ("write", "omniscape_torch.data.generate", "atomic_write_text"),
    ("write", "omniscape_torch.data.generate", "atomic_write_bytes"),
    ("scene build", "omniscape_torch.scenes.town", "Town.scene"),
    ("texels in view", "omniscape_torch.data.generate", "_Plan.texels"),
    ("texels in view", "omniscape_torch.data.generate", "FrameRenderer.texels"),
    ("image conversion", "omniscape_torch.data.generate", "pack_instances"),
    ("image conversion", "omniscape_torch.data.generate", "_write_labels"),
    ("image conversion", "omniscape_torch.data.generate", "_to_uint8"),
    ("town build", "omniscape_torch.scenes.town", "Town.__init__"),
    ("face sizes", "omniscape_torch.data.generate", "_face_sizes"),
    ("calibration files", "omniscape_torch.data.generate", "_write_run_files"),
    ("contact sheet", "omniscape_torch.data.generate", "contact_sheet"),
]

PER_RUN = ("town build", "face sizes", "calibration files", "contact sheet")


class StageTimer:
    """Exclusive CPU time per stage, per thread: a thread's CPU clock is charged to the
    innermost stage it is in (a stack per thread), and the threads' sums are added; the wall
    clock likewise (``walls``: meaningful for the stages that run alone on the main thread, the
    per-run ones)."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = {}
        self.walls: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._local = threading.local()
        self._lock = threading.Lock()

    def _charge(self) -> None:
        now, wall = time.thread_time(), time.perf_counter()
        stack = self._local.__dict__.setdefault("stack", [])
        last, last_wall = self._local.__dict__.get("last", (now, wall))
        if stack:
            with self._lock:
                self.totals[stack[-1]] = self.totals.get(stack[-1], 0.0) + now - last
                self.walls[stack[-1]] = self.walls.get(stack[-1], 0.0) + wall - last_wall
        self._local.last = (now, wall)

    def wrap(self, stage: str, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            self._charge()
            stack = self._local.__dict__.setdefault("stack", [])
            stack.append(stage)
            with self._lock:
                self.calls[stage] = self.calls.get(stage, 0) + 1
            try:
                return fn(*args, **kwargs)
            finally:
                self._charge()
                stack.pop()
        timed.__wrapped_stage__ = stage
        return timed


def install(timer: StageTimer) -> list[tuple[object, str, object]]:
    """Wrap every target that exists; returns what to restore."""
    undo, seen = [], set()
    for stage, module, attr in TARGETS:
        try:
            obj = importlib.import_module(module)
        except ImportError:
            continue
        *path, name = attr.split(".")
        for p in path:
            obj = getattr(obj, p, None)
        fn = getattr(obj, name, None) if obj is not None else None
        if fn is None or getattr(fn, "__wrapped_stage__", None) or (id(obj), name) in seen:
            continue
        seen.add((id(obj), name))
        try:
            setattr(obj, name, timer.wrap(stage, fn))
        except (TypeError, AttributeError):  # a C type's attribute
            continue
        undo.append((obj, name, fn))
    return undo


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--image-size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    ap.add_argument("--label", required=True, help="key of this run in the JSON "
                    "(e.g. before, after)")
    ap.add_argument("--town", type=int, default=None, help="DatasetConfig.town, where it exists")
    ap.add_argument("--weather", default="clear_noon")
    ap.add_argument("--keep", type=Path, default=None, help="write the dataset here (kept) "
                    "instead of a temporary folder")
    ap.add_argument("--out", type=Path,
                    default=ROOT / "benchmarks" / "results" / "profile_generate.json")
    args = ap.parse_args(argv)
    load_start = begin_run(args.threads)

    import torch
    from omniscape_torch.data import generate as gen

    # one-time builds, once per machine and source, are not a frame's: the C++ extension (the
    # fast sampler's and the town's kernels, one library) is built (or found built) before the
    # clock starts
    try:
        from omniscape_torch.render.kernels import build as extension
        extension.load()
    except Exception as err:  # noqa: BLE001 - the layer and the town fall back to torch
        print(f"# the C++ kernels are not available ({err})", file=sys.stderr)

    timer = StageTimer()
    undo = install(timer)
    # each frame's wall time (FrameRenderer.render, on the main thread)
    frame_walls: list[float] = []
    render = gen.FrameRenderer.render

    def timed_render(self, out, k):
        start = time.perf_counter()
        try:
            return render(self, out, k)
        finally:
            frame_walls.append(time.perf_counter() - start)
    gen.FrameRenderer.render = timed_render
    undo.append((gen.FrameRenderer, "render", render))
    extra = {} if args.town is None else {"town": args.town}
    config = gen.DatasetConfig(frames=args.frames, image_size=(args.image_size,) * 2,
                               weather=tuple(args.weather.split(",")), **extra)
    folder = args.keep or Path(tempfile.mkdtemp(prefix="profile_generate_"))
    start = time.perf_counter()
    cpu_start = time.process_time()   # all the process's threads
    result = gen.generate(folder, config, progress=True)
    wall = time.perf_counter() - start
    cpu = time.process_time() - cpu_start
    for obj, name, fn in undo:
        setattr(obj, name, fn)
    if args.keep is None:
        import shutil
        shutil.rmtree(folder, ignore_errors=True)

    stages = dict(timer.totals)
    inside = sum(stages.values())
    frames = len(result["rendered"])
    per_run = {k: stages.pop(k) for k in PER_RUN if k in stages}
    per_run_wall = {k: timer.walls[k] for k in per_run}
    frame_wall = wall - sum(per_run_wall.values())
    record = {
        **run_record("profile_generate", torch.device("cpu"), args.threads),
        "load_start": load_start, "load_end": loadavg(),
        "config": config.to_dict(), "face_sizes": result["face_sizes"], "frames": frames,
        "wall_s": wall, "process_cpu_s": cpu,
        "frame_wall_s": frame_wall / max(frames, 1),
        "frame_walls_s": frame_walls,
        "steady_frame_wall_s": (sorted(frame_walls[1:])[len(frame_walls[1:]) // 2]
                                if len(frame_walls) > 1 else None),
        "per_run_s": per_run,
        "per_run_wall_s": per_run_wall,
        "per_frame_s": {k: v / max(frames, 1) for k, v in sorted(stages.items())},
        "other_per_frame_s": max(cpu - inside, 0.0) / max(frames, 1),
        "calls": timer.calls,
    }
    try:
        data = json.loads(args.out.read_text())
    except (OSError, ValueError):
        data = {}
    data[args.label] = record
    write_json_atomic(data, args.out)
    steady = record["steady_frame_wall_s"]
    print(f"{args.label}: {frames} frame(s) of {args.image_size} px, wall {wall:.1f} s, CPU "
          f"{cpu:.1f} s ({record['frame_wall_s']:.2f} s/frame after the per-run stages"
          + ("" if steady is None else f"; {steady:.2f} s a frame after the first") +
          f"), load {load_start} -> {record['load_end']}")
    print("  (stages: CPU seconds, all threads)")
    for k, v in per_run.items():
        print(f"  per run   {k:<20} {v:8.2f} s (wall {per_run_wall[k]:.2f} s)")
    for k, v in record["per_frame_s"].items():
        print(f"  per frame {k:<20} {v:8.2f} s")
    print(f"  per frame {'other':<20} {record['other_per_frame_s']:8.2f} s")
    return record


if __name__ == "__main__":
    main()
