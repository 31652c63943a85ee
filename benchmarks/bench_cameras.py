"""Throughput of every camera model's ``project`` and ``unproject``, with OpenCV as the peer.

For each model of ``ot.cameras.MODELS`` the benchmark draws points (or pixels) from a seeded
generator over the model's valid domain, with realistic parameters, and times the pure functions
``get_model(name).project(points (N, 3), params (P,))`` and ``.unproject(pixels (N, 2), params)``.
OpenCV is timed in the same run on the same data, so the headline figures are ratios:

* ``kannala_brandt`` project vs ``cv2.fisheye.projectPoints`` (float32 and float64 input) and vs
  ``cv2.fisheye.distortPoints`` on ``(x/z, y/z)`` (the numpy division included): from Python,
  ``projectPoints`` always computes its 2N x 15 Jacobian (the binding allocates every output),
  ``distortPoints`` is the Jacobian-free path;
* ``unified`` project vs ``cv2.omnidir.projectPoints`` (float32 and float64; always computes its
  2N x 16 Jacobian from Python, and has no Jacobian-free equivalent);
* unproject, for information: ``kannala_brandt`` vs ``cv2.fisheye.undistortPoints`` and
  ``unified`` vs ``cv2.omnidir.undistortPoints``. These return normalised plane coordinates, not
  unit rays, and stop after a fixed iteration count; ours return unit rays and a validity mask.

Timing: ``--warmup`` untimed calls, then ``--repeats`` timed calls of one full evaluation each
(``time.perf_counter``; ``torch.cuda.synchronize`` before and after on CUDA); the median and the
inter-quartile range are reported: ``torch.utils.benchmark.Timer.timeit(1)`` repeated, with a
fixed repeat count, the same thread setting applied to torch and OpenCV, and the calls of one
model (ours and its peers) timed round-robin so that a change of load hits both sides of a
ratio alike.

Usage::

    python benchmarks/bench_cameras.py             # 1M points, 2 threads, float32
    python benchmarks/bench_cameras.py --quick     # 100k points, a few repeats: seconds
    python benchmarks/bench_cameras.py --threads 1 --out benchmarks/results/cameras_t1.json

Results: a markdown table on stdout and JSON (``--out``, default
``benchmarks/results/cameras.json``, written atomically) with the machine, versions, commit,
thread count, dtype and one row per measurement.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
# Benchmark the checkout this script lives in, not whatever copy is installed.
sys.path.insert(0, str(ROOT))

import omniscape_torch as ot  # noqa: E402
from common import loadavg, measure, results_path, run_main, run_record  # noqa: E402
from omniscape_torch.cameras.scaramuzza import scaramuzza_project  # noqa: E402

try:
    import cv2
except ImportError:  # the OpenCV peers are skipped, our rows still run
    cv2 = None

OCAM_FILE = ROOT.parent / "shared" / "data" / "ocamcalib_real" / "calib_results_0.txt"
SEED = 20240601
FISHEYE_ANGLE = math.radians(80.0)

#: Realistic parameters per model (float64; cast to the benchmark dtype), and the half-angle of
#: the cone of directions that is sampled (clipped to 98% of the model's ``max_angle``).
#: scaramuzza's come from OCAM_FILE.
SPECS: dict[str, dict] = {
    # A 1280 x 960 rectified view, 60 degrees off axis (120 degree diagonal cone).
    "pinhole": dict(params=[600.0, 600.0, 639.5, 479.5], angle=math.radians(60.0)),
    # 1280 x 960 fisheyes with f = 300 px: an 80 degree ray lands 386-503 px from the centre.
    "equidistant": dict(params=[300.0, 300.0, 639.5, 479.5], angle=FISHEYE_ANGLE),
    "equisolid": dict(params=[300.0, 300.0, 639.5, 479.5], angle=FISHEYE_ANGLE),
    "stereographic": dict(params=[300.0, 300.0, 639.5, 479.5], angle=FISHEYE_ANGLE),
    "orthographic": dict(params=[300.0, 300.0, 639.5, 479.5], angle=FISHEYE_ANGLE),
    # Typical of an 848 x 800 tracking fisheye calibrated with cv2.fisheye (T265-like).
    "kannala_brandt": dict(params=[284.9, 286.1, 425.9, 398.1, -0.0073, 0.0435, -0.0412, 0.0076],
                           angle=FISHEYE_ANGLE),
    # A 1280 x 960 fisheye calibrated with cv2.omnidir (Mei): xi > 1, mild radial-tangential.
    "unified": dict(params=[710.0, 705.0, 639.5, 479.5, 1.2, -0.1, 0.02, 1e-4, -2e-4],
                    angle=FISHEYE_ANGLE),
    # Representative of the 512 x 512 TUM VI fisheyes (the magnitudes Usenko et al. 2018 fit).
    "eucm": dict(params=[191.0, 190.6, 254.9, 256.9, 0.63, 1.04], angle=FISHEYE_ANGLE),
    "double_sphere": dict(params=[158.3, 158.3, 254.9, 256.9, -0.18, 0.59], angle=FISHEYE_ANGLE),
    "scaramuzza": dict(params=None, angle=FISHEYE_ANGLE),
    # A 2048 x 1024 full panorama; every direction.
    "equirectangular": dict(params=[2048 / (2 * math.pi), 1024 / math.pi, 1023.5, 511.5],
                            angle=math.pi),
}


# --------------------------------------------------------------------------------------------
# Environment
# --------------------------------------------------------------------------------------------

# --------------------------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------------------------

# --------------------------------------------------------------------------------------------
# Data: seeded, over each model's valid domain
# --------------------------------------------------------------------------------------------

def directions_in_cone(n: int, angle: float, gen: torch.Generator) -> torch.Tensor:
    """``(n, 3)`` float64 unit vectors uniform over the cap of half-angle ``angle`` around +z."""
    cos_t = 1 - torch.rand(n, generator=gen, dtype=torch.float64) * (1 - math.cos(angle))
    sin_t = torch.sqrt((1 - cos_t * cos_t).clamp(min=0))
    phi = torch.rand(n, generator=gen, dtype=torch.float64) * (2 * math.pi)
    return torch.stack((sin_t * torch.cos(phi), sin_t * torch.sin(phi), cos_t), dim=-1)


def pixels_in_circle(model, params64: torch.Tensor, angle: float, n: int,
                     gen: torch.Generator) -> torch.Tensor:
    """``(n, 2)`` float64 pixels uniform over the largest disk around the image of the optical
    axis that stays inside the image of the cone of half-angle ``angle``."""
    if model.name == "equirectangular":
        fx, fy, cx, cy = params64.tolist()
        u = cx + fx * math.pi * (2 * torch.rand(n, generator=gen, dtype=torch.float64) - 1)
        v = cy + fy * (math.pi / 2) * (2 * torch.rand(n, generator=gen, dtype=torch.float64) - 1)
        return torch.stack((u, v), dim=-1)
    phi = torch.linspace(0, 2 * math.pi, 721, dtype=torch.float64)[:-1]
    ring = torch.stack((math.sin(angle) * torch.cos(phi), math.sin(angle) * torch.sin(phi),
                        torch.full_like(phi, math.cos(angle))), dim=-1)
    axis = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    ring_px, ring_ok = model.project(ring, params64)
    centre, _ = model.project(axis, params64)
    assert bool(ring_ok.all()), f"{model.name}: the sampled cone leaves the model's domain"
    radius = float((ring_px - centre).norm(dim=-1).min()) * 0.999
    r = radius * torch.sqrt(torch.rand(n, generator=gen, dtype=torch.float64))
    phi = torch.rand(n, generator=gen, dtype=torch.float64) * (2 * math.pi)
    return centre + torch.stack((r * torch.cos(phi), r * torch.sin(phi)), dim=-1)


def model_params(name: str) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(float64 params, OCamCalib invpol or None)."""
    if name == "scaramuzza":
        camera = ot.Camera.from_ocamcalib(OCAM_FILE)
        return camera.params.detach().double(), camera.invpol.double()
    return torch.tensor(SPECS[name]["params"], dtype=torch.float64), None


# --------------------------------------------------------------------------------------------
# The benchmark
# --------------------------------------------------------------------------------------------

def to_numpy(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy())


def run(args: argparse.Namespace) -> dict:
    device = torch.device(args.device)
    cpu = torch.device("cpu")
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    torch.set_num_threads(args.threads)
    if cv2 is not None:
        cv2.setNumThreads(args.threads)
    n, repeats, warmup = args.points, args.repeats, args.warmup
    load_start = loadavg()
    if load_start is not None and load_start[0] > 0.5:
        print(f"# warning: load average {load_start[0]:.2f} before the run; with {args.threads} "
              f"threads on {os.cpu_count()} cores, other processes distort the timings",
              file=sys.stderr, flush=True)
    rows: list[dict] = []
    ratios: list[dict] = []

    def row(model: str, op: str, impl: str, in_dtype: str, dev: torch.device, **extra) -> dict:
        return {"model": model, "op": op, "impl": impl, "input_dtype": in_dtype,
                "device": str(dev), "points": n, "repeats": repeats, "warmup": warmup,
                "median_s": None, "iqr_s": None, "min_s": None, "points_per_s": None,
                "valid_fraction": None, "max_abs_diff_px_vs_ours": None, "note": "", **extra}

    def error_row(model: str, op: str, impl: str, err: Exception) -> dict:
        text = str(err).strip()
        msg = f"{type(err).__name__}: {text.splitlines()[0] if text else ''}"
        print(f"# {model} {op} {impl}: {msg}", file=sys.stderr, flush=True)
        return row(model, op, impl, args.dtype, device, error=msg)

    for name, model in ot.cameras.MODELS.items():
        gen = torch.Generator().manual_seed(SEED + sum(map(ord, name)))
        params64, invpol = model_params(name)
        angle = min(SPECS[name]["angle"], 0.98 * float(model.max_angle(params64)))
        dirs64 = directions_in_cone(n, angle, gen)
        points = dirs64.to(device=device, dtype=dtype)
        params = params64.to(device=device, dtype=dtype)
        px_ref = ok = pix64 = None
        # (row, fn, device) to time together; rows with an "error" are reported, not timed.
        cases: list[tuple[dict, Callable[[], object] | None, torch.device]] = []
        # (ours row, peer row, target)
        pairs: list[tuple[dict, dict, float | None]] = []

        with torch.no_grad():
            try:
                px_ref, ok = (t.numpy() for t in model.project(dirs64, params64))
                _, valid = model.project(points, params)
                ours_p = row(name, "project", "omniscape_torch", args.dtype, device,
                             valid_fraction=float(valid.float().mean()))
                cases.append((ours_p, lambda: model.project(points, params), device))
            except Exception as err:  # a broken model must not hide the others
                ours_p = error_row(name, "project", "omniscape_torch", err)
                cases.append((ours_p, None, device))
            if invpol is not None:
                inv = invpol.to(device=device, dtype=dtype)
                impl = "omniscape_torch (invpol)"
                try:
                    _, valid_inv = scaramuzza_project(points, params, invpol=inv)
                    r = row(name, "project", impl, args.dtype, device,
                            valid_fraction=float(valid_inv.float().mean()),
                            note="OCamCalib's world2cam: inverse polynomial instead of Newton")
                    cases.append((r, lambda: scaramuzza_project(points, params, invpol=inv),
                                  device))
                except Exception as err:
                    cases.append((error_row(name, "project", impl, err), None, device))
            try:
                pix64 = pixels_in_circle(model, params64, angle, n, gen)
                pixels = pix64.to(device=device, dtype=dtype)
                _, valid_u = model.unproject(pixels, params)
                ours_u = row(name, "unproject", "omniscape_torch", args.dtype, device,
                             valid_fraction=float(valid_u.float().mean()))
                cases.append((ours_u, lambda: model.unproject(pixels, params), device))
            except Exception as err:
                ours_u = error_row(name, "unproject", "omniscape_torch", err)
                cases.append((ours_u, None, device))

        def max_diff(out: np.ndarray) -> float | None:
            """Largest |OpenCV - ours (float64)| in pixels where ours is valid."""
            if px_ref is None or not ok.any():
                return None
            return float(np.abs(out.reshape(n, 2) - px_ref)[ok].max())

        def peer(ours: dict, impl: str, np_dtype, fn: Callable[[], object], target: float | None,
                 note: str, diff: float | None = None) -> None:
            r = row(name, ours["op"], impl, np.dtype(np_dtype).name, cpu, note=note,
                    max_abs_diff_px_vs_ours=diff)
            cases.append((r, fn, cpu))
            pairs.append((ours, r, target))

        p = [float(v) for v in params64]
        zero = np.zeros((1, 3))
        if cv2 is not None and name == "kannala_brandt":
            K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
            D = np.array(p[4:8])
            for np_dtype in (np.float32, np.float64):
                obj = to_numpy(dirs64).astype(np_dtype).reshape(1, n, 3)

                def project_cv(obj=obj):
                    return cv2.fisheye.projectPoints(obj, zero, zero, K, D)

                peer(ours_p, "cv2.fisheye.projectPoints", np_dtype, project_cv, 1.0,
                     "computes its 2N x 15 Jacobian (Python allocates every output)",
                     max_diff(project_cv()[0]))
            for np_dtype in (np.float32, np.float64):
                xyz = to_numpy(dirs64).astype(np_dtype)

                def distort_cv(xyz=xyz):  # the division is part of the projection
                    m = xyz[:, :2] / xyz[:, 2:]
                    return cv2.fisheye.distortPoints(m.reshape(1, n, 2), K, D)

                peer(ours_p, "cv2.fisheye.distortPoints(x/z)", np_dtype, distort_cv, None,
                     "Jacobian-free: numpy x/z, y/z then distortPoints; z > 0 only",
                     max_diff(distort_cv()))
            for np_dtype in (np.float32, np.float64) if pix64 is not None else ():
                dist = to_numpy(pix64).astype(np_dtype).reshape(1, n, 2)
                peer(ours_u, "cv2.fisheye.undistortPoints", np_dtype,
                     lambda dist=dist: cv2.fisheye.undistortPoints(dist, K, D), None,
                     "returns x/z, y/z (no unit rays, no validity); default criteria: "
                     "10 iterations, eps 1e-8")
        elif cv2 is not None and name == "unified":
            K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
            xi = p[4]
            D = np.array([p[5:9]])
            for np_dtype in (np.float32, np.float64):
                obj = to_numpy(dirs64).astype(np_dtype).reshape(1, n, 3)

                def project_cv(obj=obj):
                    return cv2.omnidir.projectPoints(obj, zero, zero, K, xi, D)

                peer(ours_p, "cv2.omnidir.projectPoints", np_dtype, project_cv, 1.0,
                     "computes its 2N x 16 Jacobian (Python allocates every output)",
                     max_diff(project_cv()[0]))
            eye = np.eye(3)
            for np_dtype in (np.float32, np.float64) if pix64 is not None else ():
                dist = to_numpy(pix64).astype(np_dtype).reshape(1, n, 2)

                def undistort_cv(dist=dist):
                    return cv2.omnidir.undistortPoints(dist, K, D, np.array([xi]), eye)

                try:
                    cv2.omnidir.undistortPoints(dist[:, :8], K, D, np.array([xi]), eye)
                except cv2.error as err:  # not every OpenCV build takes float32
                    print(f"# skipped cv2.omnidir.undistortPoints {np.dtype(np_dtype).name}: "
                          f"{str(err).strip().splitlines()[-1]}", file=sys.stderr)
                    continue
                peer(ours_u, "cv2.omnidir.undistortPoints", np_dtype, undistort_cv, None,
                     "returns normalised plane points; 20 fixed iterations")

        timed = [(r, fn, dev) for r, fn, dev in cases if fn is not None]
        # OpenCV runs on the CPU: synchronising CUDA around its calls costs nothing.
        with torch.no_grad():
            stats = measure([fn for _, fn, _ in timed], repeats, warmup, device)
        for (r, _, _), st in zip(timed, stats):
            r.update(st, points_per_s=n / st["median_s"])
        for ours, other, target in pairs:
            if ours["median_s"] is None:
                continue
            ratio = ours["median_s"] / other["median_s"]
            other["ratio_ours_over_this"] = ratio
            ratios.append({"model": name, "op": ours["op"], "ours_dtype": ours["input_dtype"],
                           "peer": other["impl"], "peer_dtype": other["input_dtype"],
                           "ratio_ours_over_peer": ratio,
                           # of the fastest calls: a cross-check that load spikes cannot inflate
                           "ratio_of_min_times": ours["min_s"] / other["min_s"],
                           "target": target,
                           "meets_target": None if target is None else ratio <= target})
        rows.extend(r for r, _, _ in cases)
        print(f"# {name}: done", file=sys.stderr, flush=True)

    return {
        **run_record("cameras", device, args.threads, cv2),
        "dtype": args.dtype,
        "points": n,
        "repeats": repeats,
        "warmup": warmup,
        "seed": SEED,
        "timer": ("time.perf_counter around single calls, after warm-up, the calls of one model "
                  "round-robin; median and IQR; an untimed 10 ms pause before every timed "
                  "call (common.SETTLE_S)"),
        "timestamp_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "loadavg_start": load_start,
        "loadavg_end": loadavg(),
        "rows": rows,
        "ratios": ratios,
    }


def markdown(result: dict) -> str:
    def ms(s: float) -> str:
        return f"{1e3 * s:.2f}"

    lines = [f"cameras: {result['points']:,} points, {result['dtype']}, "
             f"{result['threads']} threads, {result['device']}, commit {result['commit'][:12]}"
             f"{' (dirty)' if result['dirty'] else ''}", "",
             "| model | op | impl | input | median ms | IQR ms | min ms | Mpoints/s | valid % | "
             "ours / this |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        if r.get("error"):
            lines.append(f"| {r['model']} | {r['op']} | {r['impl']} | {r['input_dtype']} | "
                         f"ERROR: {r['error'][:90]} | | | | | |")
            continue
        valid = "" if r["valid_fraction"] is None else f"{100 * r['valid_fraction']:.1f}"
        ratio = r.get("ratio_ours_over_this")
        lines.append(f"| {r['model']} | {r['op']} | {r['impl']} | {r['input_dtype']} | "
                     f"{ms(r['median_s'])} | {ms(r['iqr_s'])} | {ms(r['min_s'])} | "
                     f"{r['points_per_s'] / 1e6:.1f} | "
                     f"{valid} | {'' if ratio is None else f'{ratio:.2f}'} |")
    if result["ratios"]:
        lines += ["", "| ratio ours/peer (median) | of min times | model | op | peer | peer input | "
                  "target |", "|---:|---:|---|---|---|---|---|"]
        for q in result["ratios"]:
            target = ("" if q["target"] is None else
                      f"<= {q['target']:.1f} {'ok' if q['meets_target'] else 'MISSED'}")
            lines.append(f"| {q['ratio_ours_over_peer']:.2f} | {q['ratio_of_min_times']:.2f} | "
                         f"{q['model']} | {q['op']} | "
                         f"{q['peer']} | {q['peer_dtype']} | {target} |")
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=None,
                        help="points per call (default 1_000_000; 100_000 with --quick)")
    parser.add_argument("--threads", type=int, default=2,
                        help="torch and OpenCV thread count (default 2)")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed calls per row (default 15; 5 with --quick)")
    parser.add_argument("--warmup", type=int, default=None,
                        help="untimed calls before timing (default 2; 1 with --quick)")
    parser.add_argument("--quick", action="store_true",
                        help="100k points and few repeats: a smoke run of a few seconds")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                        help="device of our functions (OpenCV always runs on the CPU)")
    parser.add_argument("--out", type=Path, default=None, help="JSON output (default benchmarks/results/cameras.json)")
    args = parser.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("cameras.json", quick=args.quick)
    if args.points is None:
        args.points = 100_000 if args.quick else 1_000_000
    if args.repeats is None:
        args.repeats = 5 if args.quick else 15
    if args.warmup is None:
        args.warmup = 1 if args.quick else 2
    for name in ("points", "threads", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1")
    if args.warmup < 0:
        parser.error("--warmup must be >= 0")
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: CUDA is not available in this torch build or machine")
    return args


def main(argv=None) -> int:
    return run_main(parse_args, run, markdown, argv)


if __name__ == "__main__":
    sys.exit(main())
