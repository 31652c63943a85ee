"""The ``omniscape-torch`` command line (thin: parsing and printing; the work is in the package).

Angles are printed in degrees (the only place besides file formats where degrees appear).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

#: The real OCamCalib calibration shipped beside the project (see ../shared/data/README.md).
DEFAULT_OCAMCALIB = Path("../shared/data/ocamcalib_real/calib_results_0.txt")


def _load_camera(args: argparse.Namespace):
    from .cameras import Camera
    if args.json is not None:
        return Camera.load_json(args.json), str(args.json)
    path = args.ocamcalib if args.ocamcalib is not None else DEFAULT_OCAMCALIB
    if not path.is_file():
        raise SystemExit(f"omniscape-torch info: no calibration file at {path} (run from the "
                         f"project root, or pass --ocamcalib PATH or --json PATH)")
    return Camera.from_ocamcalib(path), str(path)


def _edge_angle(camera, pixels: torch.Tensor) -> float:
    """Largest angle to the optical axis among valid ``pixels``, degrees."""
    rays, valid = camera.unproject(pixels)
    theta = torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2])
    return math.degrees(float(theta[valid].max())) if bool(valid.any()) else float("nan")


def cmd_info(args: argparse.Namespace) -> int:
    camera, source = _load_camera(args)
    if camera.batch_shape != ():
        raise SystemExit("omniscape-torch info: expected one camera, got a batch")
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="omniscape-torch", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    info = sub.add_parser("info", help="field of view and angular resolution of a camera")
    source = info.add_mutually_exclusive_group()
    source.add_argument("--ocamcalib", type=Path, default=None,
                        help=f"OCamCalib calib_results.txt (default: {DEFAULT_OCAMCALIB})")
    source.add_argument("--json", type=Path, default=None, help="camera JSON (Camera.save_json)")
    info.set_defaults(func=cmd_info)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, TypeError, FileNotFoundError) as err:
        print(f"omniscape-torch {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
