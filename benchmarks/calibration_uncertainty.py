"""Does ``fit``'s predicted pixel error match the error against the truth? (issue 33)

Synthetic boards with a known camera: a 9 x 6 checkerboard (inner corners) of 8 cm squares
(``calibration_stability.BOARD_WIDE``) seen from ``random_views``' random poses by two wide
lenses on a 1280 x 1024 sensor, each image circle inscribed in the sensor's height:

* ``kannala-brandt 190``: a Kannala-Brandt fisheye of 190 degrees
  (``calibration_stability.KB_DISTORTION``);
* ``unified 230``: a Mei camera of 230 degrees (unified model, xi 0.9 of the catadioptric
  preset, k1 -0.05, k2 0.01, p1 2e-4, p2 -1e-4, as ``calibration_stability``'s).

3, 8 and 21 views, ``--seeds`` seeds (default 40; issue 33 asks for at least 20) each, seed ``s`` with Gaussian corner noise
of 0.1, 0.3 or 0.5 px per coordinate (``NOISES[s % 3]``; the ratio below does not depend on the
noise's scale, as long as the fit is linear over it); ``fit`` with its defaults. Two figures per fit, the same statistic
over the same pixels, the grid of ``coverage.covered_rays`` (48 samples along the longer side,
the pixels no farther off axis than the corners reach):

* **true**: the RMS over those pixels ``g`` of ``|project(d_g, fitted) - g|``, ``d_g`` the
  truth's ray at ``g``: how far the fitted camera puts what the true camera sees at ``g``;
* **predicted**: ``Coverage.pixel_error`` of ``assess_coverage``: the median of the
  distribution of that RMS implied by the fit's covariance ``C`` of the intrinsics (the poses
  marginalised, scaled by the residuals' noise; ``coverage.predicted_error``); and
  ``Coverage.pixel_rms``, the root of its mean square (the RMS of the per-pixel predicted std
  ``sqrt(trace(J C J^T))``).

A calibrated prediction puts half the fits' true error above ``pixel_error`` (median over
seeds of ``predicted / true`` near 1; issue 33 asks for [0.7, 1.4] in every case) and gives
``mean true^2 = mean pixel_rms^2`` (the "rms ratio" column, ``sqrt(mean pixel_rms^2 / mean
true^2)`` over seeds). The table also lists the ratio's quartiles, the medians of both
figures per noise level and how many fits the verdict of ``omniscape-torch fit``
(``coverage.THRESHOLDS``, over the lens's field of view as ``fit --images`` judges the image
circle) passes. The first ``--jackknife`` seeds of the 8- and 21-view cases also get
``leave_one_out``'s resampled figure, an estimate of ``pixel_rms`` (the median over those
seeds of their ratio is listed): how to read that figure on real photographs.

Measured first (before issue 33's fix): ``pixel_rms`` matches the truth (rms ratio 0.8-1.4)
but ``predicted / true`` has a median of 1.65 on 3 views of the Kannala-Brandt lens (repeating
the noise on one set of 3 poses 20 times: mean squares within 4-8%, medians of the ratio
1.43-1.48): with few views one direction of the intrinsics dominates the error, whose RMS is
then nearly ``|N(0, 1)|`` times its root mean square, median 0.67 of it. The median of the
distribution is the figure that matches a single fit's error; the verdict used the largest
per-pixel std, a further 1.2-1.6 times above. With that median, 30 noise draws on each of three
3-view pose sets give medians of the ratio of 0.98-1.15; over seeds (one draw each, new poses)
the median's standard error is about 0.12 at 20 seeds (a 20-seed run gave 1.41 on 3 views of
the Kannala-Brandt lens, its mean squares 1.39), hence 40 seeds by default.

The real set (``tests/data/ocamcalib_fisheye2``: 8 photographs of a ~180-degree fisheye, an
8 x 6 board; Kannala-Brandt, the area bounded by the image circle of the images) is reported
with both figures, the predicted and the leave-one-view-out.

    python benchmarks/calibration_uncertainty.py            # 40 seeds (~4 min of one core)
    python benchmarks/calibration_uncertainty.py --quick    # 3 seeds, into results/quick/
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import omniscape_torch as ot  # noqa: E402
from omniscape_torch.calibration import assess_coverage, checkerboard, fit, random_views  # noqa
from omniscape_torch.calibration.coverage import (THRESHOLDS, covered_rays,  # noqa: E402
                                                  leave_one_out)
from omniscape_torch.io import atomic_write_text  # noqa: E402

from calibration_stability import BOARD_WIDE, wide_camera  # noqa: E402
from common import (ROOT, begin_run, git_commit, loadavg, machine_info,  # noqa: E402
                    results_path, write_json_atomic)

SIZE = (1024, 1280)
LENSES = ("kannala-brandt 190", "unified 230")
VIEWS = (3, 8, 21)
NOISES = (0.1, 0.3, 0.5)
BAND = (0.7, 1.4)
REAL = ROOT / "tests" / "data" / "ocamcalib_fisheye2"


def lens(name: str) -> ot.Camera:
    """The truth of a lens (module docstring)."""
    return wide_camera({"unified 230": "mei230", "kannala-brandt 190": "kb190"}[name], SIZE)


def true_error(camera: ot.Camera, truth: ot.Camera, pixels: list[torch.Tensor]) -> float:
    """RMS over ``covered_rays``' pixels ``g`` of ``|project(truth ray at g, camera) - g|``."""
    grid, _ = covered_rays(camera, pixels)
    rays, valid = truth.unproject(grid)
    projected, ok = camera.model.project(rays[valid], camera.params)
    if not bool(ok.all()):
        return math.inf
    return float((projected - grid[valid]).square().sum(-1).mean().sqrt())


def trial(name: str, views: int, seed: int, jackknife: bool) -> dict:
    truth = lens(name)
    board = checkerboard(*BOARD_WIDE)
    noise = NOISES[seed % len(NOISES)]
    gen = torch.Generator().manual_seed(seed)
    pixels, _, _ = random_views(truth, board, views, generator=gen, noise=noise)
    start = time.perf_counter()
    result = fit(board, pixels, truth.model.name, SIZE)
    seconds = time.perf_counter() - start
    row = {"lens": name, "views": views, "noise": noise, "seed": seed,
           "converged": result.converged, "reason": result.reason, "seconds": seconds}
    if result.camera is None:
        return row
    coverage = assess_coverage(result.camera, result.covariance, pixels, fov=truth.fov)
    row.update(predicted=coverage.pixel_error, predicted_rms=coverage.pixel_rms,
               true=true_error(result.camera, truth, pixels),
               max_pixel_std=coverage.max_pixel_std, cells=coverage.cells,
               angle_share=coverage.angle_share, verdict_ok=coverage.ok,
               near_degenerate=list(getattr(result, "near_degenerate", [])))
    if jackknife:
        row["resampled"] = leave_one_out(result, board, pixels).pixel_error
    return row


def _quantile(values: list[float], q: float) -> float:
    values = sorted(values)
    pos = q * (len(values) - 1)
    lo, hi = math.floor(pos), math.ceil(pos)
    return values[lo] + (values[hi] - values[lo]) * (pos - lo)


def summarise(rows: list[dict]) -> list[dict]:
    table = []
    for name in LENSES:
        for views in VIEWS:
            mine = [r for r in rows if (r["lens"], r["views"]) == (name, views)
                    and math.isfinite(r.get("true", math.inf)) and r["true"] > 0
                    and math.isfinite(r["predicted"])]
            if not mine:
                continue
            ratio = [r["predicted"] / r["true"] for r in mine]
            entry = {
                "lens": name, "views": views, "fits": len(mine),
                "converged": sum(r["converged"] for r in mine),
                "ratio_median": statistics.median(ratio),
                "ratio_q25": _quantile(ratio, 0.25), "ratio_q75": _quantile(ratio, 0.75),
                "ratio_rms": math.sqrt(sum(r["predicted_rms"] ** 2 for r in mine)
                                       / sum(r["true"] ** 2 for r in mine)),
                "in_band": BAND[0] <= statistics.median(ratio) <= BAND[1],
                "verdict_ok": sum(r["verdict_ok"] for r in mine)}
            for noise in NOISES:
                at = [r for r in mine if r["noise"] == noise]
                if at:
                    entry[f"predicted_{noise:g}"] = statistics.median(r["predicted"] for r in at)
                    entry[f"true_{noise:g}"] = statistics.median(r["true"] for r in at)
            jack = [r for r in mine if "resampled" in r]
            if jack:
                entry["resampled_ratio_median"] = statistics.median(
                    r["resampled"] / r["predicted_rms"] for r in jack)
                entry["resampled_fits"] = len(jack)
            table.append(entry)
    return table


def real_set() -> dict:
    """Kannala-Brandt on ``tests/data/ocamcalib_fisheye2``: predicted and resampled figures."""
    import numpy as np

    from omniscape_torch.calibration import Board, detect_corners, image_circle
    from omniscape_torch.calibration.detect import image_files
    from omniscape_torch.io.images import read_image

    files = image_files(REAL)
    data = detect_corners(files, Board.parse("checkerboard:8x6:0.117"))
    result = fit(data.object_points, data.image_points, "kannala_brandt", data.image_size)
    mean = np.mean([read_image(f).double().numpy().reshape(data.image_size + (-1,)).mean(-1)
                    for f in files], axis=0)
    fov = float(image_circle(mean, result.camera))
    fov = fov if math.isfinite(fov) and 0 < fov < 2 * math.pi else None
    coverage = assess_coverage(result.camera, result.covariance, data.image_points, fov=fov)
    resampled = leave_one_out(result, data.object_points, data.image_points, fov=fov)
    return {"set": "tests/data/ocamcalib_fisheye2", "model": "kannala_brandt",
            "views": len(data.names), "rms_px": result.rms, "converged": result.converged,
            "fov_deg": None if fov is None else math.degrees(fov),
            "predicted": coverage.pixel_error, "predicted_rms": coverage.pixel_rms,
            "resampled": resampled.pixel_error,
            "resampled_moves": resampled.moves.tolist(), "verdict_ok": coverage.ok,
            "warnings": coverage.warnings}


def markdown(record: dict) -> str:
    lines = [
        "# Predicted against true calibration error (issue 33)", "",
        f"`{record['command']}`: {record['wall_s']:.0f} s wall on one thread, load "
        f"{record['load']} at the start, {record['load_end']} at the end, commit "
        f"{record['commit']}. Method and definitions: `benchmarks/calibration_uncertainty.py`.",
        "",
        "predicted / true: the median over seeds (quartiles), and the root of mean predicted^2 / "
        "mean true^2; figures in px (medians over seeds); verdict: fits that "
        f"`omniscape-torch fit` passes (thresholds {record['thresholds']}).", "",
        "| lens | views | fits | predicted / true (q25-q75) | rms ratio | in [0.7, 1.4] | "
        "predicted / true px at 0.1, 0.3, 0.5 px noise | verdict ok | jackknife / pixel_rms (fits) |",
        "|---|---|---|---|---|---|---|---|---|"]
    for e in record["table"]:
        jack = (f"{e['resampled_ratio_median']:.2f} ({e['resampled_fits']})"
                if "resampled_ratio_median" in e else "")
        px = ", ".join(f"{e[f'predicted_{n:g}']:.2f} / {e[f'true_{n:g}']:.2f}"
                       for n in NOISES if f"predicted_{n:g}" in e)
        lines.append(
            f"| {e['lens']} | {e['views']} | {e['fits']} | "
            f"{e['ratio_median']:.2f} ({e['ratio_q25']:.2f}-{e['ratio_q75']:.2f}) | "
            f"{e['ratio_rms']:.2f} | {'yes' if e['in_band'] else 'NO'} | {px} | "
            f"{e['verdict_ok']}/{e['fits']} | {jack} |")
    real = record.get("real")
    if real:
        lines += ["", f"Real photographs, {real['set']} ({real['views']} views, "
                  f"{real['model']}, rms {real['rms_px']:.3f} px, image circle "
                  f"{real['fov_deg'] and round(real['fov_deg'], 1)} deg): predicted "
                  f"{real['predicted']:.3f} px (rms {real['predicted_rms']:.3f} px), "
                  f"leave-one-view-out (jackknife) {real['resampled']:.3f} px; verdict "
                  f"{'ok' if real['verdict_ok'] else 'poor'}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 seeds, into results/quick/")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per case (default 40)")
    parser.add_argument("--jackknife", type=int, default=None,
                        help="seeds of the 8- and 21-view cases with leave_one_out (default 4, "
                             "quick 1)")
    args = parser.parse_args(argv)
    seeds = args.seeds or (3 if args.quick else 40)
    jack = args.jackknife if args.jackknife is not None else (1 if args.quick else 4)
    load = begin_run(1)
    start = time.perf_counter()
    rows = []
    for name in LENSES:
        for views in VIEWS:
            for seed in range(seeds):
                rows.append(trial(name, views, seed, views > 3 and seed < jack))
            print(f"{name}, {views} views: done ({time.perf_counter() - start:.0f} s)",
                  file=sys.stderr)
    record = {"benchmark": "calibration_uncertainty",
              "command": "python benchmarks/calibration_uncertainty.py"
              + "".join(f" {a}" for a in (argv if argv is not None else sys.argv[1:])),
              "commit": git_commit()[0], "machine": machine_info(), "load": load,
              "thresholds": dict(THRESHOLDS), "seeds": seeds, "table": summarise(rows),
              "real": real_set(), "rows": rows}
    record["wall_s"] = time.perf_counter() - start
    record["load_end"] = loadavg()
    name = "calibration_uncertainty"
    write_json_atomic(record, results_path(f"{name}.json", quick=args.quick))
    text = markdown(record)
    atomic_write_text(results_path(f"{name}.md", quick=args.quick), text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
