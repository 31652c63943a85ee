"""Where calibration methods fail: success rate and final error per method against noise,
number of views, bad initialisation and near-degenerate views.

The truth is the real OCamCalib camera of ``../shared/data/ocamcalib_real`` (1600 x 1600, a
degree-4 polynomial) with its sensor roll ``e`` set to 0 (the fit holds ``e``: the poses absorb
a roll). A 9 x 12 checkerboard (inner corners) of 4 cm squares is seen from random poses
(``random_views``) with Gaussian pixel noise; every scenario is run ``--trials`` times with
seeds 0, 1, ... and every method on the same data:

* ``lm``, ``lbfgs``, ``adam``: ``ot.calibration.fit`` with that method (at most 100, 500 and
  1000 iterations), started from OCamCalib's linear solution, or, in the ``bad init`` rows,
  from the truth with the polynomial scaled as if the focal length were off by the factor and
  the centre moved by 30 px (poses then from the planar homography);
* ``linear``: OCamCalib's linear solution itself (no start needed, so no ``bad init`` rows).

A trial **succeeds** when the result says ``converged`` and its calibration error is below
1 px: the RMS distance between the fitted and the true camera's projections of the true
camera's rays on a 32 x 32 pixel grid, over the rays no farther from the axis than the board
points of that trial (a fit says nothing about the lens where no board was seen).
``false_converged`` counts results that said ``converged`` while the truth lies outside their
own 99.9% confidence region (``chi2`` of the intrinsics' error under the result's covariance
above the chi-square quantile, and an error above 1e-6 px): a failure returned as a good fit
(it must stay 0). A result can be converged and honest yet miss by more than 1 px when the
noise is high: its error bars say so. The linear solution never claims a least-squares
minimum (its ``converged`` means that the closed form gave a camera; its ``reason`` says it is
not refined), so it has no false convergence column.

    python benchmarks/calibration_stability.py            # 3 trials (about 20 min on 1 core)
    python benchmarks/calibration_stability.py --quick    # 1 trial, fewer scenarios
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import omniscape_torch as ot  # noqa: E402
from omniscape_torch.calibration import checkerboard, fit, random_views  # noqa: E402
from omniscape_torch.calibration.params import transform  # noqa: E402
from omniscape_torch.io import atomic_write_text  # noqa: E402

from common import ROOT, git_commit, loadavg, machine_info, write_json_atomic  # noqa: E402

OCAMCALIB = ROOT.parent / "shared" / "data" / "ocamcalib_real" / "calib_results_0.txt"
METHODS = ("lm", "lbfgs", "adam", "linear")
MAX_ITERATIONS = {"lm": 100, "lbfgs": 500, "adam": 1000, "linear": None}
SUCCESS_PX = 1.0
#: Below this error against the truth a fit is exact (noise-free data): its covariance is zero
#: and chi2 measures rounding.
EXACT_PX = 1e-6


def scenarios(quick: bool) -> list[dict]:
    base = {"noise": 0.2, "views": 8, "init": None, "fronto_parallel": False}
    rows = [{**base, "group": "noise", "noise": s} for s in
            ((0.0, 0.5, 2.0) if quick else (0.0, 0.2, 0.5, 1.0, 2.0))]
    rows += [{**base, "group": "views", "views": v} for v in ((2, 4) if quick else (2, 3, 5, 10))]
    rows += [{**base, "group": "bad init", "init": k} for k in
             ((0.5, 2.0) if quick else (0.5, 0.8, 1.25, 2.0))]
    rows += [{**base, "group": "near-degenerate", "fronto_parallel": True}]
    return rows


def bad_start(truth: torch.Tensor, factor: float) -> torch.Tensor:
    """The truth with the image scaled by ``factor`` (a_i -> a_i factor^(1 - i)) and the centre
    moved by 30 px."""
    start = truth.clone()
    i = torch.arange(len(truth) - 5, dtype=truth.dtype)
    start[5:] = truth[5:] * factor ** (1 - i)
    start[:2] += 30.0
    return start


def chi2(result, truth: torch.Tensor) -> tuple[float, float]:
    """Squared Mahalanobis distance of the free intrinsics from the truth under the result's
    covariance, and its 99.9% quantile for that many parameters (Wilson-Hilferty)."""
    free = [result.param_names.index(n) for n in result.free_names]
    err = (result.params - truth)[free]
    value = float(err @ torch.linalg.pinv(result.covariance[free][:, free]) @ err)
    k = len(free)
    return value, k * (1 - 2 / (9 * k) + 3.090 * math.sqrt(2 / (9 * k))) ** 3


def truth_error(camera: ot.Camera | None, rays: torch.Tensor, pixels: torch.Tensor) -> float:
    if camera is None:
        return math.inf
    projected, valid = camera.model.project(rays, camera.params)
    if not bool(valid.all()):
        return math.inf
    return float(torch.sqrt(((projected - pixels) ** 2).sum(-1).mean()))


def run(trials: int, quick: bool) -> tuple[list[dict], list[dict]]:
    from tqdm import tqdm

    params = ot.Camera.from_ocamcalib(OCAMCALIB).params.double().clone()
    params[4] = 0.0
    truth = ot.Camera("scaramuzza", params, (1600, 1600))
    grid = (torch.arange(32, dtype=torch.float64) + 0.5) / 32 * 1600 - 0.5
    v, u = torch.meshgrid(grid, grid, indexing="ij")
    grid_px = torch.stack((u, v), -1).reshape(-1, 2)
    rays, ok = truth.unproject(grid_px)
    rays, grid_px = rays[ok], grid_px[ok]
    board = checkerboard(9, 12, 0.04)
    records = []
    plan = [(s, t) for s in scenarios(quick) for t in range(trials)]
    for scenario, trial in tqdm(plan, desc="calibration_stability", file=sys.stderr):
        gen = torch.Generator().manual_seed(trial)
        pixels, poses, _ = random_views(truth, board, scenario["views"], generator=gen,
                                        noise=scenario["noise"],
                                        fronto_parallel=scenario["fronto_parallel"])
        seen = transform(poses[:, None], board)
        covered = float(torch.atan2(seen[..., :2].norm(dim=-1), seen[..., 2]).max())
        inside = torch.atan2(rays[:, :2].norm(dim=-1), rays[:, 2]) <= covered
        for method in METHODS:
            if method == "linear" and scenario["init"] is not None:
                continue
            init = None if scenario["init"] is None else bad_start(params, scenario["init"])
            start = time.perf_counter()
            try:
                result = fit(board, pixels, "scaramuzza", (1600, 1600), method=method,
                             init=init, max_iterations=MAX_ITERATIONS[method])
                converged, reason, rms = result.converged, result.reason, result.rms
                error = truth_error(result.camera, rays[inside], grid_px[inside])
                distance, quantile = chi2(result, params) if converged else (math.nan, math.inf)
            except ValueError as err:  # e.g. a linear solution that is not a camera
                converged, reason, rms, error = False, f"raised: {err}", math.nan, math.inf
                distance, quantile = math.nan, math.inf
            records.append({**scenario, "trial": trial, "method": method,
                            "converged": converged, "reason": reason, "rms_px": rms,
                            "covered_angle_deg": math.degrees(covered),
                            "truth_error_px": error, "chi2": distance,
                            "chi2_999": quantile,
                            "seconds": time.perf_counter() - start})
    return records, summarise(records)


def _label(s: dict) -> str:
    if s["group"] == "noise":
        return f"noise {s['noise']:g} px"
    if s["group"] == "views":
        return f"{s['views']} views"
    if s["group"] == "bad init":
        return f"start x{s['init']:g}, centre +30 px"
    return "all boards fronto-parallel"


def summarise(records: list[dict]) -> list[dict]:
    rows = []
    keys = []
    for r in records:
        key = (_label(r), r["method"])
        if key not in keys:
            keys.append(key)
    for label, method in keys:
        rs = [r for r in records if _label(r) == label and r["method"] == method]
        success = [r["converged"] and r["truth_error_px"] < SUCCESS_PX for r in rs]
        finite = [r["truth_error_px"] for r in rs if math.isfinite(r["truth_error_px"])]
        rows.append({
            "scenario": label, "method": method, "trials": len(rs),
            "success_rate": sum(success) / len(rs),
            "converged_rate": sum(r["converged"] for r in rs) / len(rs),
            "false_converged": (None if method == "linear" else
                                sum(r["converged"] and r["chi2"] > r["chi2_999"]
                                    and r["truth_error_px"] > EXACT_PX for r in rs)),
            "median_rms_px": float(np.nanmedian([r["rms_px"] for r in rs])),
            "median_truth_error_px": float(np.median(finite)) if finite else math.inf,
            "median_seconds": float(np.median([r["seconds"] for r in rs])),
        })
    return rows


def markdown(rows: list[dict]) -> str:
    lines = ["| scenario | method | success | converged | false conv. | median rms px | "
             "median error vs truth px | median s |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scenario']} | {r['method']} | {r['success_rate']:.0%} | "
                     f"{r['converged_rate']:.0%} | "
                     f"{'n/a' if r['false_converged'] is None else r['false_converged']} | "
                     f"{r['median_rms_px']:.3f} | {r['median_truth_error_px']:.3g} | "
                     f"{r['median_seconds']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=None, help="seeds per scenario "
                        "(default 3, 1 with --quick)")
    parser.add_argument("--quick", action="store_true", help="fewer scenarios and trials")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--out", type=Path,
                        default=ROOT / "benchmarks" / "results" / "calibration_stability.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    trials = args.trials or (1 if args.quick else 3)
    load_start = loadavg()
    start = time.perf_counter()
    records, rows = run(trials, args.quick)
    commit, dirty = git_commit()
    table = markdown(rows)
    write_json_atomic({
        "benchmark": "calibration_stability", "commit": commit, "dirty": dirty,
        "versions": {"torch": torch.__version__, "numpy": np.__version__},
        "threads": args.threads, "machine": machine_info(torch.device("cpu")),
        "loadavg_start": load_start, "loadavg_end": loadavg(),
        "wall_seconds": time.perf_counter() - start, "trials": trials,
        "success_px": SUCCESS_PX, "truth": str(OCAMCALIB.relative_to(ROOT.parent)),
        "summary": rows, "records": records}, args.out)
    header = (f"Calibration stability: real OCamCalib camera (e = 0) as truth, 9 x 12 board, "
              f"{trials} trials per row; success = converged and < {SUCCESS_PX:g} px from the "
              f"truth. Generated by `benchmarks/calibration_stability.py`.\n\n")
    atomic_write_text(args.out.with_suffix(".md"), header + table)
    print(table)


if __name__ == "__main__":
    main()
