"""The ``omniscape-torch`` command line (thin: parsing and printing; the work is in the package).

Angles are printed in degrees (the only place besides file formats where degrees appear).

Every error ends the command with one line on stderr and an exit code (``--traceback`` shows
the Python traceback instead): 2 for bad input (options, files that are missing or malformed),
1 for a run that could not be done (an output that cannot be written, memory, another run in
the same folder, a failed fit), 3 for a fit whose views leave the camera poorly constrained
(``fit``: its files are written; ``--accept-coverage`` makes it 0 for poor coverage) or
near-degenerate (``fit``: written, with a line naming the correlated parameters; ``--strict``
refuses it instead: exit 1, nothing written), 130 for Ctrl-C, whose line says what was kept
and whether the same command resumes.
"""

from __future__ import annotations

import argparse
import errno
import math
import shutil
import sys
import tempfile
from pathlib import Path

import torch

#: The real OCamCalib calibration shipped beside the project (see ../shared/data/README.md).
DEFAULT_OCAMCALIB = Path("../shared/data/ocamcalib_real/calib_results_0.txt")


def _load_camera(args: argparse.Namespace):
    from .cameras import Camera
    if args.camera is not None:
        camera = Camera.load(args.camera, args.camera_format, name=args.name)
        return camera, str(args.camera) + ("" if args.name is None else f" ({args.name})")
    if args.camera_format is not None or args.name is not None:
        raise ValueError("--camera-format and --name apply to --camera FILE; give --camera")
    if args.json is not None:
        return Camera.load_json(args.json), str(args.json)
    path = args.ocamcalib if args.ocamcalib is not None else DEFAULT_OCAMCALIB
    if not path.is_file():   # a missing input: exit 2, like any other
        raise FileNotFoundError(f"no calibration file at {path} (run from the project root, "
                                f"or pass --camera PATH, --ocamcalib PATH or --json PATH)")
    return Camera.from_ocamcalib(path), str(path)


def _edge_angle(camera, pixels: torch.Tensor) -> float:
    """Largest angle to the optical axis among valid ``pixels``, degrees."""
    rays, valid = camera.unproject(pixels)
    theta = torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2])
    return math.degrees(float(theta[valid].max())) if bool(valid.any()) else float("nan")


def cmd_info(args: argparse.Namespace) -> int:
    camera, source = _load_camera(args)
    if camera.batch_shape != ():
        raise ValueError(f"{source}: expected one camera, got a batch of "
                         f"{tuple(camera.batch_shape)}")
    h, w = camera.image_size
    names = camera.param_names
    values = camera.params.detach().double().tolist()
    res = camera.angular_resolution()
    per_deg = {k: float(v) * math.pi / 180 for k, v in res.items() if k != "edge_angle"}
    kw = dict(dtype=camera.params.dtype)
    centre_row = torch.stack((torch.arange(w, **kw), torch.full((w,), (h - 1) / 2, **kw)), -1)
    centre_col = torch.stack((torch.full((h,), (w - 1) / 2, **kw), torch.arange(h, **kw)), -1)
    print(f"camera      {source}")
    print(f"model       {camera.model.name}")
    print("params      " + ", ".join(f"{n}={v:.6g}" for n, v in zip(names, values)))
    print(f"image       {w} x {h} pixels (W x H)")
    print("field of view (valid pixels, degrees):")
    print(f"  whole image  {math.degrees(float(camera.field_of_view())):8.2f}")
    print(f"  horizontal   {2 * _edge_angle(camera, centre_row):8.2f}   (through the image centre)")
    print(f"  vertical     {2 * _edge_angle(camera, centre_col):8.2f}")
    print(f"  model limit  {2 * math.degrees(float(camera.max_angle())):8.2f}")
    print("angular resolution (pixels per degree):")
    print(f"  optical axis {per_deg['center']:8.3f}")
    print(f"  edge         {per_deg['edge_coarsest']:8.3f} to {per_deg['edge_finest']:.3f} (coarsest "
          f"to finest direction, {math.degrees(float(res['edge_angle'])):.2f} deg off axis)")
    print(f"  finest       {per_deg['finest']:8.3f}")
    return 0


def _image_size(text: str) -> tuple[int, int]:
    """``N`` (square) or ``HxW`` pixels."""
    parts = text.lower().replace(",", "x").split("x")
    try:
        size = tuple(int(p) for p in parts)
    except ValueError:
        size = ()
    if len(size) == 1:
        size = size * 2
    if len(size) != 2 or min(size) < 8:
        raise argparse.ArgumentTypeError(f"expected N or HxW pixels, each at least 8, got "
                                         f"{text!r}")
    return size


def positive_int(text: str) -> int:
    """``argparse`` type: an int >= 1 (the benchmarks' scripts use it too)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _shard(text: str) -> tuple[int, int]:
    """``argparse`` type: ``K/N``, run K of N (from 0)."""
    from .data.distributed import parse_shard
    try:
        return parse_shard(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err).removeprefix("shard: ")) from None


def _names(choices, what: str):
    def parse(text: str) -> list[str]:
        names = [n.strip() for n in text.split(",") if n.strip()]
        bad = [n for n in names if n not in choices]
        if bad or not names:
            shown = ", ".join(map(repr, bad)) if bad else repr(text)
            raise argparse.ArgumentTypeError(f"unknown {what} {shown}; choose from "
                                             f"{', '.join(choices)}")
        return names
    return parse


#: What to do about an operating-system error, by errno.
_OS_ADVICE = {
    errno.ENOTDIR: "a file is in the way where a folder is needed: choose another path or "
                   "move the file",
    errno.EEXIST: "it already exists: choose another path or remove it",
    errno.EISDIR: "it is a folder, a file was expected: give a file",
    errno.EACCES: "permission denied: choose a folder you can write, or change its permissions",
    errno.EPERM: "operation not permitted: choose a folder you can write, or change its "
                 "permissions",
    errno.EROFS: "the file system is read-only: write to another disk",
    errno.ENOSPC: "no space left on the device: free some space or write to another disk",
    errno.EDQUOT: "disk quota exceeded: free some space or write to another disk",
    errno.ENOENT: "no such file or folder",
    errno.ENAMETOOLONG: "the file name is too long: choose a shorter path",
}

#: What an interrupted command leaves, and how to go on.
_INTERRUPTED = {
    "generate": "the finished frames are kept; the same command resumes the run",
    "convert": "the captures converted so far are complete; the same command converts them "
               "all again",
    "pack": "the shards written so far are whole; the same command writes the rest",
}


def describe_os_error(err: OSError) -> str:
    """One line: the path at fault, what happened and what to do."""
    path = err.filename if err.filename is not None else ""
    what = _OS_ADVICE.get(err.errno) or err.strerror or str(err)
    return f"{path}: {what}" if path else what


def cmd_generate(args: argparse.Namespace) -> int:
    import gc
    import time
    from .data.distributed import TaskErrors
    from .data.format import CONTACT_SHEET
    from .data.generate import DatasetConfig, Interrupted, generate
    from .io.atomic import check_writable

    cameras = [n for group in args.cameras for n in group]
    weather = [n for group in args.weather for n in group]
    config = DatasetConfig(frames=args.frames, fps=args.fps, image_size=args.image_size,
                           face_size=args.face_size, max_face_size=args.max_face_size,
                           cameras=tuple(dict.fromkeys(cameras)),
                           weather=tuple(dict.fromkeys(weather)), seed=args.seed,
                           save_cubemaps=args.save_cubemaps, save_panorama=args.save_panorama,
                           town=args.town, antialias=args.antialias,
                           min_object_pixels=args.min_object_pixels)
    check_writable(args.out)
    start = time.perf_counter()
    try:
        result = generate(args.out, config, workers=args.workers, ray=args.ray,
                          shard=args.shard, format=args.format,
                          frames_per_shard=args.frames_per_shard,
                          progress=None if not args.no_progress else False,
                          log=lambda msg: print(msg, file=sys.stderr))
    except Interrupted as err:
        if args.traceback:
            raise
        print(f"\nomniscape-torch generate: interrupted: {err.kept} of {err.frames} frames kept "
              f"in {err.out}; run the same command again to render the rest", file=sys.stderr)
        # the process ends next: its teardown then skips collecting the objects alive now
        # (torch's: 0.5 s of the 2 s a Ctrl-C may take, measured on 2 busy cores)
        gc.freeze()
        return 130
    except TaskErrors as err:
        print(f"omniscape-torch generate: {len(err.failures)} frame(s) failed (the others are "
              f"written; the same command renders only what is missing):", file=sys.stderr)
        for frame, message in err.failures.items():
            print(f"  frame {frame}: {message}", file=sys.stderr)
        return 1
    sheet = args.out / CONTACT_SHEET
    print(f"wrote {len(result['rendered'])} frame(s), skipped {len(result['skipped'])} "
          f"finished, to {args.out} in {time.perf_counter() - start:.1f} s"
          + (f"; open {sheet} first: one frame of each camera (image, depth, labels, valid "
             f"area), then 'omniscape-torch stats {args.out}' for the class shares"
             if sheet.is_file() else ""))
    return 0


def cmd_pack(args: argparse.Namespace) -> int:
    from .data.shards import pack

    result = pack(args.dir, args.frames_per_shard,
                  progress=None if not args.no_progress else False,
                  log=lambda msg: print(msg, file=sys.stderr))
    print(f"wrote {len(result['written'])} shard(s), {len(result['skipped'])} already there, "
          f"to {args.dir / 'shards'}")
    if result["incomplete"]:
        print(f"omniscape-torch pack: {len(result['incomplete'])} shard(s) not written, their "
              f"frames unfinished ({', '.join(result['incomplete'])}): run generate again, "
              "then pack", file=sys.stderr)
        return 1
    return 0


def cmd_stats(args: argparse.Namespace) -> int:
    from .data.format import STATS, STATS_PLOT
    from .data.stats import PLOT_INSTALL, format_stats, plot_available, stats

    # the chart needs matplotlib (optional): without it, the tables and stats.json all the same
    plot = not args.no_plot and plot_available()
    result = stats(args.dir, plot=plot)
    print(format_stats(result))
    print(f"\nwrote {args.dir / STATS}" + (f" and {args.dir / STATS_PLOT}" if plot else ""))
    if not plot and not args.no_plot:
        print(f"{STATS_PLOT} not drawn (it needs matplotlib): {PLOT_INSTALL}")
    return 0


#: Exit code of a fit whose views do not constrain it (``--accept-coverage`` turns it off).
EXIT_POORLY_CONSTRAINED = 3


def _fit_data(args: argparse.Namespace):
    """The correspondences of ``fit``: the points file, or the corners detected in
    ``--images``; and what to tell the report about them."""
    from .calibration import read_correspondences

    if (args.correspondences is None) == (args.images is None):
        raise ValueError("give a correspondence file or --images DIR (with --board), not "
                         + ("both" if args.images is not None else "neither"))
    if args.images is None:
        if args.board is not None:
            raise ValueError("--board: only with --images (a correspondence file holds its "
                             "target points)")
        return read_correspondences(args.correspondences), str(args.correspondences), None, {}
    from .calibration.detect import detect_corners, image_files, summarize_skipped
    from .calibration.targets import Board

    if args.board is None:
        raise ValueError("--images: also give --board, e.g. checkerboard:9x6:0.03 (inner "
                         "corners cols x rows : square side in metres)")
    board = Board.parse(args.board)
    files = image_files(args.images)
    data = detect_corners(files, board)
    print(f"{board}: found in {len(data.names)} of {len(files)} images of {args.images}")
    for line in summarize_skipped(data.skipped):   # one line per reason
        print(f"  skipped {line}")
    return data, str(args.images), str(board), data.skipped


def _fit_area(args: argparse.Namespace, camera, data, views
              ) -> tuple[float | None, str, str | None]:
    """The full field of view (radians) over which coverage is judged, where it came from, and
    why the image circle was not used: ``--fov``; else the image circle of the images; else
    (not measurable: 0, NaN or an error) the corners' reach (twice the largest angle off axis
    of the detected corners' rays through the fitted camera), or the whole sensor where the
    images are lit to its edges (None: the whole valid image), from ``views``
    (:func:`_view_images`). Measuring the area never turns a finished fit into an error
    (issue 33)."""
    if args.fov is not None:
        return math.radians(args.fov), "--fov", None
    if args.images is None:
        return None, "whole sensor", None
    try:
        from .calibration.convert import image_circle

        if isinstance(views, Exception):
            raise views
        fov = float(image_circle(views.mean(0), camera))
        why = f"it measured {fov:g} rad"
    except Exception as err:   # noqa: BLE001 (any failure of the measurement: fall back)
        fov, why = math.nan, f"{type(err).__name__}: {err}"
    if math.isfinite(fov) and fov >= 2 * math.pi:
        return None, "whole sensor", ("the images are lit to the sensor's edges (the image "
                                      "circle lies beyond the sensor)")
    if math.isfinite(fov) and fov > 0:
        return fov, "image circle", None
    reach = _corners_reach(camera, data) / 2
    if not math.isfinite(reach) or reach <= 0:
        return None, "whole sensor", f"the image circle could not be measured ({why}), nor " \
            "the corners' reach"
    return min(2 * reach, 2 * math.pi), "corners' reach", \
        f"the image circle could not be measured ({why}: a dark centre or border?)"


def _view_images(args: argparse.Namespace, data, camera):
    """``(V, H, W)`` grey levels of up to 8 of the images where the board was found (not a
    corrupt file the detection skipped); None without ``--images``, the error where they
    cannot be read (the measurements that need them fall back)."""
    if args.images is None:
        return None
    try:
        import numpy as np

        from .calibration.detect import image_files
        from .io.images import read_image

        files = [f for f in image_files(args.images)
                 if "_".join(f.stem.split()) in set(data.names)][:8]
        return np.stack([read_image(f).double().numpy().reshape(camera.image_size + (-1,))
                         .mean(-1) for f in files])
    except Exception as err:   # noqa: BLE001 (never lose the fit for a measurement)
        return err


def _fit_blind_cone(camera, data, views) -> float | None:
    """The blind cone (full angle, radians) of the images: the disc about the axis dark in
    every view (``calibration.convert.blind_cone`` of their per-pixel maximum), kept below the
    corners' nearest angle to the axis; None where there is none or it cannot be measured."""
    if views is None or isinstance(views, Exception):
        return None
    try:
        from .calibration.convert import blind_cone

        blind = blind_cone(views.max(0), camera)
    except Exception:   # noqa: BLE001 (a measurement that fails leaves the cone out)
        return None
    angle = _corner_angles(camera, data)
    if angle.numel():
        blind = min(blind, 2 * float(angle.min()))
    return blind if blind > 0 and blind < (camera.fov or 2 * math.pi) else None


def _corner_angles(camera, data) -> torch.Tensor:
    """The angles off axis (radians) of the corners' valid rays through ``camera``."""
    with torch.no_grad():
        rays, valid = camera.unproject(torch.cat(list(data.image_points)).to(
            camera.params.dtype))
        return torch.atan2(rays[..., :2].norm(dim=-1), rays[..., 2])[valid]


def _corners_reach(camera, data) -> float:
    """Twice the largest angle off axis of the corners' rays through ``camera`` (radians; NaN
    where none is valid)."""
    angle = _corner_angles(camera, data)
    return 2 * float(angle.max()) if angle.numel() else math.nan


def cmd_fit(args: argparse.Namespace) -> int:
    from .calibration import fit
    from .calibration.coverage import assess_coverage
    from .calibration.report import write_fit_files
    from .io.atomic import check_writable, publish

    data, source, board, skipped = _fit_data(args)
    check_writable(args.out)
    options = {}
    if args.reject_outliers:   # only where fit has the option (issue 19)
        options = {"reject_outliers": True, "outlier_threshold": args.outlier_threshold}
    result = fit(data.object_points, data.image_points, args.model, data.image_size,
                 method=args.method, degree=args.degree, freeze=args.freeze,
                 fov=None if args.fov is None else math.radians(args.fov), loss=args.loss,
                 loss_scale=args.loss_scale, max_iterations=args.max_iterations,
                 progress=False if args.no_progress else None, **options)
    outliers = getattr(result, "outliers", None) or []
    dropped = sum(len(o) for o in outliers)
    print(f"{args.model} ({args.method}): rms {result.rms:.4f} px over "
          f"{result.num_observations} points in {len(data.names)} views, "
          f"{result.iterations} iterations" + (f", {dropped} outliers dropped" if dropped
                                               else "") + f"; {result.reason}")
    for name, value, std in zip(result.param_names, result.params.tolist(),
                                result.std.tolist()):
        print(f"  {name:6s} {value:16.9g} +- {std:.3g}")
    near_degenerate = not result.converged and result.only_near_degenerate
    if not result.converged and (args.strict or not near_degenerate):
        print(f"omniscape-torch fit: did not converge ({result.reason}); nothing written",
              file=sys.stderr)
        return 1
    views = _view_images(args, data, result.camera)
    fov, fov_source, fov_note = _fit_area(args, result.camera, data, views)
    if fov_note is not None:
        area = "the whole sensor" if fov is None else \
            f"the corners' reach, {math.degrees(fov):.1f} deg"
        print(f"omniscape-torch fit: field of view for coverage: {area}, as {fov_note}; set it "
              f"with --fov DEG", file=sys.stderr)
    coverage = assess_coverage(result.camera, result.covariance, data.image_points, fov=fov)
    if fov is not None:   # camera.json keeps the area judged, for later conversions and exports
        result.camera.fov = max(fov, min(_corners_reach(result.camera, data), 2 * math.pi))
    blind = _fit_blind_cone(result.camera, data, views)
    if blind is not None:
        result.camera.blind_fov = blind
        print(f"blind cone: {math.degrees(blind):.1f} deg about the optical axis, dark in every "
              f"image (a catadioptric camera's own reflection); camera.json keeps it")
    area = "the whole image" if fov is None else f"a {math.degrees(fov):.1f} deg field of view"
    print(f"coverage over {area}: corners in {100 * coverage.cells:.0f}% of the cells, up to "
          f"{math.degrees(coverage.angle):.1f} of {math.degrees(coverage.half_fov):.1f} deg off "
          f"axis; predicted pixel error {coverage.pixel_error:.3g} px (RMS where the corners "
          f"reach, median of its distribution; root mean square {coverage.pixel_rms:.3g}, "
          f"largest per pixel {coverage.max_pixel_std:.3g})")
    resampling = None
    if args.leave_one_out:
        from .calibration.coverage import leave_one_out
        resampling = leave_one_out(result, data.object_points, data.image_points, fov=fov)
        print(f"leave-one-view-out: {resampling.pixel_error:.3g} px (jackknife RMS where the "
              f"corners reach; predicted {coverage.pixel_rms:.3g})")
    # every file into a temporary folder first: a failed writer leaves nothing half-written,
    # and an output that cannot be written (disk full, removed) does not lose the fit
    staging = Path(tempfile.mkdtemp(prefix="omniscape-fit-"))
    try:
        files, report = write_fit_files(staging, result, data, coverage=coverage,
                                        source=source, board=board, skipped=skipped,
                                        write_points=args.images is not None,
                                        fov_source=fov_source, fov_note=fov_note,
                                        resampling=resampling)
        written = publish(files, args.out)
    except OSError as err:
        print(f"omniscape-torch fit: error: {describe_os_error(err)}; the fitted camera is "
              f"kept in {staging}", file=sys.stderr)
        return 1
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    shutil.rmtree(staging, ignore_errors=True)
    print("wrote " + ", ".join(map(str, written)))
    for line in report["warnings"]:
        print(f"omniscape-torch fit: warning: {line}", file=sys.stderr)
    if near_degenerate:
        from .calibration.fit import correlated_pairs

        print(f"omniscape-torch fit: near-degenerate: "
              f"{correlated_pairs(result.near_degenerate)}: these views leave a "
              f"combination of them undetermined (see {Path(args.out) / 'report.md'}); add "
              f"views, freeze one (--freeze), or pass --strict to refuse such a fit",
              file=sys.stderr)
        return EXIT_POORLY_CONSTRAINED
    if not coverage.ok and not args.accept_coverage:
        print(f"omniscape-torch fit: poorly constrained: the views do not pin the camera down "
              f"over the image (see {Path(args.out) / 'report.md'} and uncertainty.png); add "
              f"views, or pass --accept-coverage to accept it", file=sys.stderr)
        return EXIT_POORLY_CONSTRAINED
    limit = coverage.thresholds["max_pixel_error"]
    if resampling is not None and not resampling.pixel_error <= limit \
            and not args.accept_coverage:
        # the views judged by their refits, not the noise model alone (on real photographs the
        # refits move 2 to 5 times more than the residuals predict)
        print(f"omniscape-torch fit: poorly constrained: refits without each view move the "
              f"projections by {resampling.pixel_error:.3g} px (jackknife RMS where the "
              f"corners reach), above {limit:g} px, though the residuals predict "
              f"{coverage.pixel_rms:.3g} px; add views, or pass --accept-coverage to accept "
              f"it", file=sys.stderr)
        return EXIT_POORLY_CONSTRAINED
    return 0


def _conversion_area(args: argparse.Namespace, camera) -> dict:
    """``convert``'s area options from ``--fov`` (degrees) or ``--image`` (its image circle)."""
    from .calibration.convert import image_circle
    from .io.images import read_image

    if args.fov is not None and args.image is not None:
        raise ValueError("--fov and --image both set the converted area; give one")
    if args.image is not None:
        fov = image_circle(read_image(args.image), camera)
        if not 0 < fov <= 2 * math.pi:
            raise ValueError(f"--image: the image circle of {args.image} could not be measured "
                             "(a dark centre or border?); give the field of view with --fov DEG")
        print(f"image circle of {args.image}: {math.degrees(fov):.1f} deg")
        return {"fov": fov}
    return {} if args.fov is None else {"fov": math.radians(args.fov)}


def _rotation_line(rotation: torch.Tensor) -> str:
    """The fitted rotation as an angle about an axis, for the table."""
    from .calibration.params import matrix_to_axis_angle

    r = matrix_to_axis_angle(rotation)
    angle = float(r.norm())
    if angle == 0:
        return "identity"
    axis = ", ".join(f"{float(v):+.3f}" for v in r / angle)
    return f"{math.degrees(angle):.4f} deg about ({axis})"


def cmd_convert_model(args: argparse.Namespace) -> int:
    from .calibration import convert, save_result
    from .calibration.convert import without_affine

    _check_format_options(args)
    camera, source = _load_camera(args)
    area = _conversion_area(args, camera)
    twin = None
    if args.split:
        if camera.model.name != "scaramuzza":
            raise ValueError("--split: the source has no affine term to split off (not an "
                             "OCamCalib camera)")
        twin = without_affine(camera)
    print(f"source {source} ({camera.model.name}); errors on held-out pixels"
          + (f" within {math.degrees(area['fov']) / 2:.1f} deg of the axis" if area else ""))
    print(f"{'model':18s} {'params':>6s} {'max px':>9s} {'rms px':>9s} {'max deg':>9s} "
          f"{'rms deg':>9s} {'outside':>8s}  converged")
    failed = 0
    for model in args.to:
        result = convert(camera, model, degree=args.degree, grid=args.grid, **area)
        print(f"{model:18s} {result.num_params:6d} {result.max_px:9.4f} {result.rms_px:9.4f} "
              f"{math.degrees(result.max_angle):9.5f} {math.degrees(result.rms_angle):9.5f} "
              f"{100 * result.unrepresentable:7.2f}%  "
              f"{'yes' if result.converged else 'NO: ' + result.fit.reason}")
        if not torch.equal(result.rotation, torch.eye(3, dtype=result.rotation.dtype)):
            print(f"{'':18s} rotation source -> target frame: {_rotation_line(result.rotation)}")
        if twin is not None:
            model_part = convert(twin, model, degree=args.degree, grid=args.grid, **area)
            print(f"{'':18s} max px: {model_part.max_px:.4f} the model's (c = 1, d = e = 0), "
                  f"{result.max_px - model_part.max_px:+.4f} the affine term's")
        failed += not result.converged
        if args.format is not None and result.converged:
            _write_format(result, args)
        elif args.out is not None and result.converged:
            save_result(result.camera, result.to_dict(), "conversion", args.out / f"{model}.json")
            if model == "scaramuzza":
                result.camera.to_ocamcalib(args.out / "calib_results.txt")
    if args.out is not None and args.format is None:
        print(f"wrote the converged cameras to {args.out}")
    return 1 if failed else 0


def cmd_select_model(args: argparse.Namespace) -> int:
    from .calibration import save_result
    from .calibration.select import DEFAULT_CANDIDATES, select_model

    camera, source = _load_camera(args)
    area = _conversion_area(args, camera)
    candidates = DEFAULT_CANDIDATES if args.models is None else [
        c for c in DEFAULT_CANDIDATES if c[0] in args.models] + [
        (m, None) for m in args.models if m not in {c[0] for c in DEFAULT_CANDIDATES}]
    selection = select_model(camera, args.rms, max_tolerance=args.max, grid=args.grid,
                             candidates=candidates,
                             progress=None if not args.no_progress else False, **area)
    bound = f"RMS <= {args.rms:g} px" + ("" if args.max is None else f", max <= {args.max:g} px")
    print(f"source {source} ({camera.model.name}); held-out pixel distances; {bound}")
    print(f"{'model':18s} {'params':>6s} {'rms px':>9s} {'max px':>9s} {'outside':>8s}  within")
    for row in selection.table:
        name = row.model + (f"({row.degree})" if row.degree is not None else "")
        verdict = ("yes" if row.within else "not converged" if not row.converged else
                   "no: the area reaches past the model" if row.outside > 0 else "no")
        print(f"{name:18s} {row.num_params:6d} {row.heldout_rms:9.4f} {row.heldout_max:9.4f} "
              f"{100 * row.outside:7.2f}%  {verdict}")
    if selection.best is None:
        print("no model is within the tolerances")
        return 1
    print(f"selected: {selection.best.model}"
          + (f" of degree {selection.best.degree}" if selection.best.degree else ""))
    if args.out is not None:
        save_result(selection.camera, selection.to_dict(), "selection", args.out)
        print(f"wrote {args.out}")
    return 0


def _check_format_options(args: argparse.Namespace) -> None:
    """``--format`` writes one file, ``--out``, of one model (before the slow fit)."""
    from .cameras.export import supported_models

    if args.format is None:
        if args.accept_fov or args.accept_skew:
            raise ValueError("--accept-fov and --accept-skew apply to --format's file; give "
                             "--format")
        return
    if len(args.to) != 1:
        raise ValueError(f"--format writes one file: give one model in --to, got "
                         f"{', '.join(args.to)}")
    if args.out is None:
        raise ValueError("--format needs --out FILE, the file to write")
    if args.to[0] not in supported_models(args.format):
        raise ValueError(f"--to {args.to[0]}: the {args.format} format holds "
                         f"{', '.join(supported_models(args.format))}")


def _write_format(result, args: argparse.Namespace) -> None:
    """The converted camera as ``--format``'s file; an accepted limit is printed as a warning."""
    import warnings

    from .calibration import save_result

    if args.format == "json":   # with the conversion report, as without --format
        save_result(result.camera, result.to_dict(), "conversion", args.out)
    else:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result.camera.save(args.out, args.format, accept_fov=args.accept_fov,
                               accept_skew=args.accept_skew)
        for warning in caught:
            print(f"omniscape-torch convert-model: warning: {warning.message}", file=sys.stderr)
    print(f"wrote {args.out} ({args.format})")


def _add_convert_parser(sub) -> None:
    """``convert`` (angles in degrees)."""
    from .data.captures import CAMERAS
    from .io.carla import LABEL_SETS

    p = sub.add_parser(
        "convert", help="render simulator cubemap captures into fisheye / catadioptric images",
        description="Read DIR/<capture>/{front,back,left,right,up,down}_{rgb,depth,labels}.png "
                    "(CARLA raw depth and semantic images) and write fisheye and catadioptric "
                    "renderings (rgb png, depth exr, labels png) per capture.")
    p.add_argument("--cubemaps", type=Path, required=True, help="folder of capture folders")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--label-set", choices=tuple(LABEL_SETS), default="13",
                   help="the simulator's tag set: 13 (CARLA <= 0.9.9), 23 (0.9.10-0.9.13), "
                        "new (Cityscapes-ordered tags of later versions); default 13")
    p.add_argument("--unknown-label", type=int, default=None,
                   help="class id for tags outside the label set (default: error)")
    p.add_argument("--cameras", nargs="+", choices=CAMERAS, default=list(CAMERAS))
    p.add_argument("--size", type=int, nargs=2, default=(1024, 1024), metavar=("H", "W"),
                   help="output image size (default 1024 1024)")
    p.add_argument("--fisheye-model", default="equidistant",
                   help="fisheye preset model (default equidistant)")
    p.add_argument("--fisheye-fov", type=float, default=190.0, help="degrees (default 190)")
    p.add_argument("--cata-xi", type=float, default=None, help="mirror xi (default 0.9)")
    p.add_argument("--cata-fov", type=float, default=220.0, help="degrees (default 220)")
    p.add_argument("--cata-blind-fov", type=float, default=40.0,
                   help="degrees, 0 for none (default 40)")
    p.add_argument("--cata-looking", choices=("down", "up"), default="down")
    p.add_argument("--depth-output", choices=("range", "z"), default="range")
    p.add_argument("--interpolation", choices=("nearest", "bilinear", "bicubic"),
                   default="bilinear", help="for rgb")
    p.add_argument("--device", default="cpu")
    p.add_argument("--min-object-pixels", type=positive_int, default=1, metavar="N",
                   help="with instance faces, the objects files list the objects of at least "
                        "N pixels (default 1: all; the instance maps keep every id)")
    _add_ray_option(p, "captures")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_convert)


def _add_ray_option(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--ray", nargs="?", const=True, default=None, metavar="ADDRESS",
                   help=f"chunks of {what} as tasks on a Ray cluster: ADDRESS (HOST:PORT of "
                        "its head, or auto), else $RAY_ADDRESS, else the cluster of 'ray "
                        "start' on this machine, else a local one started for the run (needs "
                        "pip install -e \".[ray]\"); the folders must be at the same path "
                        "on every node")


def cmd_convert(args: argparse.Namespace) -> int:
    from .data.captures import ConvertError, convert_captures
    from .io.atomic import check_writable

    failures: dict[str, str] = {}
    check_writable(args.out)
    try:
        results = convert_captures(
            args.cubemaps, args.out, label_set=args.label_set, cameras=tuple(args.cameras),
            image_size=tuple(args.size), fisheye_model=args.fisheye_model,
            fisheye_fov=math.radians(args.fisheye_fov), catadioptric_xi=args.cata_xi,
            catadioptric_fov=math.radians(args.cata_fov),
            catadioptric_blind_fov=(math.radians(args.cata_blind_fov) if args.cata_blind_fov > 0
                                    else None),
            catadioptric_looking=args.cata_looking, depth_output=args.depth_output,
            interpolation=args.interpolation, unknown_label=args.unknown_label,
            device=args.device, ray=args.ray, progress=None if not args.no_progress else False,
            min_object_pixels=args.min_object_pixels)
    except ConvertError as err:
        results, failures = err.results, err.failures
    for capture, paths in results.items():
        print(f"{capture}: {len(paths)} files -> {Path(args.out) / capture}")
    if results:
        print(f"cameras: {Path(args.out) / 'cameras.json'}")
    if failures:
        print(f"convert: {len(failures)} of {len(failures) + len(results)} captures failed "
              "(nothing written for them):", file=sys.stderr)
        for capture, message in failures.items():
            print(f"  {capture}: {message}", file=sys.stderr)
        return 1
    return 0


def _add_camera_source(group, parser) -> None:
    """``--camera FILE [--camera-format F] [--name N]``: any file ``Camera.load`` reads."""
    from .cameras import READ_FORMATS

    group.add_argument("--camera", type=Path, default=None, metavar="FILE",
                       help="a camera file of another tool, recognised from its content: "
                            "OpenCV / Kalibr / ORB-SLAM3 YAML, basalt or Project Aria JSON, "
                            "COLMAP cameras.txt / cameras.bin / sparse folder, OCamCalib, "
                            "this package's JSON")
    parser.add_argument("--camera-format", choices=READ_FORMATS, default=None,
                        help="the format of --camera (default: recognised from the content)")
    parser.add_argument("--name", default=None, help="the camera of a multi-camera --camera "
                        "file (Kalibr cam1, ORB-SLAM3 Camera2, a COLMAP camera id, an Aria "
                        "label; default: the first)")


class _Parser(argparse.ArgumentParser):
    """argparse's parser (its sub-commands' too) whose usage errors are one line, like every
    other error of the command line: the message and where the usage is, exit 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())}; see {self.prog} "
                     f"--help\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="omniscape-torch", description=__doc__.splitlines()[0])
    parser.add_argument("--traceback", action="store_true",
                        help="on an error, show the Python traceback instead of one line")
    sub = parser.add_subparsers(dest="command", required=True)
    info = sub.add_parser("info", help="field of view and angular resolution of a camera")
    source = info.add_mutually_exclusive_group()
    source.add_argument("--ocamcalib", type=Path, default=None,
                        help=f"OCamCalib calib_results.txt (default: {DEFAULT_OCAMCALIB})")
    source.add_argument("--json", type=Path, default=None, help="camera JSON (Camera.save_json)")
    _add_camera_source(source, info)
    info.set_defaults(func=cmd_info)

    from .data.generate import CAMERAS
    from .scenes.town import CARLA_PRESETS, LAYOUTS, WEATHERS
    gen = sub.add_parser("generate", help="write an OmniScape-like dataset (see "
                                          "omniscape_torch/data/format.py for the layout)")
    gen.add_argument("--out", type=Path, required=True, help="dataset folder (created; a "
                     "rerun completes an interrupted run)")
    gen.add_argument("--frames", type=positive_int, default=8, help="frames (default 8)")
    gen.add_argument("--fps", type=_positive_float, default=2.0, help="frames per second "
                     "(default 2)")
    gen.add_argument("--image-size", type=_image_size, default=(256, 256), metavar="N|HxW",
                     help="image size in pixels (default 256)")
    gen.add_argument("--face-size", type=positive_int, default=None, help="cube face size "
                     "for every camera (default: each camera's required_face_size)")
    gen.add_argument("--max-face-size", type=positive_int, default=1024,
                     help="cap on the default face sizes (default 1024)")
    gen.add_argument("--cameras", type=_names(CAMERAS, "camera"), nargs="+",
                     default=[list(CAMERAS)], metavar="NAME[,NAME]",
                     help=f"cameras to render (default all: {', '.join(CAMERAS)})")
    gen.add_argument("--weather", type=_names(tuple(WEATHERS), "weather"), nargs="+",
                     default=[list(CARLA_PRESETS)], metavar="NAME[,NAME]",
                     help=f"weather preset(s), one drawn per frame when several "
                          f"({', '.join(WEATHERS)}; default CARLA's 14: "
                          f"{', '.join(CARLA_PRESETS)})")
    gen.add_argument("--workers", type=positive_int, default=1, help="processes on this "
                     "machine (default 1)")
    _add_ray_option(gen, "frames")
    gen.add_argument("--shard", type=_shard, default=None, metavar="K/N",
                     help="render only run K of N's share of the frames (K from 0; e.g. "
                          "$SLURM_ARRAY_TASK_ID/N): N such runs, at once on any machines, "
                          "write the dataset one run writes")
    gen.add_argument("--format", choices=("folder", "webdataset"), default="folder",
                     help="webdataset: also pack the frames into WebDataset tar shards, "
                          "DIR/shards/shard-NNNNNN.tar (default folder)")
    gen.add_argument("--frames-per-shard", type=positive_int, default=None, metavar="N",
                     help="frames per WebDataset shard (default 16)")
    gen.add_argument("--seed", type=int, default=0, help="town, route and ride seed "
                     "(default 0)")
    gen.add_argument("--town", type=int, choices=sorted(LAYOUTS), default=1,
                     help="the town's layout: " + ", ".join(f"{k} {v}" for k, v in
                                                           LAYOUTS.items()) + " (default 1)")
    gen.add_argument("--antialias", type=positive_int, default=None, metavar="N",
                     help="anti-aliasing: each cube texel on an edge (label, range or colour "
                          "step to a neighbour) the mean of N x N rays over its footprint, and "
                          "each RGB pixel the mean of 2 x 2 rays over its own (labels and depth "
                          "stay the texel and pixel centres'); 1: one ray a texel and a pixel "
                          "(default: 2 for images of at most 512 x 512 pixels, about 2x the "
                          "frame time at 256 for +4 dB RGB PSNR against the pixels' area; "
                          "else 1)")
    gen.add_argument("--min-object-pixels", type=positive_int, default=1, metavar="N",
                     help="the objects files (instance boxes) list the objects of at least N "
                          "pixels (default 1: all; at the default settings 38 %% of the objects "
                          "have 1-2 pixels, 57 %% fewer than 10; the instance maps "
                          "keep every id)")
    gen.add_argument("--save-cubemaps", action="store_true", help="also write the cube faces "
                     "each camera rendered (only those it sees, at its own face size): to "
                     "inspect a frame, not a training source (full cubemaps for "
                     "RandomOmniCamera: ot.scenes' Town.render_cubemap, as in notebooks/02)")
    gen.add_argument("--save-panorama", action="store_true", help="also write an "
                     "equirectangular panorama per frame")
    gen.add_argument("--no-progress", action="store_true", help="no progress bar")
    gen.set_defaults(func=cmd_generate)

    pk = sub.add_parser("pack", help="pack a generated dataset into WebDataset tar shards "
                                     "(DIR/shards/shard-NNNNNN.tar) for streaming into training")
    pk.add_argument("dir", type=Path, help="dataset folder")
    pk.add_argument("--frames-per-shard", type=positive_int, default=None, metavar="N",
                    help="frames per shard (default 16)")
    pk.add_argument("--no-progress", action="store_true", help="no progress bar")
    pk.set_defaults(func=cmd_pack)

    st = sub.add_parser("stats", help="Table I and class shares of a generated dataset")
    st.add_argument("dir", type=Path, help="dataset folder")
    st.add_argument("--no-plot", action="store_true", help="do not write stats.png")
    st.set_defaults(func=cmd_stats)

    _add_convert_parser(sub)

    from .calibration.fit import METHODS
    from .calibration.lm import LOSSES
    from .cameras import MODELS
    from .cameras.export import FORMATS, supported_models
    lenses = [m for m in MODELS if m != "equirectangular"]
    fit = sub.add_parser(
        "fit", help="calibrate a camera from images of a board, or from target points and "
                    "their pixels (file format: omniscape_torch/calibration/files.py)",
        description="Fit a camera model to a board's corners: detected in --images (OpenCV) or "
                    "read from a correspondence file. Writes camera.json, report.json, "
                    "report.md, residuals.png, uncertainty.png (and calib_results.txt for "
                    "scaramuzza, correspondences.txt for --images) into --out, all or none. "
                    f"Exits {EXIT_POORLY_CONSTRAINED} (files written) when the views leave the "
                    "camera poorly constrained (omniscape_torch/calibration/coverage.py), "
                    "unless --accept-coverage, or near-degenerate (parameters that trade "
                    "off, named with their correlation), unless --strict (exit 1, nothing "
                    "written); 1 (nothing written) when the fit failed.")
    fit.add_argument("correspondences", type=Path, nargs="?", default=None,
                     help="correspondence file (or give --images)")
    fit.add_argument("--images", type=Path, default=None, metavar="DIR",
                     help="folder of images of a calibration board (needs --board)")
    fit.add_argument("--board", default=None, metavar="SPEC",
                     help="the board in --images: checkerboard:COLSxROWS:SQUARE (inner corners, "
                          "metres), charuco:COLSxROWS:SQUARE:MARKER[:DICT] (squares, metres, "
                          "ArUco dictionary, default 6X6_250); e.g. checkerboard:9x6:0.03")
    fit.add_argument("--model", choices=lenses, required=True, help="camera model")
    fit.add_argument("--degree", type=positive_int, default=4,
                     help="scaramuzza polynomial degree (default 4)")
    fit.add_argument("--method", choices=METHODS, default="lm", help="default lm")
    fit.add_argument("--loss", choices=tuple(LOSSES), default="linear", help="default linear")
    fit.add_argument("--loss-scale", type=_positive_float, default=1.0,
                     help="robust loss scale, pixels (default 1)")
    fit.add_argument("--reject-outliers", action="store_true",
                     help="drop corners whose residual is an outlier and refit (listed in "
                          "report.json)")
    fit.add_argument("--outlier-threshold", type=_positive_float, default=3.0,
                     help="with --reject-outliers: the threshold in sigmas (default 3)")
    fit.add_argument("--freeze", type=lambda t: [n.strip() for n in t.split(",") if n.strip()],
                     default=None, metavar="NAME[,NAME]", help="parameter groups (focal, center, "
                     "distortion, affine) or names to hold at their start")
    fit.add_argument("--fov", type=_positive_float, default=None,
                     help="full field of view in degrees: a start for non-polynomial models, "
                          "and the area whose coverage is judged (default: the image circle "
                          "of --images, else the whole image)")
    fit.add_argument("--accept-coverage", action="store_true",
                     help=f"exit 0, not {EXIT_POORLY_CONSTRAINED}, when the views leave the "
                          f"camera poorly constrained (the warnings are still printed)")
    fit.add_argument("--leave-one-out", action="store_true",
                     help="also refit without each view in turn and report how far the "
                          "projections move (report.json \"resampling\"): a check of the "
                          "predicted error on real photographs (one more fit per view); "
                          f"above the limit, exit {EXIT_POORLY_CONSTRAINED} as for coverage")
    fit.add_argument("--strict", action="store_true",
                     help="refuse a near-degenerate fit (exit 1, nothing written) instead of "
                          f"writing it with exit {EXIT_POORLY_CONSTRAINED}")
    fit.add_argument("--max-iterations", type=positive_int, default=None)
    fit.add_argument("--out", type=Path, required=True, help="output folder")
    fit.add_argument("--no-progress", action="store_true", help="no progress bar")
    fit.set_defaults(func=cmd_fit)

    conv = sub.add_parser("convert-model", help="fit cameras of other models to a camera")
    source = conv.add_mutually_exclusive_group()
    source.add_argument("--ocamcalib", type=Path, default=None,
                        help=f"OCamCalib calib_results.txt (default: {DEFAULT_OCAMCALIB})")
    source.add_argument("--json", type=Path, default=None, help="camera JSON (Camera.save_json)")
    _add_camera_source(source, conv)
    conv.add_argument("--to", type=_names(lenses, "model"), required=True,
                      metavar="MODEL[,MODEL]", help=f"target models ({', '.join(lenses)})")
    conv.add_argument("--degree", type=positive_int, default=4,
                      help="scaramuzza target degree (default 4)")
    conv.add_argument("--grid", type=positive_int, default=48,
                      help="samples per image side (default 48)")
    conv.add_argument("--fov", type=_positive_float, default=None,
                      help="convert within this full field of view, degrees (default: the "
                           "source's fov, else its whole valid area)")
    conv.add_argument("--image", type=Path, default=None,
                      help="a photograph from the source camera: convert within its image "
                           "circle")
    conv.add_argument("--split", action="store_true",
                      help="also report the maximum error of the source without its affine "
                           "term (OCamCalib c = 1, d = e = 0): the model's part and the "
                           "affine term's")
    conv.add_argument("--out", type=Path, default=None, help="folder for <model>.json; with "
                      "--format, the file to write")
    conv.add_argument("--format", choices=FORMATS, default=None,
                      help="write the one model of --to as this tool's file (--out FILE): "
                           + "; ".join(f"{f}: {', '.join(supported_models(f))}"
                                       for f in FORMATS if f != "json") + "; json: any")
    conv.add_argument("--accept-fov", action="store_true", help="write a camera that sees at or "
                      "past 90 deg into a format that folds there (the file records it)")
    conv.add_argument("--accept-skew", action="store_true", help="write a camera with a skew "
                      "into a format without one, dropping it (the error is printed)")
    conv.set_defaults(func=cmd_convert_model)

    sel = sub.add_parser("select-model", help="the model with the fewest parameters that "
                                              "reproduces a camera within tolerances")
    source = sel.add_mutually_exclusive_group()
    source.add_argument("--ocamcalib", type=Path, default=None,
                        help=f"OCamCalib calib_results.txt (default: {DEFAULT_OCAMCALIB})")
    source.add_argument("--json", type=Path, default=None, help="camera JSON (Camera.save_json)")
    _add_camera_source(source, sel)
    sel.add_argument("--models", type=_names(lenses, "model"), default=None,
                     metavar="MODEL[,MODEL]", help="candidates (default: all lens models; "
                     "scaramuzza of degrees 2-6)")
    sel.add_argument("--rms", type=_positive_float, required=True,
                     help="largest held-out RMS pixel distance")
    sel.add_argument("--max", type=_positive_float, default=None,
                     help="largest held-out pixel distance (default: no bound)")
    sel.add_argument("--fov", type=_positive_float, default=None,
                     help="select within this full field of view, degrees")
    sel.add_argument("--image", type=Path, default=None,
                     help="a photograph from the camera: select within its image circle")
    sel.add_argument("--grid", type=positive_int, default=32,
                     help="samples per image side (default 32)")
    sel.add_argument("--out", type=Path, default=None, help="write the selected camera as JSON")
    sel.add_argument("--no-progress", action="store_true", help="no progress bar")
    sel.set_defaults(func=cmd_select_model)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code (module docstring)."""
    args = build_parser().parse_args(argv)
    prefix = f"omniscape-torch {args.command}"
    try:
        return args.func(args)
    except KeyboardInterrupt:
        if args.traceback:
            raise
        print(f"\n{prefix}: interrupted; "
              f"{_INTERRUPTED.get(args.command, 'nothing was written')}", file=sys.stderr)
        return 130
    except Exception as err:   # noqa: BLE001 - every error becomes one line and a code
        if args.traceback:
            raise
        if isinstance(err, FileNotFoundError):   # a missing input
            message, code = describe_os_error(err) if err.errno else str(err), 2
        elif isinstance(err, OSError):
            message, code = describe_os_error(err), 1
        elif isinstance(err, (ValueError, TypeError)):
            message, code = str(err), 2
        elif isinstance(err, MemoryError):
            message, code = str(err) or "out of memory", 1
        elif isinstance(err, ImportError):   # an optional dependency; the message says which
            message, code = str(err), 1
        else:
            message, code = f"{type(err).__name__}: {err}", 1
        print(f"{prefix}: error: {' '.join(message.split())}", file=sys.stderr)
        return code


if __name__ == "__main__":
    sys.exit(main())
