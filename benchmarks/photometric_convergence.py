"""Basin of convergence of photometric calibration (``fit_photometric``) on the built-in scene.

The target is the exact ray cast of ``Town(seed)`` through a known camera (``render_rays``),
independent of the cube sampling; the fit renders the scene's cubemap (face ``--face-size``)
through the layer. Two cameras, ``--size`` pixels square: an equidistant fisheye of 190 degrees
looking along the road, and the catadioptric preset (unified model, xi = 0.9, looking down).
Initial guesses: both focal lengths off by +-e (``--focal-errors``, percent; the sign alternates
over the trials) and the principal point off by ``--centre-errors`` pixels in a seeded random
direction. A fit **succeeds** when both focal lengths end within ``FOCAL_TOL`` (relative) and the
principal point within ``CENTRE_TOL`` pixels of the truth; this is checked against the truth,
apart from the fit's own ``converged`` flag, whose false positives (converged but wrong) are
counted. A second sweep compares the losses (``PHOTOMETRIC_LOSSES``) on a few settings.

Usage::

    python benchmarks/photometric_convergence.py            # reduced: 2 trials per setting
    python benchmarks/photometric_convergence.py --trials 4

Results: JSON (``--out``, default ``benchmarks/results/photometric_convergence.json``) and a
markdown table beside it (``.md``), both written atomically; the table also on stdout.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import git_commit, loadavg, machine_info, write_json_atomic  # noqa: E402
from omniscape_torch import Camera, presets  # noqa: E402
from omniscape_torch.calibration.photometric import (  # noqa: E402
    PHOTOMETRIC_LOSSES,
    fit_photometric,
)
from omniscape_torch.io import atomic_write_text  # noqa: E402
from omniscape_torch.scenes import Town  # noqa: E402

#: Success: relative focal error and principal-point error (pixels) of the result. The fit's
#: floor on this scene is about 0.4 % and 0.1 px (cube resampling against the exact ray cast).
FOCAL_TOL, CENTRE_TOL = 0.01, 0.5
POSITION = (0.0, -1.2, 0.0)  # the centre line at eye height


def cameras(size: int) -> dict[str, tuple[Camera, torch.Tensor]]:
    """The true cameras and their camera-to-cube rotations."""
    fisheye = presets.fisheye((size, size), fov=math.radians(190))
    return {"equidistant_190": (fisheye, torch.eye(3)),
            "catadioptric": presets.catadioptric((size, size))}


def run_fit(cube, target, valid, camera, rotation, focal_err, centre_err, direction, loss):
    """One fit from a guess ``focal_err`` (relative, signed) and ``centre_err`` pixels away."""
    p = camera.params.clone()
    p[:2] *= 1 + focal_err
    p[2] += centre_err * math.cos(direction)
    p[3] += centre_err * math.sin(direction)
    guess = Camera(camera.model, p, camera.image_size, fov=camera.fov,
                   blind_fov=camera.blind_fov)
    start = time.perf_counter()
    result = fit_photometric(cube, target, guess, rotation=rotation, mask=valid, loss=loss,
                             progress=False)
    seconds = time.perf_counter() - start
    fitted, true = result.camera.params, camera.params
    focal = float(((fitted[:2] - true[:2]) / true[:2]).abs().max())
    centre = float(torch.linalg.vector_norm(fitted[2:4] - true[2:4]))
    return {"loss": loss, "focal_err": focal_err, "centre_err_px": centre_err,
            "direction_rad": direction, "final_focal_rel_err": focal,
            "final_centre_err_px": centre, "error": result.error,
            "initial_error": result.initial_error, "converged": result.converged,
            "reason": result.reason, "success": focal < FOCAL_TOL and centre < CENTRE_TOL,
            "seconds": seconds}


def summarise(fits: list[dict]) -> dict:
    ok = [f for f in fits if f["success"]]
    return {
        "n": len(fits),
        "success_rate": len(ok) / len(fits),
        "converged_rate": sum(f["converged"] for f in fits) / len(fits),
        "false_converged": sum(f["converged"] and not f["success"] for f in fits),
        "missed": sum(f["success"] and not f["converged"] for f in fits),
        "median_focal_rel_err_success": statistics.median(
            [f["final_focal_rel_err"] for f in ok]) if ok else None,
        "median_centre_err_px_success": statistics.median(
            [f["final_centre_err_px"] for f in ok]) if ok else None,
        "max_error_success": max(f["error"] for f in ok) if ok else None,
        "min_error_failure": min((f["error"] for f in fits if not f["success"]), default=None),
    }


def sweep(cube, target, valid, camera, rotation, focal_errors, centre_errors, trials, loss,
          gen) -> list[dict]:
    rows = []
    for fe in focal_errors:
        for ce in centre_errors:
            fits = []
            for t in range(trials):
                direction = float(torch.rand((), generator=gen)) * 2 * math.pi
                sign = 1 if t % 2 == 0 else -1
                fits.append(run_fit(cube, target, valid, camera, rotation, sign * fe / 100,
                                    ce, direction, loss))
            rows.append({"focal_err_pct": fe, "centre_err_px": ce, "loss": loss,
                         **summarise(fits), "fits": fits})
    return rows


def markdown(results: dict, args) -> str:
    lines = ["# Photometric calibration: basin of convergence\n",
             f"Town seed {args.seed}, images {args.size} x {args.size}, cube faces "
             f"{args.face_size}, default settings of `fit_photometric`; {args.trials} trials "
             f"per setting (focal error sign alternating, centre error in a random direction). "
             f"Success: both focal lengths within {FOCAL_TOL:.0%} and the centre within "
             f"{CENTRE_TOL} px of the truth. Cells: success rate (fits reported converged).\n"]
    for name, rows in results["basin"].items():
        lines.append(f"\n## {name}, loss charbonnier\n")
        ces = sorted({r["centre_err_px"] for r in rows})
        lines.append("| focal error | " + " | ".join(f"centre {c:g} px" for c in ces) + " |")
        lines.append("|---" * (len(ces) + 1) + "|")
        for fe in sorted({r["focal_err_pct"] for r in rows}):
            cells = [next(r for r in rows if r["focal_err_pct"] == fe and r["centre_err_px"] == c)
                     for c in ces]
            lines.append(f"| +-{fe:g} % | " + " | ".join(
                f"{c['success_rate']:.0%} ({c['converged_rate']:.0%})" for c in cells) + " |")
    lines.append("\n## Losses compared\n")
    lines.append("| camera | loss | fits | success | false converged | missed | median focal "
                 "err (success) | median centre err px (success) | mean s per fit |")
    lines.append("|---|---|---|---|---|---|---|---|---|")
    for name, per_loss in results["losses"].items():
        for loss, rows in per_loss.items():
            fits = [f for r in rows for f in r["fits"]]
            s = summarise(fits)
            fmt = (lambda v, p: "-" if v is None else f"{v:{p}}")  # noqa: E731
            lines.append(f"| {name} | {loss} | {s['n']} | {s['success_rate']:.0%} | "
                         f"{s['false_converged']} | {s['missed']} | "
                         f"{fmt(s['median_focal_rel_err_success'], '.2%')} | "
                         f"{fmt(s['median_centre_err_px_success'], '.2f')} | "
                         f"{statistics.mean(f['seconds'] for f in fits):.2f} |")
    all_fits = [f for rows in results["basin"].values() for r in rows for f in r["fits"]]
    s = summarise(all_fits)
    lines.append(f"\nBasin sweep, all fits: {s['n']}, success {s['success_rate']:.0%}, "
                 f"reported converged {s['converged_rate']:.0%}, false converged "
                 f"{s['false_converged']}, missed {s['missed']}; largest 1 - ZNCC of a success "
                 f"{s['max_error_success']}, smallest of a failure {s['min_error_failure']}.\n")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=128, help="image side, pixels")
    ap.add_argument("--face-size", type=int, default=64)
    ap.add_argument("--focal-errors", default="10,20,30,50", help="percent")
    ap.add_argument("--centre-errors", default="0,15,30", help="pixels")
    ap.add_argument("--loss-focal-errors", default="20", help="percent, loss comparison")
    ap.add_argument("--loss-centre-errors", default="15", help="pixels, loss comparison")
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path,
                    default=ROOT / "benchmarks" / "results" / "photometric_convergence.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    floats = lambda s: [float(x) for x in s.split(",")]  # noqa: E731
    load_start = loadavg()
    start = time.perf_counter()

    town = Town(args.seed)
    position = torch.tensor(POSITION)
    cube = town.render_cubemap(position, face_size=args.face_size)["rgb"]
    results: dict = {"basin": {}, "losses": {}}
    for name, (camera, rotation) in cameras(args.size).items():
        rays, valid = camera.ray_grid()
        target = town.render_rays(position, rays @ rotation.T)["rgb"]
        target = (target * valid.unsqueeze(-1)).permute(2, 0, 1).unsqueeze(0)
        gen = torch.Generator().manual_seed(args.seed)
        common = (cube, target, valid, camera, rotation)
        results["basin"][name] = sweep(*common, floats(args.focal_errors),
                                       floats(args.centre_errors), args.trials, "charbonnier",
                                       gen)
        results["losses"][name] = {
            loss: sweep(*common, floats(args.loss_focal_errors), floats(args.loss_centre_errors),
                        args.trials, loss, torch.Generator().manual_seed(args.seed))
            for loss in PHOTOMETRIC_LOSSES}
        print(f"{name}: done at {time.perf_counter() - start:.0f} s", file=sys.stderr)

    commit, dirty = git_commit()
    data = {"benchmark": "photometric_convergence", "machine": machine_info(torch.device("cpu")),
            "torch": torch.__version__, "commit": commit, "dirty": dirty,
            "threads": args.threads, "seed": args.seed, "size": args.size,
            "face_size": args.face_size, "trials": args.trials, "focal_tol": FOCAL_TOL,
            "centre_tol_px": CENTRE_TOL, "total_s": time.perf_counter() - start,
            "loadavg_start": load_start, "loadavg_end": loadavg(), **results}
    table = markdown(results, args)
    print(table)
    write_json_atomic(data, args.out)
    atomic_write_text(args.out.with_suffix(".md"), table)
    print(f"wrote {args.out} and {args.out.with_suffix('.md')}")
    return data


if __name__ == "__main__":
    main()
