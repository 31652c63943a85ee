"""Conversion accuracy: real OCamCalib calibrations converted to the other lens models, and the
published conversion figures of other tools next to ours (issue 18, item 4).

**(a) Real OCamCalib files** (``../shared/data/ocamcalib_real/calib_results_0.txt``, whose
image circle ``image_circle`` finds in its photograph ``img0.jpg``, and the five files of
``tests/data/ocamcalib``, which come without photographs: their area is the circle about the
principal point inscribed in the image, twice the smallest angle at the four edge midpoints),
each converted with ``ot.calibration.convert`` over that area to ``kannala_brandt`` and
``double_sphere`` (every target with ``--all-targets``; the shared file always goes to
``kannala_brandt``, ``unified``, ``double_sphere`` and ``eucm``). Per row, on the held-out grid
(``ConversionResult``): the largest and RMS pixel distance, the largest angle, and three
contrasts that show what each part of ``convert`` brings:

* ``affine part``: ``max_px`` (and ``rms_px``) minus that of the same camera with ``c = 1,
  d = e = 0`` (``without_affine``): what OCamCalib's affine term costs once the skew and the
  rotation between frames are fitted (about 0 where the target has a skew);
* ``no skew/rotation``: ``max_px`` with ``rotation=False, skew=False`` (the affine term left to
  the focal lengths alone);
* ``least squares``: ``max_px`` / ``rms_px`` with ``minimax=0`` (no Lawson rounds).

**(b) Anchors**: the source camera of a published conversion figure, rebuilt with the same
parameters and image size, converted with ``convert`` over the same area (``fov`` 180 degrees:
both tools keep the sampled pixels whose ray has ``z > 0``) and scored with the publication's
measure: the **mean** pixel distance ``|target.project(ray) - pixel|`` over the publication's
own sample points, the centres of a ``round(sqrt(n W / H)) x round(sqrt(n H / W))`` grid of
cells over the image (``n = 500``) whose ray has ``z > 0`` (fisheye-tools
``src/geometry/mod.rs`` ``sample_points`` and ``compute_reprojection_error``; Fisheye-Calib-
Adapter ``src/adapter.cpp`` ``sample_points`` and ``evaluate_reprojection_error``). They fit on
those points and report the mean on them; ours fit on their own 48 x 48 grid, so the
publication's points are held out for us. The unified model is scored without its distortion
terms (``k1 = k2 = p1 = p2 = 0``: the UCM the publications convert to). Sources: ``ANCHORS``.

    python benchmarks/conversion_table.py              # full run (about a minute on 1 core)
    python benchmarks/conversion_table.py --quick      # the shared file to kannala_brandt, grid 24

The JSON (``--out``, default ``benchmarks/results/conversion_table.json``) holds every
conversion (``ConversionResult.to_dict()``: parameters, rotation, convergence) and the usual
environment record; the markdown table goes beside it (``.md``) and to stdout.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (ROOT, begin_run, loadavg, results_path, run_record,  # noqa: E402
                    write_json_atomic)

import omniscape_torch as ot  # noqa: E402
from omniscape_torch.calibration import convert  # noqa: E402
from omniscape_torch.calibration.convert import image_circle, without_affine  # noqa: E402
from omniscape_torch.io import atomic_write_text  # noqa: E402
from omniscape_torch.io.images import read_image  # noqa: E402

D = torch.float64
SHARED_FILE = ROOT.parent / "shared" / "data" / "ocamcalib_real" / "calib_results_0.txt"
TESTS_FILES = ROOT / "tests" / "data" / "ocamcalib"
ALL_TARGETS = ("kannala_brandt", "unified", "double_sphere", "eucm")
#: Targets of the files without a photograph: one with a skew, one without.
SOME_TARGETS = ("kannala_brandt", "double_sphere")
#: The unified model as the publications use it (Geyer-Daniilidis / UCM: no distortion terms).
UCM_FREEZE = ("k1", "k2", "p1", "p2")
#: Mark of a figure from a fit that did not claim convergence.
NOT_CONVERGED = "†"

FISHEYE_TOOLS = "amin-abouee/fisheye-tools"
FISHEYE_TOOLS_AT = "be7a1a3"   # "Enhance README documentation", 2025-06-09: the figures' commit
FCA = "eowjd0512/fisheye-calib-adapter"
FCA_AT = "b5b0e82"             # HEAD when read (2025-08-26); the camera file dates from 2024-06

#: Published conversion figures. ``published``: target -> (figure as printed, short citation,
#: full citation), None where no figure could be read; the measure of both tools is the mean
#: pixel distance (module docstring).
ANCHORS = [
    {
        "name": "fisheye-tools: TUM VI cam0 (Kannala-Brandt, 512 x 512)",
        "short": "TUM VI cam0 KB 512 x 512 (fisheye-tools)",
        # samples/kannala_brandt.yaml: TUM VI's 512 x 512 cam0 calibration (Kalibr pinhole-equi)
        "params": [190.97847715128717, 190.9733070521226, 254.93170605935475, 256.8974428996504,
                   0.0034823894022493434, 0.0007150348452162257, -0.0020532361418706202,
                   0.00020293673591811182],
        "image_size": (512, 512),
        "camera_source": f"{FISHEYE_TOOLS} samples/kannala_brandt.yaml @ {FISHEYE_TOOLS_AT}",
        "points": 500,   # examples/all_conversions.rs line 206 @ be7a1a3
        "published": {
            "double_sphere": (0.008, "fisheye-tools README (raw 0.007732)",
                              f"{FISHEYE_TOOLS} README.md @ {FISHEYE_TOOLS_AT} lines 21, 139 "
                              "(lines 22, 163 at HEAD 9ffaf72); raw output 0.007732 px in "
                              f"rust_benchmark_results.txt @ {FISHEYE_TOOLS_AT} line 11"),
            "unified": (0.145, "fisheye-tools README (raw 0.145221)",
                        f"{FISHEYE_TOOLS} README.md @ {FISHEYE_TOOLS_AT} lines 22, 140 (lines "
                        "23, 164 at HEAD 9ffaf72); raw output 0.145221 px in "
                        f"rust_benchmark_results.txt @ {FISHEYE_TOOLS_AT} line 25"),
            "eucm": (0.314, "fisheye-tools README (no raw output)",
                     f"{FISHEYE_TOOLS} README.md @ {FISHEYE_TOOLS_AT} lines 23, 141 (lines 24, "
                     "165 at HEAD 9ffaf72); no raw output in the repository's history (the "
                     "one there, 97.19 px, is an earlier failed run)"),
        },
    },
    {
        "name": "Fisheye-Calib-Adapter: dataset/kalibr/KB.yml (Kannala-Brandt, 752 x 480)",
        "short": "FCA kalibr KB 752 x 480",
        "params": [461.58688085556616, 460.2811732644195, 366.28603126815506, 249.08026891791644,
                   -0.012523386218579752, 0.057836801948828065, -0.08495347810986263,
                   0.04362766880887814],
        "image_size": (480, 752),
        "camera_source": f"{FCA} dataset/kalibr/KB.yml @ {FCA_AT}",
        "points": 500,   # example/config.yml sample_point
        # arXiv 2407.12405's tables could not be read here: no published figure is quoted
        "published": {"double_sphere": None, "unified": None, "eucm": None},
    },
]


def inscribed_fov(camera: ot.Camera) -> float:
    """Twice the smallest angle off the axis at the four edge midpoints through the principal
    point: the circle about the principal point inscribed in the image (radians)."""
    h, w = camera.image_size
    cx, cy = float(camera.params[0]), float(camera.params[1])
    edges = torch.tensor([[cx, -0.5], [cx, h - 0.5], [-0.5, cy], [w - 0.5, cy]], dtype=D)
    rays, valid = camera.unproject(edges)
    if not bool(valid.all()):
        raise ValueError("an edge midpoint is outside the camera's domain")
    return 2 * float(torch.acos(rays[:, 2].clamp(-1, 1)).min())


def real_sources(quick: bool) -> list[dict]:
    """The real files: name, path, camera, area (fov, radians) and how it was found."""
    shared = ot.Camera.from_ocamcalib(SHARED_FILE)
    out = [{"name": "calib_results_0 (shared data)",
            "path": str(SHARED_FILE.relative_to(ROOT.parent)), "camera": shared,
            "area": "image circle (img0.jpg)",
            "fov": image_circle(read_image(SHARED_FILE.with_name("img0.jpg")), shared)}]
    if quick:
        return out
    for path in sorted(TESTS_FILES.glob("*/calib_results*.txt")):
        camera = ot.Camera.from_ocamcalib(path)
        out.append({"name": path.parent.name, "path": str(path.relative_to(ROOT)),
                    "camera": camera, "area": "inscribed circle", "fov": inscribed_fov(camera)})
    return out


def timed_convert(camera, target, **kwargs) -> tuple[object, float]:
    start = time.perf_counter()
    result = convert(camera, target, **kwargs)
    return result, time.perf_counter() - start


def real_rows(sources: list[dict], grid: int, all_targets: bool, quick: bool) -> list[dict]:
    rows = []
    for i, src in enumerate(sources):
        camera, fov = src["camera"], src["fov"]
        targets = ("kannala_brandt",) if quick else (
            ALL_TARGETS if all_targets or i == 0 else SOME_TARGETS)
        for target in targets:
            kw = {"fov": fov, "grid": grid}
            res, seconds = timed_convert(camera, target, **kw)
            twin, _ = timed_convert(without_affine(camera), target, **kw)
            plain, _ = timed_convert(camera, target, rotation=False, skew=False, **kw)
            lsq, _ = timed_convert(camera, target, minimax=0, **kw)
            turn = math.degrees(math.acos(max(-1.0, min(1.0, (float(
                res.rotation.trace()) - 1) / 2))))
            row = {"source": src["name"], "path": src["path"], "area": src["area"],
                   "image_size": list(camera.image_size), "half_angle_deg":
                   math.degrees(fov / 2), "target": target, "seconds": seconds,
                   "max_px": res.max_px, "rms_px": res.rms_px,
                   "max_angle_deg": math.degrees(res.max_angle),
                   "rms_angle_deg": math.degrees(res.rms_angle),
                   "unrepresentable": res.unrepresentable, "rotation_deg": turn,
                   "affine_part_px": res.max_px - twin.max_px,
                   "twin_max_px": twin.max_px, "twin_rms_px": twin.rms_px,
                   "no_skew_rotation_max_px": plain.max_px,
                   "no_skew_rotation_rms_px": plain.rms_px,
                   "least_squares_max_px": lsq.max_px, "least_squares_rms_px": lsq.rms_px,
                   "affine_part_rms_px": res.rms_px - twin.rms_px,
                   "converged": {"defaults": res.converged, "twin": twin.converged,
                                 "no_skew_rotation": plain.converged,
                                 "least_squares": lsq.converged},
                   "reason": {"defaults": res.fit.reason, "twin": twin.fit.reason,
                              "no_skew_rotation": plain.fit.reason,
                              "least_squares": lsq.fit.reason},
                   "result": res.to_dict()}
            rows.append(row)
            print(f"# {src['name']} -> {target}: max {res.max_px:.3f} px, rms "
                  f"{res.rms_px:.3f} px ({seconds:.1f} s)", file=sys.stderr)
    return rows


def publication_points(camera: ot.Camera, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The publications' samples (module docstring): ``(pixels (K, 2), rays (K, 3))``."""
    h, w = camera.image_size
    nx = math.floor(math.sqrt(n * w / h) + 0.5)   # std::round / Rust f64::round (no ties here)
    ny = math.floor(math.sqrt(n * h / w) + 0.5)
    v, u = torch.meshgrid((torch.arange(ny, dtype=D) + 0.5) * h / ny,
                          (torch.arange(nx, dtype=D) + 0.5) * w / nx, indexing="ij")
    pixels = torch.stack((u, v), -1).reshape(-1, 2)
    rays, valid = camera.unproject(pixels)
    keep = valid & (rays[:, 2] > 0)
    return pixels[keep], rays[keep]


def on_points(result, pixels: torch.Tensor, rays: torch.Tensor) -> dict:
    """Mean, RMS and largest pixel distance of ``result``'s camera over given samples."""
    if result.camera is None:
        return {"mean_px": math.nan, "rms_px": math.nan, "max_px": math.nan, "points": 0}
    projected, ok = result.camera.model.project(rays @ result.rotation.T, result.fit.params)
    d = (projected - pixels).norm(dim=-1)[ok]
    return {"mean_px": float(d.mean()), "rms_px": float(d.pow(2).mean().sqrt()),
            "max_px": float(d.max()), "points": int(ok.sum()), "of": len(pixels)}


def anchor_rows(grid: int, quick: bool) -> list[dict]:
    rows = []
    for anchor in ANCHORS[:1] if quick else ANCHORS:
        camera = ot.Camera("kannala_brandt", torch.tensor(anchor["params"], dtype=D),
                           anchor["image_size"])
        pixels, rays = publication_points(camera, anchor["points"])
        for target, published in anchor["published"].items():
            freeze = UCM_FREEZE if target == "unified" else None
            kw = {"fov": math.pi, "grid": grid, "freeze": freeze}
            res, seconds = timed_convert(camera, target, **kw)
            lsq, _ = timed_convert(camera, target, minimax=0, **kw)
            rows.append({
                "source": anchor["name"], "short": anchor["short"],
                "camera_source": anchor["camera_source"], "params": anchor["params"],
                "image_size": list(anchor["image_size"]), "target": target,
                "model_note": "UCM (unified, k1 = k2 = p1 = p2 = 0)" if target == "unified"
                else None,
                "published_mean_px": None if published is None else published[0],
                "published_short": None if published is None else published[1],
                "published_where": None if published is None else published[2],
                "sample_points": len(pixels), "seconds": seconds,
                "defaults": {**on_points(res, pixels, rays), "held_out_max_px": res.max_px,
                             "held_out_rms_px": res.rms_px, "converged": res.converged},
                "least_squares": {**on_points(lsq, pixels, rays),
                                  "held_out_max_px": lsq.max_px,
                                  "held_out_rms_px": lsq.rms_px, "converged": lsq.converged},
                "result": res.to_dict()})
            print(f"# anchor {anchor['short']} -> {target}: mean "
                  f"{rows[-1]['least_squares']['mean_px']:.4f} px (least squares), "
                  f"{len(pixels)} points", file=sys.stderr)
    return rows


def _f(x: float, digits: int = 3) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def markdown(real: list[dict], anchors: list[dict]) -> str:
    lines = ["| source | H x W | area half-angle (deg) | target | max px | RMS px | "
             "max angle (deg) | affine part: max / RMS px | no skew/rotation: max px | "
             "least squares: max / RMS px |",
             "|---|---|---:|---|---:|---:|---:|---:|---:|---:|"]
    for r in real:
        h, w = r["image_size"]
        ok = r["converged"]
        mark = {k: "" if v else NOT_CONVERGED for k, v in ok.items()}
        both = "" if ok["defaults"] and ok["twin"] else NOT_CONVERGED
        lines.append(
            f"| {r['source']} | {h} x {w} | {r['half_angle_deg']:.1f} | {r['target']} | "
            f"{_f(r['max_px'])}{mark['defaults']} | {_f(r['rms_px'])}{mark['defaults']} | "
            f"{_f(r['max_angle_deg'], 4)}{mark['defaults']} | "
            f"{r['affine_part_px']:+.3f} / {r['affine_part_rms_px']:+.3f}{both} | "
            f"{_f(r['no_skew_rotation_max_px'])}{mark['no_skew_rotation']} | "
            f"{_f(r['least_squares_max_px'])} / {_f(r['least_squares_rms_px'])}"
            f"{mark['least_squares']} |")
    lines += ["", f"{NOT_CONVERGED}: a fit involved did not claim convergence (degenerate or "
              "near-degenerate:\n`reason` in the JSON), so `convert` skipped its minimax rounds."]
    lines += ["", "Anchors: mean pixel distance over the publication's own sample points "
              "(z > 0 within a 500-cell grid), area 180 deg.", "",
              "| source | target | points | published mean px | ours, least squares: mean / max "
              "px | ours, defaults: mean / max px | published in |",
              "|---|---|---:|---:|---:|---:|---|"]
    for a in anchors:
        target = "unified (UCM)" if a["target"] == "unified" else a["target"]
        ls, df = a["least_squares"], a["defaults"]
        pub = "not found" if a["published_mean_px"] is None else f"{a['published_mean_px']:g}"
        where = a["published_short"] or "arXiv 2407.12405 (tables not retrieved)"
        mark = {k: "" if v["converged"] else NOT_CONVERGED for k, v in (("ls", ls), ("df", df))}
        lines.append(f"| {a['short']} | {target} | {a['sample_points']} | {pub} | "
                     f"{_f(ls['mean_px'], 4)} / {_f(ls['max_px'])}{mark['ls']} | "
                     f"{_f(df['mean_px'], 4)} / {_f(df['max_px'])}{mark['df']} | {where} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="the shared file to kannala_brandt and one anchor, grid 24")
    parser.add_argument("--grid", type=int, default=None,
                        help="samples per image side of convert's grids (default 48, 24 quick)")
    parser.add_argument("--all-targets", action="store_true",
                        help="every real file to all four targets (default: the shared file)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--out", type=Path,
                        default=None)
    args = parser.parse_args(argv)
    if args.out is None:   # a --quick run never overwrites the full run's
        args.out = results_path("conversion_table.json", quick=args.quick)
    grid = args.grid or (24 if args.quick else 48)
    load_start = begin_run(args.threads)
    start = time.perf_counter()
    real = real_rows(real_sources(args.quick), grid, args.all_targets, args.quick)
    anchors = anchor_rows(grid, args.quick)
    table = markdown(real, anchors)
    record = run_record("conversion_table", torch.device("cpu"), args.threads)
    record.update({"loadavg_start": load_start, "loadavg_end": loadavg(),
                   "wall_seconds": time.perf_counter() - start, "quick": args.quick,
                   "grid": grid, "real": real, "anchors": anchors})
    write_json_atomic(record, args.out)
    header = ("Conversion accuracy (`ot.calibration.convert`, defaults unless said; held-out "
              f"{grid} x {grid} grid). Generated by `benchmarks/conversion_table.py"
              f"{' --quick' if args.quick else ''}`.\n\n")
    atomic_write_text(args.out.with_suffix(".md"), header + table)
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
