"""The files of a generated dataset that are written once per run, not per frame: the
manifest (``dataset.json``), the vehicle's dynamics (``dynamics.json``, ``dynamics.csv``) and
per camera its intrinsics (``camera.json``), its OCamCalib polynomial model
(``calib_results.txt``, `omniscape_torch.data.ocamcalib`) and its extrinsics; each rewritten
only when its text changes (a rerun keeps their modification times). The layout:
`omniscape_torch.data.format`.
"""

from __future__ import annotations

import csv
import io as _io
import json
import platform
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..cubemap.faces import FACES
from ..io import CLASSES, IGNORE_INDEX, atomic_write_text
from ..io.labels import PALETTE
from ..scenes import ride as _ride
from . import format as fmt
from . import ocamcalib

__all__ = ["FIT_INTRO", "write_run_files"]


def _write_if_changed(path: Path, text: str) -> None:
    """Atomic write, skipped when the file already holds ``text`` (a rerun keeps its mtime)."""
    try:
        if path.read_text(encoding="utf-8") == text:
            return
    except (FileNotFoundError, UnicodeDecodeError):
        pass
    atomic_write_text(path, text)


def _dumps(obj) -> str:
    return json.dumps(obj, indent=2) + "\n"


def _matrix(t: torch.Tensor) -> list:
    return [[float(x) for x in row] for row in t.tolist()]


def _pose(rotation: torch.Tensor, centre: torch.Tensor) -> list:
    t = torch.eye(4, dtype=torch.float64)
    t[:3, :3], t[:3, 3] = rotation, centre
    return _matrix(t)


def _versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version
    try:
        ours = version("omniscape_torch")
    except PackageNotFoundError:  # pragma: no cover - run from a checkout never installed
        ours = "unknown"
    out = {"omniscape_torch": ours, "torch": torch.__version__, "numpy": np.__version__,
           "python": platform.python_version()}
    for name, module in (("pillow", "PIL"), ("opencv", "cv2")):   # cv2: optional
        try:
            out[name] = __import__(module).__version__
        except ImportError:  # pragma: no cover
            pass
    return out


def _dynamics_csv(recs: list[dict]) -> str:
    columns = ["frame", "timestamp"]
    for key in ("location", "velocity", "acceleration", "angular_velocity"):
        columns += [f"{key}_{a}" for a in "xyz"]
    columns += ["rotation_pitch", "rotation_yaw", "rotation_roll", "speed"]
    buf = _io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for r in recs:
        row = [r["frame"], repr(r["timestamp"])]
        for key in ("location", "velocity", "acceleration", "angular_velocity"):
            row += [repr(r[key][a]) for a in "xyz"]
        row += [repr(r["rotation"][a]) for a in ("pitch", "yaw", "roll")]
        row.append(repr(r["speed"]))
        writer.writerow(row)
    return buf.getvalue()


def _read_json(path: Path):
    """The JSON in ``path``, or None when it is missing or unreadable (a file to rewrite)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


#: Said once before the cameras whose OCamCalib model a run fits (the first run in a folder).
FIT_INTRO = (f"{fmt.OCAMCALIB}: each camera written also as OCamCalib's polynomial model (the "
             f"format the OmniScape dataset ships its cameras in; {fmt.CAMERA} holds the exact "
             f"camera), fitted now and kept for later runs:")


def _write_camera_files(name: str, camera, base: Path, fits: dict) -> str | None:
    """``camera.json`` and ``calib_results.txt`` of one camera. The polynomial model is fitted
    once per distinct camera of the run (``fits``: Camera JSON -> fit, shared by the stereo
    pairs) and not at all when the folder already holds the file and its record for this
    camera (a rerun); the file is written before the record that names it. Returns a line
    saying how close the fitted model is to the camera, or None when none was fitted."""
    data = camera.to_dict()
    old = _read_json(base / fmt.CAMERA)
    written = ({k: v for k, v in old.items() if k != "ocamcalib"}
               if isinstance(old, dict) else None)
    record = ocamcalib.cached_record(old.get("ocamcalib") if isinstance(old, dict) else None,
                                     base / fmt.OCAMCALIB, data, written)
    line = None
    if record is None:
        key = json.dumps(data, sort_keys=True)
        if key not in fits:
            fits[key] = ocamcalib.fit_polynomial(camera)
        fit = fits[key]
        record = ocamcalib.write_calib_results(fit, base / fmt.OCAMCALIB)
        line = (f"  {name}: a polynomial of degree {fit.degree}, within {fit.max_px:.3f} px "
                f"of the camera at the pixels the fit did not use (RMS {fit.rms_px:.3f} px)"
                + ("" if fit.within_tolerance else
                   f"; above the {ocamcalib.TOLERANCE_PX} px aimed at: the best of degrees "
                   f"{list(ocamcalib.DEGREES)}"))
    _write_if_changed(base / fmt.CAMERA, _dumps({**data, "ocamcalib": record}))
    return line


def write_run_files(plan, out: Path,
                     log: Callable[[str], None] = lambda msg: None) -> None:
    """Write (or keep, when unchanged) the per-run files of ``plan`` (a ``generate`` plan: its
    configuration, ride, cameras, poses and faces) into ``out``; ``log`` gets a line per
    camera whose OCamCalib model is fitted, after one saying what they are (`FIT_INTRO`)."""
    config = plan.config
    recs = _ride.records(plan.frames)
    _write_if_changed(out / fmt.DYNAMICS, _dumps(recs))
    _write_if_changed(out / fmt.DYNAMICS_CSV, _dynamics_csv(recs))
    cameras = {}
    fits: dict = {}
    fitted = False
    for name, c in plan.cameras.items():
        base = out / name
        base.mkdir(parents=True, exist_ok=True)
        line = _write_camera_files(name, c["camera"], base, fits)
        if line is not None:
            if not fitted:
                log(FIT_INTRO)
            fitted = True
            log(line)
        t_rig = _pose(c["r_cam"], c["position"])
        poses = []
        for k in range(config.frames):
            poses.append({"frame": k,
                          "T_world_camera": _pose(plan.rotation(name, k), plan.centre(name, k)),
                          "faces": [f for f, v in zip(FACES, plan.faces(name, k).tolist())
                                    if v]})
        extr = {"frames": {"rig": "x right, y down, z forward (OpenCV), origin on the ground "
                                  "under the motorcycle's reference point, metres",
                           "world": "x east, y down, z north, metres (town frame; CARLA "
                                    "location (x, y, z) = world (z, x, -y))",
                           "camera": "OpenCV, x right, y down, z forward"},
                "T_rig_camera": t_rig, "face_size": c["face_size"], "poses": poses}
        _write_if_changed(base / "extrinsics.json", _dumps(extr))
        cameras[name] = {"model": c["camera"].model.name,
                         "image_size": list(config.image_size),
                         "face_size": c["face_size"],
                         "position_rig": [float(x) for x in c["position"]],
                         "rotation_rig_camera": _matrix(c["r_cam"])}
    manifest = {"format": fmt.FORMAT, "format_version": fmt.FORMAT_VERSION,
                "config": config.to_dict(), "versions": _versions(),
                "frames": config.frames, "cameras": cameras,
                "classes": list(CLASSES), "ignore_index": IGNORE_INDEX,
                "palette": PALETTE.tolist(),
                "weather_per_frame": [plan.weather(k) for k in range(config.frames)],
                "layout": fmt.layout(config.save_cubemaps, config.save_panorama),
                "conventions": {"depth": "range (Euclidean, along the ray), metres",
                                "angles": "degrees in dynamics.json (CARLA)",
                                "pixels": "(u, v) = (column, row), (0, 0) the centre of the "
                                          "top-left pixel",
                                "boxes": "objects/*.json: XYXY corners, pixel columns u0..u1 "
                                         "and rows v0..v1 -> [u0, v0, u1 + 1, v1 + 1]",
                                "instances": "16-bit ids, 0 none; the same object keeps its "
                                             "id in every frame and camera"}}
    _write_if_changed(out / fmt.MANIFEST, _dumps(manifest))
