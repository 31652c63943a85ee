"""The `omniscape-torch` command line (thin: parsing and printing; each command's work is in
`commands.py`, which calls the package).

Angles are printed in degrees (the only place besides file formats where degrees appear).

Every error ends the command with one line on stderr and an exit code (`--traceback` shows
the Python traceback instead, with the same exit code): 2 for bad input (options, files that
are missing or malformed), 1 for a run that could not be done (an output that cannot be
written, memory, another run in the same folder, a failed fit), 3 for a fit whose views leave
the camera poorly constrained (`fit`: its files are written; `--accept-coverage` makes it 0
for poor coverage) or near-degenerate (`fit`: written, with a line naming the correlated
parameters; `--strict` refuses it instead: exit 1, nothing written), 130 for Ctrl-C, whose
line says what was kept and whether the same command resumes.

The parser is built and the arguments parsed before torch or any module of the package that
needs it is imported (each command imports what it uses), so `--help` and a usage error answer
at once; the names it offers are the tables below, which `tests/test_cli.py` checks against the
package's own.
"""

from __future__ import annotations

import argparse
import math
import sys
import traceback
from pathlib import Path

from .commands import (DEFAULT_OCAMCALIB, EXIT_POORLY_CONSTRAINED, cmd_convert, cmd_convert_model,
                       cmd_export, cmd_fit, cmd_generate, cmd_info, cmd_pack, cmd_select_model,
                       cmd_stats, describe_os_error)


# The names the parser offers, written here rather than imported so that parsing needs no
# torch. tests/test_cli.py compares each with the package's table (named in its comment): a name
# added there fails that test until it is added here.
#: `cameras.MODELS` without `equirectangular` (not a lens).
LENS_MODELS = ("pinhole", "equidistant", "equisolid", "stereographic", "orthographic",
               "kannala_brandt", "unified", "eucm", "double_sphere", "scaramuzza", "fov",
               "division", "opencv", "thin_prism_fisheye", "fisheye624", "woodscape")
#: `cameras.READ_FORMATS`.
READ_FORMATS = ("json", "ocamcalib", "opencv", "kalibr", "basalt", "orbslam3", "colmap", "aria",
                "woodscape")
#: `cameras.export.FORMATS` and `supported_models(format)` (json: every model).
WRITE_FORMATS = {
    "json": ("any",),
    "ocamcalib": ("scaramuzza",),
    "opencv": ("kannala_brandt", "unified", "opencv"),
    "kalibr": ("pinhole", "kannala_brandt", "unified", "double_sphere", "eucm", "fov", "opencv"),
    "basalt": ("pinhole", "kannala_brandt", "unified", "double_sphere", "eucm", "fov"),
    "orbslam3": ("pinhole", "kannala_brandt"),
    "colmap": ("pinhole", "kannala_brandt", "fov", "division", "opencv", "thin_prism_fisheye",
               "fisheye624"),
}
#: `calibration.METHODS`.
FIT_METHODS = ("lm", "lbfgs", "adam", "linear")
#: `calibration.LOSSES`.
FIT_LOSSES = ("linear", "huber", "cauchy")
#: `data.generate.CAMERAS`.
RIG_CAMERAS = ("fisheye_left", "fisheye_right", "catadioptric_left", "catadioptric_right")
#: `data.generate.RIGS`.
RIGS = ("omniscape", "woodscape")
#: `data.woodscape.CAMERAS`.
WOODSCAPE_CAMERAS = ("FV", "MVL", "MVR", "RV")
#: `data.generate.FORMATS`.
DATASET_FORMATS = ("folder", "webdataset")
#: `data.captures.CAMERAS`.
CAPTURE_CAMERAS = ("fisheye", "catadioptric")
#: `scenes.town.CARLA_PRESETS`: CARLA's 14 weathers, the default of `generate --weather`.
CARLA_PRESETS = ("clear_noon", "cloudy_noon", "wet_noon", "wet_cloudy_noon", "mid_rainy_noon",
                 "hard_rain_noon", "soft_rain_noon", "clear_sunset", "cloudy_sunset",
                 "wet_sunset", "wet_cloudy_sunset", "mid_rain_sunset", "hard_rain_sunset",
                 "soft_rain_sunset")
#: `scenes.town.WEATHERS`: CARLA's and the town's own.
WEATHERS = CARLA_PRESETS + ("overcast", "sunset", "night", "fog")
#: `scenes.town.LAYOUTS`.
LAYOUTS = {1: "main street", 2: "crossroads", 3: "blocks"}
#: `io.carla.LABEL_SETS`.
LABEL_SETS = ("13", "23", "new")


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


def _comma_list(text: str) -> list[str]:
    """``argparse`` type: ``NAME[,NAME]``, the non-empty names."""
    return [n.strip() for n in text.split(",") if n.strip()]


def _names(choices, what: str):
    def parse(text: str) -> list[str]:
        names = _comma_list(text)
        bad = [n for n in names if n not in choices]
        if bad or not names:
            shown = ", ".join(map(repr, bad)) if bad else repr(text)
            raise argparse.ArgumentTypeError(f"unknown {what} {shown}; choose from "
                                             f"{', '.join(choices)}")
        return names
    return parse



#: What an interrupted command leaves, and how to go on.
_INTERRUPTED = {
    "generate": "the finished frames are kept; the same command resumes the run",
    "convert": "the captures converted so far are complete; the same command converts them "
               "all again",
    "pack": "the shards written so far are whole; the same command writes the rest",
    "export": "the files written so far are whole; the same command completes the export",
}


#: ``data.export.FORMATS``, written out so that the parser is built without importing torch
#: (a test checks that they agree).
EXPORT_FORMATS = ("coco", "mmseg", "cityscapes", "yolo")


def _add_export_parser(sub) -> None:
    ex = _command(
        sub, "export", cmd_export,
        help="write a generated dataset in a training tool's format (COCO, "
             "mmsegmentation, Cityscapes, YOLO)",
        description="Export a generated dataset's finished frames: coco (instances JSON with "
                    "RLE masks), mmseg (img_dir/ann_dir, metainfo.json), cityscapes "
                    "(leftImg8bit/gtFine in Cityscapes' label ids) or yolo (images/labels, "
                    "data.yaml), split into train and val by frame. A rerun completes an "
                    "interrupted export (layouts: docs/datasets.md).")
    ex.add_argument("format", choices=EXPORT_FORMATS, help="the format to write")
    ex.add_argument("dataset", type=Path, help="dataset folder (written by generate)")
    ex.add_argument("--out", type=Path, required=True, help="export folder (created)")
    ex.add_argument("--classes", type=_comma_list, default=None, metavar="NAME[,NAME]",
                    help="the classes to export, names or ids (default: the instance classes "
                         "Pedestrian, Pole, Vehicle, TrafficSign for coco and yolo; all 13 "
                         "for mmseg and cityscapes); the others are left out (mmseg: 255, "
                         "cityscapes: unlabeled)")
    ex.add_argument("--val-fraction", type=float, default=0.1, metavar="F",
                    help="share of the frames in the val split, in [0, 1) (default 0.1; at "
                         "least one frame when above 0 and the dataset has two)")
    ex.add_argument("--seed", type=int, default=0, help="seed of the split (default 0)")
    ex.add_argument("--cameras", type=_comma_list, default=None, metavar="NAME[,NAME]",
                    help="the cameras to export (default all)")
    _add_progress_option(ex)


def _add_convert_parser(sub) -> None:
    """`convert` (angles in degrees)."""
    p = _command(
        sub, "convert", cmd_convert,
        help="render simulator cubemap captures into fisheye / catadioptric images",
        description="Read DIR/<capture>/{front,back,left,right,up,down}_{rgb,depth,labels}.png "
                    "(CARLA raw depth and semantic images) and write fisheye and catadioptric "
                    "renderings (rgb png, depth exr, labels png) per capture. Guide: "
                    "docs/datasets.md.")
    p.add_argument("--cubemaps", type=Path, required=True, help="folder of capture folders")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--label-set", choices=LABEL_SETS, default="13",
                   help="the simulator's tag set: 13 (CARLA <= 0.9.9), 23 (0.9.10-0.9.13), "
                        "new (Cityscapes-ordered tags of later versions); default 13")
    p.add_argument("--unknown-label", type=int, default=None,
                   help="class id for tags outside the label set (default: error)")
    p.add_argument("--cameras", nargs="+", choices=CAPTURE_CAMERAS, default=list(CAPTURE_CAMERAS),
                   help="the cameras to render each capture into: a forward fisheye, a "
                        "catadioptric camera, or both (default both)")
    p.add_argument("--size", type=int, nargs=2, default=(1024, 1024), metavar=("H", "W"),
                   help="output image size (default 1024 1024)")
    p.add_argument("--fisheye-model", default="equidistant",
                   help="fisheye preset model (default equidistant)")
    p.add_argument("--fisheye-fov", type=float, default=190.0, help="degrees (default 190)")
    p.add_argument("--cata-xi", type=float, default=None, help="mirror xi (default 0.9)")
    p.add_argument("--cata-fov", type=float, default=220.0, help="degrees (default 220)")
    p.add_argument("--cata-blind-fov", type=float, default=40.0,
                   help="degrees, 0 for none (default 40)")
    p.add_argument("--cata-looking", choices=("down", "up"), default="down",
                   help="where the catadioptric camera's axis points: down (the camera under "
                        "its mirror, seeing the ground and the horizon) or up (default down)")
    p.add_argument("--depth-output", choices=("range", "z"), default="range",
                   help="depth written: range, the distance along each pixel's ray, or z, "
                        "along the camera's optical axis; metres (default range)")
    p.add_argument("--interpolation", choices=("nearest", "bilinear", "bicubic"),
                   default="bilinear", help="for rgb (labels are always nearest; default "
                                            "bilinear)")
    p.add_argument("--device", default="cpu",
                   help="torch device to render on, e.g. cpu, cuda, cuda:1 (default cpu)")
    p.add_argument("--min-object-pixels", type=positive_int, default=1, metavar="N",
                   help="with instance faces, the objects files list the objects of at least "
                        "N pixels (default 1: all; the instance maps keep every id)")
    _add_ray_option(p, "captures")
    _add_progress_option(p)


def _command(sub, name: str, func, **kwargs) -> argparse.ArgumentParser:
    """The parser of sub-command ``name`` (``help``, ``description``: ``kwargs``), which runs
    ``func(args)``."""
    parser = sub.add_parser(name, **kwargs)
    parser.set_defaults(func=func)
    return parser


def _add_progress_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_ray_option(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--ray", nargs="?", const=True, default=None, metavar="ADDRESS",
                   help=f"chunks of {what} as tasks on a Ray cluster: ADDRESS (HOST:PORT of "
                        "its head, or auto), else $RAY_ADDRESS, else the cluster of 'ray "
                        "start' on this machine, else a local one started for the run (needs "
                        "pip install -e \".[ray]\"); the folders must be at the same path "
                        "on every node")


def _add_camera_source(parser) -> None:
    """The camera of `info`, `convert-model` and `select-model`: `--ocamcalib`, `--json` or
    `--camera FILE [--camera-format F] [--name N]` (any file `Camera.load` reads)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--ocamcalib", type=Path, default=None,
                       help=f"OCamCalib calib_results.txt (default: {DEFAULT_OCAMCALIB})")
    group.add_argument("--json", type=Path, default=None,
                       help="camera JSON (Camera.save_json, fit's camera.json)")
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


#: The top-level help: what the command does, three examples, the guides.
DESCRIPTION = """Fisheye and catadioptric images from cubemaps: datasets from a built-in
town or simulator captures, camera calibration, conversion between camera models.

examples:
  omniscape-torch generate --out out/demo --frames 8
      a small dataset (four cameras, 256 x 256) from the built-in town
  omniscape-torch fit --images photos --board checkerboard:9x6:0.03 --model kannala_brandt --out calib
      calibrate a camera from photographs of a checkerboard
  omniscape-torch convert-model --json calib/camera.json --to unified,double_sphere --out models/
      fit other camera models to that camera

guides (in the repository and on the documentation site):
  docs/getting-started.md   installation and a first dataset
  docs/datasets.md          generate, stats, pack, convert
  docs/calibration.md       fit, convert-model, select-model, info
  docs/troubleshooting.md   every error message and exit code

exit codes: 0 done; 2 bad input; 1 a run that could not be done; 3 a fit the views leave
poorly constrained (files written); 130 interrupted (Ctrl-C)."""


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser; it imports nothing heavy (module docstring)."""
    parser = _Parser(prog="omniscape-torch", description=DESCRIPTION,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--traceback", action="store_true",
                        help="on an error, also show the Python traceback (same exit code)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                title="commands (omniscape-torch COMMAND --help for each)")
    info = _command(sub, "info", cmd_info,
                    help="field of view and angular resolution of a camera",
                    description="Print a camera's model, parameters, field of view and "
                                "angular resolution. Guide: docs/cameras.md.")
    _add_camera_source(info)
    _add_generate_parser(sub)
    _add_pack_parser(sub)
    _add_stats_parser(sub)
    _add_convert_parser(sub)
    _add_export_parser(sub)
    _add_fit_parser(sub)
    _add_convert_model_parser(sub)
    _add_select_model_parser(sub)
    return parser


def _add_generate_parser(sub) -> None:
    gen = _command(sub, "generate", cmd_generate,
                   help="write an OmniScape-like (or WoodScape-like) dataset "
                        "from the built-in town",
                   description="Render an OmniScape-like dataset (fisheye and "
                               "catadioptric images with depth, labels, instances and "
                               "the vehicle's dynamics) from the built-in town; with "
                               "--rig woodscape, WoodScape's four fisheye cameras on a "
                               "car, in WoodScape's layout. Its layout and options: "
                               "docs/datasets.md.")
    gen.add_argument("--out", type=Path, required=True, help="dataset folder (created; a "
                     "rerun completes an interrupted run)")
    gen.add_argument("--frames", type=positive_int, default=8, help="frames (default 8)")
    gen.add_argument("--fps", type=_positive_float, default=2.0, help="frames per second "
                     "(default 2)")
    gen.add_argument("--rig", choices=RIGS, default="omniscape",
                     help="omniscape: a motorcycle with stereo fisheye and catadioptric cameras, "
                          "OmniScape's layout; woodscape: a car with WoodScape's cameras FV, "
                          "MVL, MVR, RV, WoodScape's layout (rgb_images/, semantic_annotations/, "
                          "box_2d_annotations/, ...; needs OpenCV); default omniscape")
    gen.add_argument("--image-size", type=_image_size, default=None, metavar="N|HxW",
                     help="image size in pixels (default 256; 966x1280 with --rig woodscape)")
    gen.add_argument("--face-size", type=positive_int, default=None, help="cube face size "
                     "for every camera (default: each camera's required_face_size)")
    gen.add_argument("--max-face-size", type=positive_int, default=1024,
                     help="cap on the default face sizes (default 1024)")
    gen.add_argument("--cameras", type=_names(RIG_CAMERAS + WOODSCAPE_CAMERAS, "camera"),
                     nargs="+", default=None, metavar="NAME[,NAME]",
                     help=f"cameras to render (default all the rig's: {', '.join(RIG_CAMERAS)}; "
                          f"with --rig woodscape {', '.join(WOODSCAPE_CAMERAS)})")
    gen.add_argument("--weather", type=_names(WEATHERS, "weather"), nargs="+",
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
    gen.add_argument("--format", choices=DATASET_FORMATS, default="folder",
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
    _add_progress_option(gen)


def _add_pack_parser(sub) -> None:
    pk = _command(sub, "pack", cmd_pack,
                  help="pack a generated dataset into WebDataset tar shards "
                       "(DIR/shards/shard-NNNNNN.tar) for streaming into training",
                  description="Pack a generated dataset into WebDataset tar shards. "
                              "Guide: docs/distributed.md.")
    pk.add_argument("dir", type=Path, help="dataset folder")
    pk.add_argument("--frames-per-shard", type=positive_int, default=None, metavar="N",
                    help="frames per shard (default 16)")
    _add_progress_option(pk)


def _add_stats_parser(sub) -> None:
    st = _command(sub, "stats", cmd_stats,
                  help="Table I and class shares of a generated dataset",
                  description="The paper's Table I (the vehicle's attitude) and the "
                              "class shares of a generated dataset, written to "
                              "DIR/stats.json and DIR/stats.png. Guide: "
                              "docs/datasets.md.")
    st.add_argument("dir", type=Path, help="dataset folder")
    st.add_argument("--no-plot", action="store_true", help="do not write stats.png")


def _add_fit_parser(sub) -> None:
    fit = _command(
        sub, "fit", cmd_fit,
        help="calibrate a camera from images of a board, or from target points and "
             "their pixels",
        description="Fit a camera model to a board's corners: detected in --images (OpenCV) or "
                    "read from a correspondence file (its format: docs/calibration.md). Writes "
                    "camera.json, report.json, report.md, residuals.png, uncertainty.png (and "
                    "calib_results.txt for scaramuzza, correspondences.txt for --images) into "
                    "--out, all or none. "
                    f"Exits {EXIT_POORLY_CONSTRAINED} (files written) when the views leave the "
                    "camera poorly constrained, unless --accept-coverage, or near-degenerate "
                    "(parameters that trade off, named with their correlation), unless "
                    "--strict (exit 1, nothing written); 1 (nothing written) when the fit "
                    "failed. Guide: docs/calibration.md.")
    fit.add_argument("correspondences", type=Path, nargs="?", default=None,
                     help="correspondence file (or give --images)")
    fit.add_argument("--images", type=Path, default=None, metavar="DIR",
                     help="folder of images of a calibration board (needs --board)")
    fit.add_argument("--board", default=None, metavar="SPEC",
                     help="the board in --images: checkerboard:COLSxROWS:SQUARE (inner corners, "
                          "metres), charuco:COLSxROWS:SQUARE:MARKER[:DICT] (squares, metres, "
                          "ArUco dictionary, default 6X6_250); e.g. checkerboard:9x6:0.03")
    fit.add_argument("--model", choices=LENS_MODELS, required=True, help="camera model")
    fit.add_argument("--degree", type=positive_int, default=4,
                     help="scaramuzza polynomial degree (default 4)")
    fit.add_argument("--method", choices=FIT_METHODS, default="lm",
                     help="lm (Levenberg-Marquardt), lbfgs, adam, or linear (OCamCalib's "
                          "closed form, scaramuzza only); default lm")
    fit.add_argument("--loss", choices=FIT_LOSSES, default="linear",
                     help="linear (least squares), or huber or cauchy to weigh down outlying "
                          "corners; default linear")
    fit.add_argument("--loss-scale", type=_positive_float, default=1.0,
                     help="robust loss scale, pixels (default 1)")
    fit.add_argument("--reject-outliers", action="store_true",
                     help="drop corners whose residual is an outlier and refit (listed in "
                          "report.json)")
    fit.add_argument("--outlier-threshold", type=_positive_float, default=3.0,
                     help="with --reject-outliers: the threshold in sigmas (default 3)")
    fit.add_argument("--freeze", type=_comma_list,
                     default=None, metavar="NAME[,NAME]", help="parameter groups (focal, center, "
                     "distortion, affine) or names to hold at their start")
    fit.add_argument("--fov", type=_positive_float, default=None,
                     help="full field of view in degrees: a start for non-polynomial models, "
                          "and the area whose coverage and predicted error are judged "
                          "(default: the image circle of --images, else the corners' reach)")
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
    fit.add_argument("--max-iterations", type=positive_int, default=None, metavar="N",
                     help="a hard limit on the optimiser's iterations (default: lm runs "
                          "rounds of 100 while the cost still falls, at most 1000; lbfgs 500, "
                          "adam 3000); a fit stopped there has not converged: exit 1")
    fit.add_argument("--out", type=Path, required=True, help="output folder")
    _add_progress_option(fit)


def _add_convert_model_parser(sub) -> None:
    conv = _command(sub, "convert-model", cmd_convert_model,
                    help="fit cameras of other models to a camera",
                    description="Fit cameras of other models to a camera over its valid "
                                "area and print their held-out errors; write them as "
                                "JSON or as another tool's file (--format). Guide: "
                                "docs/calibration.md.")
    _add_camera_source(conv)
    conv.add_argument("--to", type=_names(LENS_MODELS, "model"), required=True,
                      metavar="MODEL[,MODEL]", help=f"target models ({', '.join(LENS_MODELS)})")
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
    conv.add_argument("--format", choices=tuple(WRITE_FORMATS), default=None,
                      help="write the one model of --to as this tool's file (--out FILE): "
                           + "; ".join(f"{f}: {', '.join(m)}" for f, m in WRITE_FORMATS.items()))
    conv.add_argument("--accept-fov", action="store_true", help="write a camera that sees at or "
                      "past 90 deg into a format that folds there (the file records it)")
    conv.add_argument("--accept-skew", action="store_true", help="write a camera with a skew "
                      "into a format without one, dropping it (the error is printed)")


def _add_select_model_parser(sub) -> None:
    sel = _command(sub, "select-model", cmd_select_model,
                   help="the model with the fewest parameters that "
                        "reproduces a camera within tolerances",
                   description="Convert a camera to each candidate model and select the "
                               "one with the fewest parameters whose held-out error is "
                               "within the tolerances. Guide: docs/calibration.md.")
    _add_camera_source(sel)
    sel.add_argument("--models", type=_names(LENS_MODELS, "model"), default=None,
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
    _add_progress_option(sel)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit code (module docstring)."""
    args = build_parser().parse_args(argv)
    prefix = f"omniscape-torch {args.command}"
    try:
        return args.func(args)
    except KeyboardInterrupt:
        if args.traceback:
            traceback.print_exc()
        print(f"\n{prefix}: interrupted; "
              f"{_INTERRUPTED.get(args.command, 'nothing was written')}", file=sys.stderr)
        return 130
    except Exception as err:   # noqa: BLE001 - every error becomes one line and a code
        if args.traceback:   # the traceback, then the same line and code as without
            traceback.print_exc()
        message, code = describe_error(err)
        print(f"{prefix}: error: {' '.join(message.split())}", file=sys.stderr)
        return code


def describe_error(err: Exception) -> tuple[str, int]:
    """The message and exit code of an error that ended a command (module docstring)."""
    atomic = sys.modules.get(f"{__package__}.io.atomic")   # not loaded: not its error
    busy = atomic is not None and isinstance(err, atomic.FolderBusyError)
    if isinstance(err, FileNotFoundError):   # a missing input
        return (describe_os_error(err) if err.errno else str(err)), 2
    if isinstance(err, OSError):
        return describe_os_error(err), 1
    if isinstance(err, (ValueError, TypeError)):
        return str(err), 2
    if isinstance(err, MemoryError):
        return str(err) or "out of memory", 1
    if busy or isinstance(err, ImportError):   # their messages say what to do
        return str(err), 1
    return f"{type(err).__name__}: {err}", 1   # unexpected: its class helps a bug report


if __name__ == "__main__":
    sys.exit(main())
