"""Where calibration methods fail: success rate and final error per method against noise,
number of views, bad initialisation, near-degenerate views, outliers and wide lenses, with
OpenCV's ``cv2.omnidir.calibrate`` and ``cv2.fisheye.calibrate`` on the same data.

Two parts, one success criterion. A trial **succeeds** when the result says ``converged``
(OpenCV: returns without an exception) and its calibration error ("ray RMS") is below 1 px:
the RMS distance between the fitted and the true camera's projections of the true camera's
rays on a 32 x 32 pixel grid, over the rays no farther from the axis than the board points of
that trial (a fit says nothing about the lens where no board was seen).

**Polynomial lens** (``scenarios``). The truth is the real OCamCalib camera of
``../shared/data/ocamcalib_real`` (1600 x 1600, a degree-4 polynomial) with its sensor roll
``e`` set to 0 (the fit holds ``e``: the poses absorb a roll). A 9 x 12 checkerboard (inner
corners) of 4 cm squares is seen from random poses (``random_views``) with Gaussian pixel
noise; every scenario is run ``--trials`` times with seeds 0, 1, ... and every method on the
same data:

* ``lm``, ``lbfgs``, ``adam``: ``ot.calibration.fit`` with that method (LM with its default
  budget, L-BFGS and Adam at most 500 and 1000 iterations), started from OCamCalib's linear
  solution, or, in the ``bad init`` rows, from the truth with the polynomial scaled as if the
  focal length were off by the factor and the centre moved by 30 px (poses then from the
  planar homography);
* ``linear``: OCamCalib's linear solution itself (no start needed, so no ``bad init`` rows).

``false_converged`` counts results that said ``converged`` while the truth lies outside their
own 99.9% confidence region (``chi2`` of the intrinsics' error under the result's covariance
above the chi-square quantile, and an error above 1e-6 px): a failure returned as a good fit
(it must stay 0). A result can be converged and honest yet miss by more than 1 px when the
noise is high: its error bars say so. The linear solution never claims a least-squares
minimum (its ``converged`` means that the closed form gave a camera; its ``reason`` says it is
not refined), so it has no false convergence column.

**Wide lenses** (``CASES``, issue 19): a 9 x 6 board (inner corners) of 8 cm squares, 0.3 px
noise, ``--seeds`` seeds (default 20), ``fit`` with its defaults (no ``fov``, no ``init``)
against OpenCV:

* ``unified 230``: a Mei camera (unified model with distortion: xi 0.9, k1 -0.05, k2 0.01,
  p1 2e-4, p2 -1e-4) whose 230-degree field of view fills an 800 x 800 image, 15 views
  (``random_views``' defaults inside that field); ``cv2.omnidir.calibrate`` (skew fixed);
* the same camera from 3 views (few views: ``converged, > 1 px`` counts the fits that claim
  convergence while more than 1 px off);
* the same camera and views with 2% of the corners moved by 10-50 px in a random direction:
  ``fit`` with the plain loss, with the Cauchy loss, and with ``reject_outliers=True``
  (``outliers listed``: how many of the moved corners it listed, and how many others);
* ``kannala-brandt 220``: a Kannala-Brandt fisheye (k1..k4 -0.02, 0.004, -0.001, 2e-4) whose
  220 degrees fill an 800 x 800 image, board centres up to 95 degrees off the axis, so that
  corners lie past 90 degrees; ``cv2.fisheye.calibrate`` (skew fixed, extrinsics recomputed);
* ``kannala-brandt 190``: the same lens at 190 degrees, boards near the rim only (centres at
  least 55 degrees off the axis, every corner within 90 degrees, where OpenCV's model holds).

``at the optimum`` (``fit`` only) tells a start's failure from the data's: the fit ended at
the cost (within ``OPTIMUM_RTOL``) of the same fit started at the true intrinsics and poses, so
its start found the least-squares minimum; a fit at the optimum that is still over 1 px from the
truth is as far as this data determines the lens (OpenCV's minimum is then the same).

OpenCV starts from its own initialisation, as ``fit`` does; its parameters are read into our
camera of the same model (omnidir is the unified model with the same parameters, fisheye
Kannala-Brandt) to measure the ray RMS the same way.

    python benchmarks/calibration_stability.py            # 3 trials, 20 seeds (~25 min on 2 cores)
    python benchmarks/calibration_stability.py --quick    # 1 trial, 2 seeds, fewer scenarios
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import omniscape_torch as ot  # noqa: E402
from omniscape_torch.calibration import checkerboard, fit, random_views  # noqa: E402
from omniscape_torch.calibration.params import transform  # noqa: E402
from omniscape_torch.io import atomic_write_text  # noqa: E402

from common import (ROOT, git_commit, loadavg, machine_info, results_path,  # noqa: E402
                    write_json_atomic)

OCAMCALIB = ROOT.parent / "shared" / "data" / "ocamcalib_real" / "calib_results_0.txt"
METHODS = ("lm", "lbfgs", "adam", "linear")
MAX_ITERATIONS = {"lm": None, "lbfgs": 500, "adam": 1000, "linear": None}
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


def truth_grid(truth: ot.Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """The truth's rays ``(K, 3)`` at the valid pixels ``(K, 2)`` of a 32 x 32 grid."""
    h, w = truth.image_size
    gv = (torch.arange(32, dtype=torch.float64) + 0.5) / 32 * h - 0.5
    gu = (torch.arange(32, dtype=torch.float64) + 0.5) / 32 * w - 0.5
    v, u = torch.meshgrid(gv, gu, indexing="ij")
    grid_px = torch.stack((u, v), -1).reshape(-1, 2)
    rays, ok = truth.unproject(grid_px)
    return rays[ok], grid_px[ok]


def ray_error(camera: ot.Camera | None, truth: ot.Camera, poses: torch.Tensor,
              board: torch.Tensor) -> tuple[float, float]:
    """(ray RMS of ``camera`` against ``truth`` over the field the boards covered, that field's
    largest angle off the axis in radians)."""
    rays, grid_px = truth_grid(truth)
    seen = transform(poses[:, None], board)
    covered = float(torch.atan2(seen[..., :2].norm(dim=-1), seen[..., 2]).max())
    inside = torch.atan2(rays[:, :2].norm(dim=-1), rays[:, 2]) <= covered
    return truth_error(camera, rays[inside], grid_px[inside]), covered


# --------------------------------------------------------------------------------------------
# Polynomial lens: the methods of fit against noise, views, starts
# --------------------------------------------------------------------------------------------

def polynomial_truth() -> tuple[torch.Tensor, ot.Camera]:
    params = ot.Camera.from_ocamcalib(OCAMCALIB).params.double().clone()
    params[4] = 0.0
    return params, ot.Camera("scaramuzza", params, (1600, 1600))


def polynomial_trial(scenario: dict, trial: int) -> list[dict]:
    params, truth = polynomial_truth()
    board = checkerboard(9, 12, 0.04)
    gen = torch.Generator().manual_seed(trial)
    pixels, poses, _ = random_views(truth, board, scenario["views"], generator=gen,
                                    noise=scenario["noise"],
                                    fronto_parallel=scenario["fronto_parallel"])
    records = []
    for method in METHODS:
        if method == "linear" and scenario["init"] is not None:
            continue
        init = None if scenario["init"] is None else bad_start(params, scenario["init"])
        start = time.perf_counter()
        try:
            result = fit(board, pixels, "scaramuzza", (1600, 1600), method=method,
                         init=init, max_iterations=MAX_ITERATIONS[method])
            converged, reason, rms = result.converged, result.reason, result.rms
            error, covered = ray_error(result.camera, truth, poses, board)
            distance, quantile = chi2(result, params) if converged else (math.nan, math.inf)
            iterations = result.iterations
        except ValueError as err:  # e.g. a linear solution that is not a camera
            converged, reason, rms = False, f"raised: {err}", math.nan
            error, covered = math.inf, ray_error(None, truth, poses, board)[1]
            distance, quantile, iterations = math.nan, math.inf, 0
        records.append({**scenario, "trial": trial, "method": method,
                        "converged": converged, "reason": reason, "rms_px": rms,
                        "iterations": iterations,
                        "covered_angle_deg": math.degrees(covered),
                        "truth_error_px": error, "chi2": distance,
                        "chi2_999": quantile,
                        "seconds": time.perf_counter() - start})
    return records


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


# --------------------------------------------------------------------------------------------
# Wide lenses (issue 19): fit's defaults against OpenCV on the same data
# --------------------------------------------------------------------------------------------

NOISE_WIDE = 0.3
KB_DISTORTION = (-0.02, 0.004, -0.001, 0.0002)

#: A fit is at the optimum when its final cost is within this relative margin of the same
#: fit started at the truth (the costs of one minimum agree to ~1e-12; a fit stopped short or
#: in another minimum is off by far more).
OPTIMUM_RTOL = 1e-6

#: The cases: camera, views, how the boards are placed, outliers, and the methods run.
CASES = (
    {"case": "unified 230, 15 views", "camera": "mei230", "views": 15,
     "methods": ("lm", "omnidir")},
    {"case": "unified 230, 3 views", "camera": "mei230", "views": 3,
     "methods": ("lm", "omnidir")},
    {"case": "unified 230, 15 views, 2% outliers", "camera": "mei230", "views": 15,
     "outliers": 0.02, "methods": ("lm", "lm cauchy", "lm reject_outliers", "omnidir")},
    {"case": "kannala-brandt 220, corners past 90 deg", "camera": "kb220", "views": 15,
     "max_angle": 95.0, "methods": ("lm", "fisheye")},
    {"case": "kannala-brandt 190, boards near the rim", "camera": "kb190", "views": 15,
     "rim": (55.0, 90.0), "methods": ("lm", "fisheye")},
)

#: The board of the wide cases: 9 x 6 inner corners, 8 cm squares (72 x 48 cm between the
#: outer corners: smaller boards leave most of a 230-degree field unseen, and the error over
#: the covered field then measures the extrapolation, not the fit).
BOARD_WIDE = (6, 9, 0.08)


def wide_camera(name: str, size: tuple[int, int] = (800, 800)) -> ot.Camera:
    """The truth of a wide case (module docstring), on a sensor of ``size`` ``(H, W)``."""
    if name == "mei230":
        cam, _ = ot.cameras.presets.catadioptric(size, fov=math.radians(230), blind_fov=None,
                                                 dtype=torch.float64)
        params = cam.params.clone()
        params[5:9] = torch.tensor([-0.05, 0.01, 2e-4, -1e-4], dtype=torch.float64)
        return ot.Camera("unified", params, size, fov=math.radians(230))
    fov = {"kb220": 220.0, "kb190": 190.0}[name]
    return ot.cameras.presets.fisheye(size, fov=math.radians(fov), model="kannala_brandt",
                                      distortion=KB_DISTORTION, dtype=torch.float64)


def rim_views(camera: ot.Camera, board: torch.Tensor, n_views: int, generator: torch.Generator,
              noise: float, min_deg: float, max_corner_deg: float
              ) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Views whose board centre is at least ``min_deg`` off the axis and whose every corner is
    within ``max_corner_deg``, drawn one at a time by ``random_views``."""
    pixels, poses = [], []
    for _ in range(20000):
        if len(poses) == n_views:
            break
        px, pose, _ = random_views(camera, board, 1, generator=generator, noise=noise,
                                   max_angle=math.radians(85))
        seen = transform(pose[0], board)
        corner = float(torch.atan2(seen[:, :2].norm(dim=-1), seen[:, 2]).max())
        centre = float(torch.atan2(pose[0, 3:5].norm(), pose[0, 5]))
        if centre >= math.radians(min_deg) and corner <= math.radians(max_corner_deg):
            pixels.append(px[0])
            poses.append(pose[0])
    if len(poses) < n_views:
        raise RuntimeError("rim_views: too few views near the rim")
    return pixels, torch.stack(poses)


def wide_data(case: dict, seed: int) -> dict:
    """The truth, board, pixels (with the outliers moved), poses and moved corners of a seed."""
    truth = wide_camera(case["camera"])
    board = checkerboard(*BOARD_WIDE)
    gen = torch.Generator().manual_seed(seed)
    if "rim" in case:
        pixels, poses = rim_views(truth, board, case["views"], gen, NOISE_WIDE, *case["rim"])
    else:
        kwargs = {"max_angle": math.radians(case["max_angle"])} if "max_angle" in case else {}
        pixels, poses, _ = random_views(truth, board, case["views"], generator=gen,
                                        noise=NOISE_WIDE, **kwargs)
    moved: list[list[int]] = [[] for _ in pixels]
    if case.get("outliers"):
        n = len(board)
        total = n * len(pixels)
        for flat in torch.randperm(total, generator=gen)[:round(case["outliers"] * total)]:
            v, i = divmod(int(flat), n)
            angle = 2 * math.pi * float(torch.rand((), generator=gen, dtype=torch.float64))
            length = 10 + 40 * float(torch.rand((), generator=gen, dtype=torch.float64))
            pixels[v] = pixels[v].clone()
            pixels[v][i] += length * torch.tensor([math.cos(angle), math.sin(angle)],
                                                  dtype=torch.float64)
            moved[v].append(i)
    return {"truth": truth, "board": board, "pixels": pixels, "poses": poses,
            "moved": [sorted(m) for m in moved]}


def run_ours(data: dict, method: str) -> dict:
    kwargs = {"lm": {}, "lm cauchy": {"loss": "cauchy"},
              "lm reject_outliers": {"reject_outliers": True}}[method]
    truth = data["truth"]
    start = time.perf_counter()
    result = fit(data["board"], data["pixels"], truth.model.name, truth.image_size, **kwargs)
    seconds = time.perf_counter() - start
    # The reference minimum: the same fit started at the true intrinsics and poses. The default
    # start found the optimum when it ends at that cost or lower (a start cannot do better;
    # what is left between the optimum and the truth is the data's, not the start's).
    oracle = fit(data["board"], data["pixels"], truth.model.name, truth.image_size,
                 init=truth.params, poses=data["poses"], **kwargs)
    listed = [set(o.tolist()) for o in result.outliers]
    found = sum(len(s & set(m)) for s, m in zip(listed, data["moved"]))
    return {"converged": result.converged, "reason": result.reason, "rms_px": result.rms,
            "iterations": result.iterations, "start": result.start, "camera": result.camera,
            "seconds": seconds, "cost": result.cost, "oracle_cost": oracle.cost,
            "at_optimum": bool(result.converged
                               and result.cost <= oracle.cost * (1 + OPTIMUM_RTOL)),
            "outliers_found": found, "outliers_false": sum(len(s) for s in listed) - found}


def run_opencv(data: dict, method: str) -> dict:
    """``cv2.omnidir.calibrate`` or ``cv2.fisheye.calibrate`` with their own initialisation;
    the camera rebuilt as ours (same models: OpenCV omnidir is the unified model with the same
    parameters, OpenCV fisheye Kannala-Brandt)."""
    import cv2

    truth = data["truth"]
    h, w = truth.image_size
    obj = [data["board"].numpy().reshape(1, -1, 3)] * len(data["pixels"])
    img = [p.numpy().reshape(1, -1, 2) for p in data["pixels"]]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    if method == "omnidir":
        rms, k, xi, dist, _, _, idx = cv2.omnidir.calibrate(
            obj, img, (w, h), None, None, None, cv2.omnidir.CALIB_FIX_SKEW, criteria)
        params = [k[0, 0], k[1, 1], k[0, 2], k[1, 2], float(np.ravel(xi)[0]),
                  *np.ravel(dist)[:4]]
        used = int(np.size(idx))
    else:
        flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
        rms, k, dist, _, _ = cv2.fisheye.calibrate(obj, img, (w, h), None, None, flags=flags,
                                                   criteria=criteria)
        params = [k[0, 0], k[1, 1], k[0, 2], k[1, 2], *np.ravel(dist)[:4]]
        used = len(img)
    try:
        camera = ot.Camera(truth.model.name, torch.tensor(params, dtype=torch.float64),
                           truth.image_size)
    except ValueError:  # parameters outside our model's range: no camera
        camera = None
    return {"converged": True, "reason": f"returned (rms {rms:.3g}, {used} of "
            f"{len(img)} views used)", "rms_px": float(rms), "iterations": None,
            "start": "opencv", "camera": camera, "outliers_found": 0, "outliers_false": 0}


def wide_trial(case: dict, seed: int) -> list[dict]:
    data = wide_data(case, seed)
    records = []
    for method in case["methods"]:
        start = time.perf_counter()
        try:
            out = (run_opencv if method in ("omnidir", "fisheye") else run_ours)(data, method)
            exception = None
        except Exception as err:  # noqa: BLE001 -- OpenCV raises cv2.error on bad data
            out = {"converged": False, "reason": f"raised: {str(err).strip()[:200]}",
                   "rms_px": math.nan, "iterations": None, "start": None, "camera": None,
                   "outliers_found": 0, "outliers_false": 0}
            if method not in ("omnidir", "fisheye"):
                out["at_optimum"] = False
            exception = type(err).__name__
        seconds = out.pop("seconds", time.perf_counter() - start)  # ours: without the oracle
        error, covered = ray_error(out.pop("camera"), data["truth"], data["poses"],
                                   data["board"])
        records.append({"case": case["case"], "seed": seed, "method": method, **out,
                        "exception": exception, "ray_rms_px": error,
                        "covered_angle_deg": math.degrees(covered),
                        "outliers_moved": sum(len(m) for m in data["moved"]),
                        "seconds": seconds})
    return records


def summarise_wide(records: list[dict]) -> list[dict]:
    rows, keys = [], []
    for r in records:
        if (r["case"], r["method"]) not in keys:
            keys.append((r["case"], r["method"]))
    for case, method in keys:
        rs = [r for r in records if r["case"] == case and r["method"] == method]
        errors = np.array([r["ray_rms_px"] for r in rs])
        its = [r["iterations"] for r in rs if r["iterations"] is not None]
        rows.append({
            "case": case, "method": method, "seeds": len(rs),
            "success_rate": float(np.mean([r["converged"] and r["ray_rms_px"] < SUCCESS_PX
                                           for r in rs])),
            "converged_rate": float(np.mean([r["converged"] for r in rs])),
            "optimum_rate": (float(np.mean([r["at_optimum"] for r in rs]))
                             if all("at_optimum" in r for r in rs) else None),
            "converged_over_1px": int(sum(r["converged"] and not r["ray_rms_px"] < SUCCESS_PX
                                          for r in rs)),
            "exceptions": int(sum(r["exception"] is not None for r in rs)),
            "median_ray_rms_px": _quantile(errors, 0.5),
            "p90_ray_rms_px": _quantile(errors, 0.9),
            "median_iterations": float(np.median(its)) if its else None,
            "max_iterations": max(its) if its else None,
            "median_seconds": float(np.median([r["seconds"] for r in rs])),
            "outliers_moved": int(sum(r["outliers_moved"] for r in rs)),
            "outliers_found": int(sum(r["outliers_found"] for r in rs)),
            "outliers_false": int(sum(r["outliers_false"] for r in rs)),
            "covered_angle_deg": float(np.median([r["covered_angle_deg"] for r in rs])),
        })
    return rows


def _quantile(values: np.ndarray, q: float) -> float:
    """The ``q`` quantile, the nearest rank at or above it (an infinite error, a failed fit,
    stays infinite instead of turning NaN by interpolation)."""
    ordered = np.sort(values)
    return float(ordered[min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))])


def markdown_wide(rows: list[dict]) -> str:
    lines = ["| case | method | success | converged | at the optimum | converged, > 1 px | "
             "exceptions | median / p90 ray RMS px | iterations median (max) | outliers listed "
             "| median s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        its = ("-" if r["median_iterations"] is None
               else f"{r['median_iterations']:g} ({r['max_iterations']})")
        listed = (f"{r['outliers_found']} of {r['outliers_moved']} (+{r['outliers_false']})"
                  if r["method"] == "lm reject_outliers" else "-")
        optimum = "-" if r.get("optimum_rate") is None else f"{r['optimum_rate']:.0%}"
        lines.append(f"| {r['case']} | {r['method']} | {r['success_rate']:.0%} | "
                     f"{r['converged_rate']:.0%} | {optimum} | {r['converged_over_1px']} | "
                     f"{r['exceptions']} | {r['median_ray_rms_px']:.3g} / "
                     f"{r['p90_ray_rms_px']:.3g} | {its} | {listed} | "
                     f"{r['median_seconds']:.2f} |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------

def _worker_init(threads: int) -> None:
    torch.set_num_threads(threads)
    try:
        os.nice(5)
    except OSError:
        pass


def _task(kind: str, spec: dict, seed: int) -> list[dict]:
    return (polynomial_trial if kind == "polynomial" else wide_trial)(spec, seed)


def run(trials: int, seeds: int, quick: bool, jobs: int, threads: int
        ) -> tuple[list[dict], list[dict]]:
    """Every task (one scenario or case and seed) in ``jobs`` processes; records in task
    order whatever the order they finish in. ``trials = 0``: the wide cases only."""
    from tqdm import tqdm

    tasks = [("polynomial", s, t) for s in scenarios(quick) for t in range(trials)]
    tasks += [("wide", c, t) for c in CASES for t in range(seeds)]
    out: list[list[dict] | None] = [None] * len(tasks)
    bar = tqdm(total=len(tasks), desc="calibration_stability", file=sys.stderr)
    if jobs <= 1:
        _worker_init(threads)
        for i, task in enumerate(tasks):
            out[i] = _task(*task)
            bar.update(1)
    else:
        with ProcessPoolExecutor(jobs, initializer=_worker_init, initargs=(threads,)) as pool:
            futures = {pool.submit(_task, *task): i for i, task in enumerate(tasks)}
            for future in as_completed(futures):
                out[futures[future]] = future.result()
                bar.update(1)
    bar.close()
    polynomial = [r for (kind, _, _), rs in zip(tasks, out) if kind == "polynomial" for r in rs]
    wide = [r for (kind, _, _), rs in zip(tasks, out) if kind == "wide" for r in rs]
    return polynomial, wide


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=None, help="seeds per polynomial "
                        "scenario (default 3, 1 with --quick)")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per wide-lens case "
                        "(default 20, 2 with --quick)")
    parser.add_argument("--quick", action="store_true", help="fewer scenarios and seeds")
    parser.add_argument("--wide-only", action="store_true", help="run the wide-lens cases only; "
                        "the polynomial records are kept from --out (with their commit)")
    parser.add_argument("--jobs", type=int, default=2, help="processes (default 2)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per process "
                        "(default 1)")
    parser.add_argument("--resummarise", action="store_true", help="no run: the tables again "
                        "from the records of --out")
    parser.add_argument("--out", type=Path,
                        default=None)
    args = parser.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("calibration_stability.json", quick=args.quick)
    if args.resummarise:
        report = json.loads(args.out.read_text())
    else:
        trials = args.trials or (1 if args.quick else 3)
        seeds = args.seeds or (2 if args.quick else 20)
        kept = {}
        if args.wide_only:
            old = json.loads(args.out.read_text())
            kept = {"polynomial_commit": old.get("polynomial_commit", old["commit"])}
            trials = old["trials"]
        load_start = loadavg()
        start = time.perf_counter()
        records, wide = run(0 if args.wide_only else trials, seeds, args.quick, args.jobs,
                            args.threads)
        if args.wide_only:
            records = old["records"]
        commit, dirty = git_commit()
        report = {
            "benchmark": "calibration_stability", "commit": commit, "dirty": dirty,
            "versions": {"torch": torch.__version__, "numpy": np.__version__,
                         "opencv": _opencv_version()},
            "threads": args.threads, "jobs": args.jobs,
            "machine": machine_info(torch.device("cpu")),
            "loadavg_start": load_start, "loadavg_end": loadavg(),
            "wall_seconds": time.perf_counter() - start, "trials": trials, "seeds": seeds,
            "success_px": SUCCESS_PX, "truth": str(OCAMCALIB.relative_to(ROOT.parent)),
            "records": records, "wide_records": wide, **kept}
    report["summary"] = summarise(report["records"])
    report["wide_summary"] = summarise_wide(report["wide_records"])
    write_json_atomic(report, args.out)
    text = (f"Calibration stability, generated by `benchmarks/calibration_stability.py` "
            f"({report['jobs']} processes of {report['threads']} thread). Success = converged "
            f"(OpenCV: no exception) and ray RMS < {SUCCESS_PX:g} px against the truth over "
            f"the field the boards covered.\n\n"
            f"## Wide lenses: `fit`'s defaults and OpenCV on the same data\n\n"
            f"9 x 6 board, {NOISE_WIDE:g} px noise, {report['seeds']} seeds per case (the "
            f"script's docstring describes the cameras and views).\n\n"
            + markdown_wide(report["wide_summary"]) +
            f"\n## Polynomial lens: the methods of `fit`\n\n"
            f"Real OCamCalib camera (e = 0) as truth, 9 x 12 board, {report['trials']} trials "
            f"per row" + (f" (run at commit {report['polynomial_commit'][:7]})"
                          if "polynomial_commit" in report else "") + ".\n\n"
            + markdown(report["summary"]))
    atomic_write_text(args.out.with_suffix(".md"), text)
    print(text)
    return 0


def _opencv_version() -> str | None:
    try:
        import cv2
    except ImportError:
        return None
    return cv2.__version__


if __name__ == "__main__":
    sys.exit(main())
