"""The work of each `omniscape-torch` sub-command (`cli.py` parses the command line and calls
these). Each imports what it needs inside it, so that importing this module, as the parser
does, loads no torch.
"""

from __future__ import annotations

import argparse
import errno
import math
import sys
from pathlib import Path

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


def _edge_angle(camera, pixels) -> float:
    """Largest angle to the optical axis among valid `pixels` `(N, 2)`, degrees."""
    import torch

    rays, valid = camera.unproject(pixels)
    theta = torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2])
    return math.degrees(float(theta[valid].max())) if bool(valid.any()) else float("nan")


def cmd_info(args: argparse.Namespace) -> int:
    import torch

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
    print("field of view (degrees: twice the largest angle off the optical axis of a valid pixel):")
    print(f"  whole image  {math.degrees(float(camera.field_of_view())):8.2f}   (any pixel, "
          f"corners included: past the lens's image circle, the calibration extrapolated)")
    print(f"  horizontal   {2 * _edge_angle(camera, centre_row):8.2f}   (across the image "
          f"through its centre: a circular fisheye's field of view)")
    print(f"  vertical     {2 * _edge_angle(camera, centre_col):8.2f}")
    print(f"  model limit  {2 * math.degrees(float(camera.max_angle())):8.2f}   (where the "
          f"model, or the camera's fov, ends)")
    print("angular resolution (pixels per degree):")
    print(f"  optical axis {per_deg['center']:8.3f}")
    print(f"  edge         {per_deg['edge_coarsest']:8.3f} to {per_deg['edge_finest']:.3f} (coarsest "
          f"to finest direction, {math.degrees(float(res['edge_angle'])):.2f} deg off axis)")
    print(f"  finest       {per_deg['finest']:8.3f}")
    return 0


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

    cameras = (None if args.cameras is None else
               tuple(dict.fromkeys(n for group in args.cameras for n in group)))
    weather = [n for group in args.weather for n in group]
    config = DatasetConfig(frames=args.frames, fps=args.fps, image_size=args.image_size,
                           face_size=args.face_size, max_face_size=args.max_face_size,
                           cameras=cameras, rig=args.rig,
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
          + ("" if not sheet.is_file() else
             f"; open {sheet} first: one frame of each camera (image and boxes, labels, "
             f"distance, previous image), in WoodScape's layout (docs/datasets.md)"
             if config.rig == "woodscape" else
             f"; open {sheet} first: one frame of each camera (image, depth, labels, valid "
             f"area), then 'omniscape-torch stats {args.out}' for the class shares"))
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


def cmd_export(args: argparse.Namespace) -> int:
    from .data.export import export_dataset

    result = export_dataset(args.format, args.dataset, args.out, classes=args.classes,
                            val_fraction=args.val_fraction, seed=args.seed,
                            cameras=args.cameras, progress=None if not args.no_progress
                            else False)
    images, objects = result["images"], result.get("annotations")
    print(f"wrote {images['train']} train and {images['val']} val image(s)"
          + (f", {objects['train']} + {objects['val']} object(s)" if objects else "")
          + f" as {args.format} to {args.out}")
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
    """The correspondences of `fit`: the points file, or the corners detected in `--images`
    (one line of what was found, one per reason an image was skipped); where they came from;
    the board."""
    if (args.correspondences is None) == (args.images is None):
        raise ValueError("give a correspondence file or --images DIR (with --board), not "
                         + ("both" if args.images is not None else "neither"))
    if args.images is None:
        if args.board is not None:
            raise ValueError("--board: only with --images (a correspondence file holds its "
                             "target points)")
        from .calibration import read_correspondences

        return read_correspondences(args.correspondences), str(args.correspondences), None
    if args.board is None:
        raise ValueError("--images: also give --board, e.g. checkerboard:9x6:0.03 (inner "
                         "corners cols x rows : square side in metres)")
    from .calibration.detect import detect_corners, image_files, summarize_skipped
    from .calibration.targets import Board

    board = Board.parse(args.board)
    files = image_files(args.images)
    data = detect_corners(files, board)
    print(f"{board}: found in {len(data.names)} of {len(files)} images of {args.images}")
    for line in summarize_skipped(data.skipped):   # one line per reason
        print(f"  skipped {line}")
    return data, str(args.images), str(board)


def cmd_fit(args: argparse.Namespace) -> int:
    from .calibration.calibrate import FitNotWritten, calibrate
    from .io.atomic import check_writable

    data, source, board = _fit_data(args)
    check_writable(args.out)
    options = {}
    if args.reject_outliers:   # only where fit has the option (issue 19)
        options = {"reject_outliers": True, "outlier_threshold": args.outlier_threshold}
    run = calibrate(data, args.model, images=args.images,
                    fov=None if args.fov is None else math.radians(args.fov),
                    leave_one_out=args.leave_one_out, strict=args.strict, source=source,
                    board=board, method=args.method, degree=args.degree, freeze=args.freeze,
                    loss=args.loss, loss_scale=args.loss_scale,
                    max_iterations=args.max_iterations,
                    progress=False if args.no_progress else None, **options)
    result, coverage = run.result, run.coverage
    dropped = sum(len(o) for o in result.outliers)
    print(f"{args.model} ({args.method}): rms {result.rms:.4f} px over "
          f"{result.num_observations} points in {len(data.names)} views, "
          f"{result.iterations} iterations" + (f", {dropped} outliers dropped" if dropped
                                               else "") + f"; {result.reason}")
    for name, value in result.params_by_name.items():
        print(f"  {name:6s} {value:16.9g} +- {result.std_by_name[name]:.3g}")
    if run.failed:
        print(f"omniscape-torch fit: did not converge ({result.reason}); nothing written",
              file=sys.stderr)
        return 1
    if run.fov_note is not None:
        area = ("the whole sensor" if run.fov is None
                else f"the corners' reach, {math.degrees(run.fov):.1f} deg")
        print(f"omniscape-torch fit: field of view for coverage: {area}, as {run.fov_note}; "
              f"set it with --fov DEG", file=sys.stderr)
    if run.blind_fov is not None:
        print(f"blind cone: {math.degrees(run.blind_fov):.1f} deg about the optical axis, dark "
              f"in every image (a catadioptric camera's own reflection); camera.json keeps it")
    area = ("the whole image" if run.fov is None
            else f"a {math.degrees(run.fov):.1f} deg field of view")
    if run.fov_source == "corners' reach" and run.fov_note is None:
        area += " (the corners' reach: a correspondence file gives no image circle; --fov DEG)"
    print(f"coverage over {area}: corners in {100 * coverage.cells:.0f}% of the cells, up to "
          f"{math.degrees(coverage.angle):.1f} of {math.degrees(coverage.half_fov):.1f} deg off "
          f"axis; predicted pixel error {coverage.pixel_error:.3g} px (RMS where the corners "
          f"reach, median of its distribution; root mean square {coverage.pixel_rms:.3g}, "
          f"largest per pixel {coverage.max_pixel_std:.3g})")
    if run.resampling is not None:
        print(f"leave-one-view-out: {run.resampling.pixel_error:.3g} px (jackknife RMS where "
              f"the corners reach; predicted {coverage.pixel_rms:.3g})")
    try:
        written, warnings = run.write(args.out)
    except FitNotWritten as err:
        print(f"omniscape-torch fit: error: {describe_os_error(err)}; the fitted camera is "
              f"kept in {err.kept}", file=sys.stderr)
        return 1
    print("wrote " + ", ".join(map(str, written)))
    for line in warnings:
        print(f"omniscape-torch fit: warning: {line}", file=sys.stderr)
    report = Path(args.out) / "report.md"
    refuse = None   # why the views leave the camera poorly constrained, if they do
    if run.near_degenerate:
        refuse = (f"near-degenerate: {run.correlated}: these views leave a combination of them "
                  f"undetermined (see {report}); add views, freeze one (--freeze), or pass "
                  f"--strict to refuse such a fit")
    elif args.accept_coverage:
        return 0
    elif run.poorly_covered:
        refuse = (f"poorly constrained: the views do not pin the camera down over the image "
                  f"(see {report} and uncertainty.png); add views, or pass --accept-coverage "
                  f"to accept it")
    elif run.poorly_resampled:
        # the views judged by their refits, not the noise model alone (on real photographs the
        # refits move 2 to 5 times more than the residuals predict)
        refuse = (f"poorly constrained: refits without each view move the projections by "
                  f"{run.resampling.pixel_error:.3g} px (jackknife RMS where the corners "
                  f"reach), above {run.resampling_limit:g} px, though the residuals predict "
                  f"{coverage.pixel_rms:.3g} px; add views, or pass --accept-coverage to "
                  f"accept it")
    if refuse is None:
        return 0
    print(f"omniscape-torch fit: {refuse}", file=sys.stderr)
    return EXIT_POORLY_CONSTRAINED


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


def _rotation_line(rotation) -> str:
    """The fitted rotation as an angle about an axis, for the table."""
    from .calibration.params import matrix_to_axis_angle

    r = matrix_to_axis_angle(rotation)
    angle = float(r.norm())
    if angle == 0:
        return "identity"
    axis = ", ".join(f"{float(v):+.3f}" for v in r / angle)
    return f"{math.degrees(angle):.4f} deg about ({axis})"


def cmd_convert_model(args: argparse.Namespace) -> int:
    import torch

    from .calibration import convert, save_result
    from .calibration.convert import without_affine

    _check_format_options(args)
    camera, source = _load_camera(args)
    area = _conversion_area(args, camera)
    _check_fold_limit(args, camera, area)
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


def _check_fold_limit(args: argparse.Namespace, camera, area: dict) -> None:
    """`--format F --to M` where F's M cannot hold rays at or past 90 deg: refused before the
    fit when the converted area reaches that far (the converted camera is valid over the
    source's pixels within the area), unless `--accept-fov`."""
    from .cameras.export import fold_limit
    from .cameras.formats import farthest_angle

    why = None if args.format is None else fold_limit(args.format, args.to[0])
    if why is None or args.accept_fov:
        return
    reach = farthest_angle(camera)
    if "fov" in area or camera.fov is not None:
        reach = min(reach, area.get("fov", camera.fov) / 2)
    if math.degrees(reach) >= 90.0:
        raise ValueError(f"--format {args.format}: the {args.to[0]} camera sees up to "
                         f"{math.degrees(reach):.2f} deg off its optical axis (the source's "
                         f"pixels within the converted area), but {why}; convert within less "
                         f"(--fov 178), or pass --accept-fov to write it with valid_angle_deg: "
                         f"90")


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


