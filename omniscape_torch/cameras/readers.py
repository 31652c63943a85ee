"""Camera files of other tools, read: the inverse of ``export.py``, and Project Aria's.

``Camera.load(path)`` reads one camera, ``ot.cameras.load_all(path)`` every camera of a file
(a dict, name -> ``Camera``, in the file's order); both call the functions here with the camera
class to build (this module imports no ``camera.py``, which imports it). The format is
recognised from the content (``format=`` names it instead); ``name=`` picks one camera of a
multi-camera file, else the first is taken.

=========== ============================== =====================================================
format      file                           models (the tool's name -> the registry's)
=========== ============================== =====================================================
json        this package's camera JSON     every model
ocamcalib   ``calib_results.txt``          scaramuzza
opencv      ``cv2.FileStorage`` YAML       fisheye -> kannala_brandt, omnidir -> unified,
            (``K``/``camera_matrix``,      a pinhole with 4/5/8/12/14 coefficients
            ``D``/``distortion_            (``cv2.calibrateCamera``) -> opencv, or pinhole
            coefficients``, ``xi``); ROS   when they are all zero; ROS's
            ``camera_info`` YAML           ``distortion_model`` equidistant -> fisheye,
                                           plumb_bob / rational_polynomial -> pinhole
kalibr      ``camchain.yaml`` (``cam0``,   pinhole-none/radtan -> pinhole (zero coefficients)
            ``cam1``, ...)                 or opencv; pinhole-equidistant -> kannala_brandt;
                                           pinhole-fov -> fov; omni-radtan/none -> unified;
                                           ds-none -> double_sphere; eucm-none -> eucm
basalt      calibration JSON (``cam0``,    pinhole, kb4 -> kannala_brandt, ucm -> unified,
            ``cam1``, ...)                 ds -> double_sphere, eucm, fov
orbslam3    settings YAML, v1.0            PinHole (``Camera1.fx``...) -> pinhole or opencv
            (``Camera1``, ``Camera2``)     (k1, k2, p1, p2, k3), KannalaBrandt8 ->
            and older (``Camera.fx``)      kannala_brandt, Rectified -> pinhole
colmap      ``cameras.txt``, ``cameras     SIMPLE_PINHOLE, PINHOLE -> pinhole; SIMPLE_RADIAL,
            .bin``, a sparse folder, a     RADIAL, OPENCV, FULL_OPENCV -> opencv;
            ``pycolmap.Camera`` or         OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE,
            ``Reconstruction`` (names:     RADIAL_FISHEYE -> kannala_brandt; SIMPLE_FISHEYE,
            the camera ids)                FISHEYE -> equidistant; FOV -> fov; SIMPLE_DIVISION,
                                           DIVISION -> division; THIN_PRISM_FISHEYE ->
                                           thin_prism_fisheye; RAD_TAN_THIN_PRISM_FISHEYE ->
                                           fisheye624; EUCM -> eucm
aria        Project Aria device            FisheyeRadTanThinPrism (15 values, one focal),
            calibration JSON, or an MPS    Fisheye624 (16), Fisheye62 (11) -> fisheye624;
            ``online_calibration.jsonl``   KannalaBrandtK3 -> kannala_brandt. Size: the
            (its first record); names:     camera's ``ImageSize``, the record's ``ImageSizes``,
            the labels (``camera-rgb``...) else the label's (projectaria_tools)
woodscape   WoodScape / SynWoodScape       radial_poly -> woodscape (the intrinsic part;
            calibration JSON (name: its    ``ot.cameras.read_woodscape`` gives the extrinsic,
            ``name``, ``FV``...)           ``woodscape_files.py``)
=========== ============================== =====================================================

Conventions, converted here and nowhere else (as ``export.py`` does for writing):

* Pixels: COLMAP's ``cx, cy`` are ours + 0.5; every other format is taken as it is: OpenCV,
  Kalibr, basalt, ORB-SLAM3 and Project Aria put the top-left pixel's centre at (0, 0) (Aria's
  "2D image coordinate system conventions" page: pixel (u, v) spans u - 0.5 to u + 0.5).
* Image size: width first in every file; ``(H, W)`` here. ORB-SLAM2-style settings without
  ``Camera.width``/``Camera.height``, or an Aria label of unknown size, need ``image_size=``.
* basalt's ``ucm`` is the unified model in its alpha form: ``xi = alpha / (1 - alpha)``, focal
  lengths divided by ``1 - alpha`` (the inverse of the writer's; equal to the last bit or two).
* The imaged area the writer kept (``export.py``): ``fov_deg`` and ``blind_fov_deg`` keys (full
  angles; under ``cam0`` for Kalibr, in an ``"omniscape_torch"`` object beside basalt's
  ``value0``, ``# fov_deg: ...`` comments in COLMAP's ``cameras.txt``) are read as the camera's
  ``fov`` and ``blind_fov``; a camera recorded as valid below 90 degrees only
  (``valid_angle_deg``) is read with ``fov`` twice that angle at most. ``fov=`` / ``blind_fov=``
  passed by the caller take precedence.

YAML is read with PyYAML (a requirement; OpenCV's ``%YAML:1.0`` header and ``!!opencv-matrix``
tags understood), so no file needs OpenCV to be read. A malformed file, a model the registry lacks, or a
format/model pair with no registry model is a ``ValueError`` of one line naming the file, the
line or key, and what was expected.

Examples:
    >>> import tempfile, pathlib, omniscape_torch as ot
    >>> cam = ot.Camera("double_sphere", [160.0, 161.0, 319.5, 239.5, -0.2, 0.6], (480, 640))
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     path = cam.save(pathlib.Path(tmp) / "camchain.yaml", format="kalibr")
    ...     back = ot.Camera.load(path)
    >>> back.model.name, back.params.tolist() == cam.params.tolist(), back.image_size
    ('double_sphere', True, (480, 640))
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import torch

from . import formats, woodscape_files
from .registry import MODELS

#: The formats ``Camera.load`` and ``load_all`` read (``FORMATS`` and Project Aria's).
READ_FORMATS = ("json", "ocamcalib", "opencv", "kalibr", "basalt", "orbslam3", "colmap", "aria",
                "woodscape")

# COLMAP's models: id -> (name, parameter names), as colmap/sensor/models.h lists them.
_COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", ("f", "cx", "cy")),
    1: ("PINHOLE", ("fx", "fy", "cx", "cy")),
    2: ("SIMPLE_RADIAL", ("f", "cx", "cy", "k")),
    3: ("RADIAL", ("f", "cx", "cy", "k1", "k2")),
    4: ("OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    5: ("OPENCV_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    6: ("FULL_OPENCV", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    7: ("FOV", ("fx", "fy", "cx", "cy", "omega")),
    8: ("SIMPLE_RADIAL_FISHEYE", ("f", "cx", "cy", "k")),
    9: ("RADIAL_FISHEYE", ("f", "cx", "cy", "k1", "k2")),
    10: ("THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4",
                                "sx1", "sy1")),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", ("fx", "fy", "cx", "cy", "k0", "k1", "k2", "k3", "k4",
                                        "k5", "p0", "p1", "s0", "s1", "s2", "s3")),
    12: ("SIMPLE_DIVISION", ("f", "cx", "cy", "k")),
    13: ("DIVISION", ("fx", "fy", "cx", "cy", "k")),
    14: ("SIMPLE_FISHEYE", ("f", "cx", "cy")),
    15: ("FISHEYE", ("fx", "fy", "cx", "cy")),
    16: ("EUCM", ("fx", "fy", "cx", "cy", "alpha", "beta")),
}
_COLMAP_BY_NAME = {name: (i, names) for i, (name, names) in _COLMAP_MODELS.items()}
#: COLMAP's models with no registry model here (its equirectangular camera holds no parameters).
_COLMAP_UNREAD = {17: "EQUIRECTANGULAR"}

#: Project Aria's image sizes (W, H) by label, as projectaria_tools' parseCameraCalibrationFromJson
#: sets them (core/calibration/loader/SensorCalibrationJson.cpp: full-resolution sensors).
_ARIA_SIZES = {"camera-rgb": (2880, 2880), "camera-slam-left": (640, 480),
               "camera-slam-right": (640, 480), "camera-et-left": (640, 480),
               "camera-et-right": (640, 480)}

_OCAM_HEADER = "#polynomial coefficients for the DIRECT mapping function"


# --------------------------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------------------------

def read_all(cls, source, format: str | None = None, *,
             image_size: tuple[int, int] | None = None, dtype: torch.dtype = torch.float64,
             **kwargs) -> dict:
    """Every camera of a file another tool wrote, as ``cls`` (``ot.cameras.load_all``)."""
    return _load_all(cls, source, format, image_size, dtype, kwargs)


def load(cls, source, format: str | None = None, *, name: str | int | None = None,
         image_size: tuple[int, int] | None = None, dtype: torch.dtype = torch.float64,
         **kwargs):
    """One camera of a file (``Camera.load``): the one called ``name``, else the first."""
    cameras = _load_all(cls, source, format, image_size, dtype, kwargs)
    if name is None:
        return next(iter(cameras.values()))
    if str(name) not in cameras:
        raise ValueError(f"{_label(source)}: no camera named {str(name)!r}; the file holds "
                         f"{', '.join(cameras)}")
    return cameras[str(name)]


def detect_format(path: str | Path) -> str:
    """The format of ``path`` (one of ``READ_FORMATS``), recognised from its content.

    Raises:
        ValueError: naming the file and the formats looked for.
    """
    path = Path(path)
    if path.is_dir():
        if any((path / n).is_file() for n in ("cameras.bin", "cameras.txt")):
            return "colmap"
        raise ValueError(f"{path}: a folder without cameras.bin or cameras.txt")
    return _detect(path, *_contents(path))


# --------------------------------------------------------------------------------------------
# Dispatch
# --------------------------------------------------------------------------------------------

def _label(source) -> str:
    return str(source) if isinstance(source, (str, Path)) else type(source).__name__


def _load_all(cls, source, format, image_size, dtype, kwargs) -> dict:
    if format is not None and format not in READ_FORMATS:
        raise ValueError(f"format: expected one of {', '.join(READ_FORMATS)}, got {format!r}")
    build = _Builder(cls, image_size, dtype, kwargs)
    if not isinstance(source, (str, Path)):
        if hasattr(source, "cameras") and hasattr(source, "images"):   # pycolmap.Reconstruction
            build.where = type(source).__name__
            for cid in sorted(source.cameras):
                _pycolmap_camera(build, source.cameras[cid])
            return _nonempty(build, "cameras")
        if all(hasattr(source, a) for a in ("model", "width", "height", "params")):
            build.where = type(source).__name__
            _pycolmap_camera(build, source)
            return build.cameras
        raise TypeError(f"source: expected a path, a pycolmap.Camera or a "
                        f"pycolmap.Reconstruction, got {type(source).__name__}")
    path = Path(source)
    if path.is_dir():
        found = [path / n for n in ("cameras.bin", "cameras.txt") if (path / n).is_file()]
        if not found:
            raise FileNotFoundError(f"{path}: a folder without cameras.bin or cameras.txt (a "
                                    f"COLMAP sparse model folder holds them)")
        path = found[0]
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such camera file")
    build.where = str(path)
    raw, text = _contents(path)
    fmt = format or _detect(path, raw, text)
    if fmt == "ocamcalib":
        build.add("camera", formats.read_ocamcalib(cls, path, dtype=dtype, **kwargs))
        return build.cameras
    if fmt == "colmap" and (text is None or path.suffix == ".bin"):
        _colmap_binary(build, raw)
        return _nonempty(build, "cameras")
    if text is None:
        raise ValueError(f"{path}: not a text file (expected a {fmt} file)")
    if fmt == "colmap":
        _colmap_text(build, text)
    elif fmt in ("opencv", "kalibr", "orbslam3"):
        data = _yaml(path, text)
        {"opencv": _opencv, "kalibr": _kalibr, "orbslam3": _orbslam3}[fmt](build, data)
    else:
        data = _json(path, text)
        if fmt == "json":
            try:
                camera = formats.camera_from_dict(cls, data, dtype=dtype, **kwargs)
            except (ValueError, TypeError) as err:
                raise ValueError(f"{path}: {err}") from None
            build.add("camera", camera)
        else:
            {"basalt": _basalt, "aria": _aria, "woodscape": _woodscape}[fmt](build, data)
    return _nonempty(build, "cameras")


def _nonempty(build, what: str) -> dict:
    if not build.cameras:
        raise ValueError(f"{build.where}: no {what} in the file")
    return build.cameras


def _contents(path: Path) -> tuple[bytes, str | None]:
    raw = path.read_bytes()
    try:
        return raw, raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw, None


def _detect(path: Path, raw: bytes, text: str | None) -> str:
    looked = ("looked for: a COLMAP cameras.bin/cameras.txt, OCamCalib's calib_results.txt, "
              "JSON (this package's, basalt's value0, Aria's CameraCalibrations, WoodScape's "
              "intrinsic/extrinsic), YAML (OpenCV K/camera_matrix, a Kalibr camchain, "
              "ORB-SLAM3 Camera.* settings)")
    if text is None or path.suffix == ".bin":
        if path.suffix == ".bin" or _looks_colmap_binary(raw):
            return "colmap"
        raise ValueError(f"{path}: not a text file, nor a COLMAP cameras.bin ({looked})")
    stripped = text.lstrip()
    if stripped.startswith(_OCAM_HEADER):
        return "ocamcalib"
    if stripped.startswith("{"):
        data = _json(path, text)
        if isinstance(data, dict):
            if isinstance(data.get("value0"), dict) and "intrinsics" in data["value0"]:
                return "basalt"
            if "CameraCalibrations" in data:
                return "aria"
            if "model" in data and "params" in data:
                return "json"
            if woodscape_files.is_woodscape(data):
                return "woodscape"
        raise ValueError(f"{path}: a JSON file of no camera format known here ({looked})")
    lines = [ln.split() for ln in text.splitlines() if ln.strip() and
             not ln.lstrip().startswith("#")]
    if lines and len(lines[0]) >= 4 and (lines[0][1] in _COLMAP_BY_NAME
                                         or lines[0][1] in _COLMAP_UNREAD.values()):
        return "colmap"
    if path.suffix == ".bin" and _looks_colmap_binary(raw):
        return "colmap"
    data = _yaml(path, text)
    if isinstance(data, dict):
        if any(isinstance(v, dict) and "camera_model" in v and "intrinsics" in v
               for v in data.values()):
            return "kalibr"
        if any(str(k).startswith(("Camera.", "Camera1.")) for k in data):
            return "orbslam3"
        if any(k in data for k in _OPENCV_K):
            return "opencv"
    raise ValueError(f"{path}: no camera format recognised ({looked}); pass format=")


def _looks_colmap_binary(raw: bytes) -> bool:
    if len(raw) < 8:
        return False
    (n,) = struct.unpack_from("<Q", raw, 0)
    return 0 < n < 1_000_000 and len(raw) >= 8 + n * 24


class _Builder:
    """Builds cameras, naming the file and the key of any value ``Camera`` refuses."""

    def __init__(self, cls, image_size, dtype, kwargs):
        self.cls, self.image_size, self.dtype, self.kwargs = cls, image_size, dtype, kwargs
        self.cameras: dict = {}
        self.where = ""

    def add(self, name: str, camera) -> None:
        if name in self.cameras:
            raise ValueError(f"{self.where}: two cameras named {name!r}")
        self.cameras[name] = camera

    def model(self, model: str, key: str, what: str) -> str:
        if model not in MODELS:
            raise ValueError(f"{self.where}: {key}: {what} is the {model} model, which this "
                             f"omniscape_torch lacks (its models: {', '.join(MODELS)})")
        return model

    def area(self, data, prefix: str = "") -> dict:
        """``fov`` / ``blind_fov`` (radians) of the ``fov_deg``, ``blind_fov_deg`` and
        ``valid_angle_deg`` keys of ``data`` (a mapping; module docstring)."""
        if not isinstance(data, dict):
            return {}
        deg = {k: None if data.get(k) is None else _number(self, prefix + k, data[k])
               for k in ("fov_deg", "blind_fov_deg", "valid_angle_deg")}
        fovs = [v for v in (deg["fov_deg"], None if deg["valid_angle_deg"] is None
                            else 2 * deg["valid_angle_deg"]) if v is not None]
        out = {} if not fovs else {"fov": math.radians(min(fovs))}
        if deg["blind_fov_deg"] is not None:
            out["blind_fov"] = math.radians(deg["blind_fov_deg"])
        return out

    def make(self, name: str, key: str, model: str, params, size_wh, *, area=None) -> None:
        """``size_wh``: (W, H) from the file, or None; ``area``: ``fov`` / ``blind_fov`` from
        the file (`area`), below the caller's."""
        if self.image_size is not None:
            size = tuple(self.image_size)
        elif size_wh is None:
            raise ValueError(f"{self.where}: {key}: the file gives no image size; pass "
                             f"image_size=(H, W)")
        else:
            size = (size_wh[1], size_wh[0])
        kwargs = dict(self.kwargs)
        for k, v in (area or {}).items():
            kwargs.setdefault(k, v)
        try:
            camera = self.cls(model, torch.tensor(params, dtype=self.dtype), size, **kwargs)
        except (ValueError, TypeError) as err:
            raise ValueError(f"{self.where}: {key}: {err}") from None
        self.add(name, camera)


def _number(build, key: str, value) -> float:
    """A finite float from a file value (PyYAML reads '1e-05' as a string: accepted)."""
    if isinstance(value, bool):
        value = None
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{build.where}: {key}: expected a number, got {value!r}") from None
    if not math.isfinite(out):
        raise ValueError(f"{build.where}: {key}: expected a finite number, got {value!r}")
    return out


def _numbers(build, key: str, values, counts: tuple[int, ...] | None = None) -> list[float]:
    if isinstance(values, dict) and "data" in values:   # a ROS camera_info matrix, untagged
        values = values["data"]
    if isinstance(values, np.ndarray):
        values = values.ravel().tolist()
    if not isinstance(values, (list, tuple)):
        raise ValueError(f"{build.where}: {key}: expected a list of numbers, got {values!r}")
    if counts is not None and len(values) not in counts:
        raise ValueError(f"{build.where}: {key}: expected {' or '.join(map(str, counts))} "
                         f"numbers, got {len(values)}")
    return [_number(build, f"{key}[{i}]", v) for i, v in enumerate(values)]


def _size(build, key: str, values) -> tuple[int, int]:
    """(W, H) as the file writes it."""
    wh = _numbers(build, key, values, (2,))
    if any(v != int(v) or v <= 0 for v in wh):
        raise ValueError(f"{build.where}: {key}: expected [width, height] as positive integers, "
                         f"got {values!r}")
    return int(wh[0]), int(wh[1])


def _get(build, data: dict, key: str, where: str = ""):
    if not isinstance(data, dict) or key not in data:
        raise ValueError(f"{build.where}: {where}{key}: missing (expected by this format)")
    return data[key]


# --------------------------------------------------------------------------------------------
# Parsers: JSON, YAML (PyYAML)
# --------------------------------------------------------------------------------------------

def _json(path: Path, text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        if err.msg == "Extra data" and err.lineno > 1:
            # JSON lines (Aria MPS online_calibration.jsonl): the first record
            return _json(path, text.splitlines()[0])
        raise ValueError(f"{path}, line {err.lineno}: not valid JSON ({err.msg})") from None


def _yaml(path: Path, text: str):
    import yaml   # PyYAML: a requirement
    # OpenCV writes '%YAML:1.0', a directive PyYAML refuses: blanked, keeping line numbers.
    lines = text.splitlines()
    if lines and lines[0].startswith("%YAML:"):
        lines[0] = ""

    class Loader(yaml.SafeLoader):
        pass

    def matrix(loader, node):
        m = loader.construct_mapping(node, deep=True)
        line = node.start_mark.line + 1
        try:
            rows, cols, data = int(m["rows"]), int(m["cols"]), m["data"]
            arr = np.array([float(v) for v in data], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{path}, line {line}: !!opencv-matrix: expected rows, cols and a "
                             f"data list of numbers") from None
        if arr.size != rows * cols:
            raise ValueError(f"{path}, line {line}: !!opencv-matrix: rows x cols = "
                             f"{rows * cols}, but data holds {arr.size} numbers")
        return arr.reshape(rows, cols)

    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", matrix)
    try:
        return yaml.load("\n".join(lines) + "\n", Loader=Loader)  # noqa: S506 (safe subclass)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"{path}, line {mark.line + 1}" if mark is not None else str(path)
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ValueError(f"{where}: not valid YAML ({problem})") from None


# --------------------------------------------------------------------------------------------
# OpenCV
# --------------------------------------------------------------------------------------------

_OPENCV_K = ("K", "camera_matrix", "cameraMatrix")
_OPENCV_D = ("D", "distortion_coefficients", "dist_coeffs", "distCoeffs")


def _opencv(build, data) -> None:
    if not isinstance(data, dict):
        raise ValueError(f"{build.where}: expected a mapping with {' or '.join(_OPENCV_K)}")
    k_key = next((k for k in _OPENCV_K if k in data), None)
    if k_key is None:
        raise ValueError(f"{build.where}: {' / '.join(_OPENCV_K)}: missing (the 3 x 3 camera "
                         f"matrix)")
    d_key = next((k for k in _OPENCV_D if k in data), None)
    K = np.asarray(_numbers(build, k_key, data[k_key], (9,))).reshape(3, 3)
    D = [] if d_key is None else _numbers(build, d_key, data[d_key], (0, 4, 5, 8, 12, 14))
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise ValueError(f"{build.where}: {k_key}: expected [[fx, s, cx], [0, fy, cy], "
                         f"[0, 0, 1]], got {K.tolist()}")
    size = (_number(build, "image_width", _get(build, data, "image_width")),
            _number(build, "image_height", _get(build, data, "image_height")))
    size = _size(build, "image_width/image_height", list(size))
    kind = data.get("camera_model", data.get("model"))
    if kind is None:   # ROS camera_info names its distortion model instead
        kind = {"equidistant": "fisheye", "fisheye": "fisheye", "plumb_bob": "pinhole",
                "rational_polynomial": "pinhole"}.get(data.get("distortion_model"))
    if kind is None:
        kind = "omnidir" if "xi" in data else "pinhole"
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    skew = [s] if s != 0 else []
    angle = build.area(data)
    if kind == "fisheye":
        if len(D) != 4:
            raise ValueError(f"{build.where}: {d_key or 'D'}: the fisheye model takes 4 "
                             f"coefficients (k1..k4), got {len(D)}")
        build.make("camera", k_key, "kannala_brandt", [fx, fy, cx, cy, *D, *skew], size,
                   area=angle)
    elif kind == "omnidir":
        if len(D) != 4:
            raise ValueError(f"{build.where}: {d_key or 'D'}: the omnidir model takes 4 "
                             f"coefficients (k1, k2, p1, p2), got {len(D)}")
        xi = _number(build, "xi", np.asarray(_get(build, data, "xi")).ravel()[0])
        build.make("camera", k_key, "unified", [fx, fy, cx, cy, xi, *D, *skew], size,
                   area=angle)
    elif kind == "pinhole":
        if skew:
            raise ValueError(f"{build.where}: {k_key}: a pinhole camera with a skew "
                             f"(K[0, 1] = {s:g}): no registry model has both (expected 0)")
        if len(D) == 14 and (D[12] or D[13]):
            raise ValueError(f"{build.where}: {d_key}: the tilted-sensor terms tauX, tauY "
                             f"(coefficients 13, 14) have no registry model (expected 0)")
        if not any(D):
            build.make("camera", k_key, "pinhole", [fx, fy, cx, cy], size, area=angle)
            return
        model = build.model("opencv", d_key, "OpenCV's pinhole with distortion")
        coeffs = (D + [0.0] * 12)[:12]
        build.make("camera", d_key, model, [fx, fy, cx, cy, *coeffs], size, area=angle)
    else:
        raise ValueError(f"{build.where}: camera_model: expected fisheye, omnidir or pinhole "
                         f"(cv2.fisheye, cv2.omnidir, cv2.calibrateCamera), got {kind!r}")


# --------------------------------------------------------------------------------------------
# Kalibr
# --------------------------------------------------------------------------------------------

def _kalibr(build, data) -> None:
    if not isinstance(data, dict):
        raise ValueError(f"{build.where}: expected a camchain mapping cam0, cam1, ...")
    for name, cam in data.items():
        if not (isinstance(cam, dict) and "camera_model" in cam):
            continue
        key = f"{name}."
        kind = str(_get(build, cam, "camera_model", key))
        dist = str(cam.get("distortion_model", "none"))
        intr = cam.get("intrinsics")
        coeffs = _numbers(build, key + "distortion_coeffs", cam.get("distortion_coeffs") or [])
        size = _size(build, key + "resolution", _get(build, cam, "resolution", key))
        angle = build.area(cam, key)
        pair = f"{kind}-{dist}"

        def need(n_coeffs: int) -> None:
            if len(coeffs) != n_coeffs:
                raise ValueError(f"{build.where}: {key}distortion_coeffs: {pair} takes "
                                 f"{n_coeffs} coefficients, got {len(coeffs)}")

        if kind == "pinhole":
            fx, fy, cx, cy = _numbers(build, key + "intrinsics", intr, (4,))
            focal = [fx, fy, cx, cy]
            if dist == "none":
                need(0)
            if dist in ("none", "radtan") and not any(coeffs):
                if dist == "radtan":
                    need(4)
                model, params = "pinhole", focal
            elif dist == "radtan":
                need(4)
                model = build.model("opencv", key + "distortion_model", "pinhole-radtan")
                params = focal + coeffs + [0.0] * 8
            elif dist == "equidistant":
                need(4)
                model, params = "kannala_brandt", focal + coeffs
            elif dist == "fov":
                need(1)
                model, params = build.model("fov", key + "distortion_model", "pinhole-fov"), \
                    focal + coeffs
            else:
                model = None
        elif kind == "omni" and dist in ("radtan", "none"):
            xi, fx, fy, cx, cy = _numbers(build, key + "intrinsics", intr, (5,))
            if dist == "radtan":
                need(4)
            model, params = "unified", [fx, fy, cx, cy, xi] + (coeffs or [0.0] * 4)
        elif kind in ("ds", "eucm") and dist == "none":
            a, b, fx, fy, cx, cy = _numbers(build, key + "intrinsics", intr, (6,))
            model = "double_sphere" if kind == "ds" else "eucm"
            params = [fx, fy, cx, cy, a, b]
        else:
            model = None
        if model is None:
            raise ValueError(f"{build.where}: {key}camera_model/distortion_model: {pair} has no "
                             f"registry model (read: pinhole-none/radtan/equidistant/fov, "
                             f"omni-none/radtan, ds-none, eucm-none)")
        build.make(str(name), key + "intrinsics", model, params, size, area=angle)
    if not build.cameras:
        raise ValueError(f"{build.where}: no camera (expected cam0: with camera_model, "
                         f"intrinsics, distortion_model, distortion_coeffs, resolution)")


# --------------------------------------------------------------------------------------------
# basalt
# --------------------------------------------------------------------------------------------

_BASALT = {   # camera_type -> (registry model, basalt's names in our order)
    "pinhole": ("pinhole", ("fx", "fy", "cx", "cy")),
    "kb4": ("kannala_brandt", ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    "ds": ("double_sphere", ("fx", "fy", "cx", "cy", "xi", "alpha")),
    "eucm": ("eucm", ("fx", "fy", "cx", "cy", "alpha", "beta")),
    "fov": ("fov", ("fx", "fy", "cx", "cy", "w")),
    "ucm": ("unified", ("fx", "fy", "cx", "cy", "alpha")),
}


def _basalt(build, data) -> None:
    root = _get(build, data, "value0")
    intrinsics = _get(build, root, "intrinsics", "value0.")
    sizes = root.get("resolution") or []
    if not isinstance(intrinsics, list):
        raise ValueError(f"{build.where}: value0.intrinsics: expected a list of cameras")
    for i, entry in enumerate(intrinsics):
        key = f"value0.intrinsics[{i}]"
        kind = _get(build, entry, "camera_type", key + ".")
        if kind not in _BASALT:
            raise ValueError(f"{build.where}: {key}.camera_type: {kind!r} has no registry model "
                             f"(read: {', '.join(_BASALT)})")
        model, names = _BASALT[kind]
        build.model(model, key + ".camera_type", f"basalt's {kind}")
        values = _get(build, entry, "intrinsics", key + ".")
        params = [_number(build, f"{key}.intrinsics.{n}", _get(build, values, n,
                                                                 f"{key}.intrinsics."))
                  for n in names]
        if kind == "ucm":   # alpha form (basalt's unified_camera.hpp): back to xi
            fx, fy, cx, cy, alpha = params
            if not 0 <= alpha < 1:
                raise ValueError(f"{build.where}: {key}.intrinsics.alpha: expected [0, 1), got "
                                 f"{alpha}")
            params = [fx / (1 - alpha), fy / (1 - alpha), cx, cy, alpha / (1 - alpha),
                      0.0, 0.0, 0.0, 0.0]
        if i >= len(sizes):
            raise ValueError(f"{build.where}: value0.resolution[{i}]: missing (one [width, "
                             f"height] per camera)")
        size = _size(build, f"value0.resolution[{i}]", sizes[i])
        build.make(f"cam{i}", key, model, params, size,
                   area=build.area(data.get("omniscape_torch"), "omniscape_torch."))


# --------------------------------------------------------------------------------------------
# ORB-SLAM3
# --------------------------------------------------------------------------------------------

def _orbslam3(build, data) -> None:
    if not isinstance(data, dict):
        raise ValueError(f"{build.where}: expected ORB-SLAM3 settings (Camera.type, Camera1.fx, "
                         f"...)")
    kind = str(data.get("Camera.type", "PinHole"))
    if kind not in ("PinHole", "KannalaBrandt8", "Rectified"):
        raise ValueError(f"{build.where}: Camera.type: expected PinHole, KannalaBrandt8 or "
                         f"Rectified, got {kind!r}")
    w, h = data.get("Camera.width"), data.get("Camera.height")
    size = None if w is None or h is None else _size(build, "Camera.width/Camera.height", [w, h])
    angle = build.area(data)
    prefixes = [p for p in ("Camera1", "Camera2") if f"{p}.fx" in data] or ["Camera"]
    if prefixes == ["Camera2"]:
        prefixes = ["Camera", "Camera2"]   # the older stereo format: Camera.fx and Camera2.fx
    for prefix in prefixes:
        def value(n: str, default=None):
            key = f"{prefix}.{n}"
            if key not in data:
                if default is None:
                    raise ValueError(f"{build.where}: {key}: missing (expected by Camera.type "
                                     f"{kind})")
                return default
            return _number(build, key, data[key])

        focal = [value(n) for n in ("fx", "fy", "cx", "cy")]
        if kind == "KannalaBrandt8":
            model, params = "kannala_brandt", focal + [value(f"k{i}") for i in range(1, 5)]
        else:
            coeffs = [value(n, 0.0) for n in ("k1", "k2", "p1", "p2", "k3")]
            if kind == "Rectified" or not any(coeffs):
                model, params = "pinhole", focal
            else:
                model = build.model("opencv", f"{prefix}.k1", "PinHole with distortion")
                params = focal + coeffs + [0.0] * 7
        build.make(prefix, f"{prefix}.fx", model, params, size, area=angle)


# --------------------------------------------------------------------------------------------
# COLMAP
# --------------------------------------------------------------------------------------------

def _colmap_camera(build, name: str, key: str, model_name: str, width: int, height: int,
                   values: list[float], area: dict | None = None) -> None:
    if model_name in _COLMAP_UNREAD.values():
        raise ValueError(f"{build.where}: {key}: COLMAP's {model_name} has no registry model "
                         f"(read: {', '.join(_COLMAP_BY_NAME)})")
    if model_name not in _COLMAP_BY_NAME:
        raise ValueError(f"{build.where}: {key}: unknown COLMAP model {model_name!r} (expected "
                         f"one of {', '.join(_COLMAP_BY_NAME)})")
    _, names = _COLMAP_BY_NAME[model_name]
    if len(values) != len(names):
        raise ValueError(f"{build.where}: {key}: {model_name} takes {len(names)} parameters "
                         f"({', '.join(names)}), got {len(values)}")
    p = dict(zip(names, values))
    if "f" in p:
        p["fx"] = p["fy"] = p["f"]
    # COLMAP puts the top-left pixel's centre at (0.5, 0.5): ours are 0.5 less.
    focal = [p["fx"], p["fy"], p["cx"] - 0.5, p["cy"] - 0.5]
    k = lambda *ns: [p.get(n, 0.0) for n in ns]   # noqa: E731
    if model_name in ("SIMPLE_PINHOLE", "PINHOLE"):
        model, params = "pinhole", focal
    elif model_name in ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV"):
        if model_name == "SIMPLE_RADIAL":
            p["k1"] = p["k"]
        model = build.model("opencv", key, f"COLMAP's {model_name}")
        params = focal + k("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6") + [0.0] * 4
    elif model_name in ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"):
        if model_name == "SIMPLE_RADIAL_FISHEYE":
            p["k1"] = p["k"]
        model, params = "kannala_brandt", focal + k("k1", "k2", "k3", "k4")
    elif model_name in ("SIMPLE_FISHEYE", "FISHEYE"):
        model, params = "equidistant", focal
    elif model_name == "FOV":
        model, params = build.model("fov", key, "COLMAP's FOV"), focal + k("omega")
    elif model_name in ("SIMPLE_DIVISION", "DIVISION"):
        model = build.model("division", key, f"COLMAP's {model_name}")
        params = focal + k("k")
    elif model_name == "THIN_PRISM_FISHEYE":
        model = build.model("thin_prism_fisheye", key, "COLMAP's THIN_PRISM_FISHEYE")
        params = focal + k("k1", "k2", "p1", "p2", "k3", "k4", "sx1", "sy1")
    elif model_name == "RAD_TAN_THIN_PRISM_FISHEYE":
        model = build.model("fisheye624", key, "COLMAP's RAD_TAN_THIN_PRISM_FISHEYE")
        params = focal + k("k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3")
    else:   # EUCM
        model, params = "eucm", focal + k("alpha", "beta")
    build.make(name, key, model, params, (width, height), area=area)


def _colmap_text(build, text: str) -> None:
    # the area the writer kept in comments (export.py): "# fov_deg: 196.0"
    notes = dict(line.lstrip("#").split(":", 1) for line in text.splitlines()
                 if line.startswith("#") and line.lstrip("# ").split(":")[0] in
                 ("fov_deg", "blind_fov_deg", "valid_angle_deg"))
    area = build.area({k.strip(): v.strip() for k, v in notes.items()})
    for number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        key = f"line {number}"
        if len(tokens) < 4:
            raise ValueError(f"{build.where}, {key}: expected CAMERA_ID MODEL WIDTH HEIGHT "
                             f"PARAMS[], got {line.strip()!r}")
        try:
            cid, width, height = int(tokens[0]), int(tokens[2]), int(tokens[3])
            values = [float(t) for t in tokens[4:]]
        except ValueError:
            raise ValueError(f"{build.where}, {key}: expected CAMERA_ID MODEL WIDTH HEIGHT "
                             f"PARAMS[] (integers, then numbers), got {line.strip()!r}") from None
        if width <= 0 or height <= 0 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"{build.where}, {key}: expected a positive size and finite "
                             f"parameters, got {line.strip()!r}")
        _colmap_camera(build, str(cid), key, tokens[1], width, height, values, area)


def _colmap_binary(build, raw: bytes) -> None:
    """COLMAP's ``cameras.bin`` (``WriteCamerasBinary``), little-endian: uint64 count; per
    camera uint32 id, int32 model id, uint64 width, uint64 height, float64 params[n]."""
    def truncated(what: str):
        return ValueError(f"{build.where}: {what}: the file ends early (a truncated "
                          f"cameras.bin?)")

    if len(raw) < 8:
        raise truncated("the camera count")
    (count,) = struct.unpack_from("<Q", raw, 0)
    offset = 8
    for i in range(count):
        if len(raw) < offset + 24:
            raise truncated(f"camera {i + 1} of {count}")
        cid, model_id, width, height = struct.unpack_from("<IiQQ", raw, offset)
        offset += 24
        if model_id in _COLMAP_UNREAD:
            _colmap_camera(build, str(cid), f"camera {cid}", _COLMAP_UNREAD[model_id], 1, 1, [])
        if model_id not in _COLMAP_MODELS:
            raise ValueError(f"{build.where}: camera {cid} (byte {offset - 20}): unknown COLMAP "
                             f"model id {model_id} (expected 0..{max(_COLMAP_MODELS)})")
        name, names = _COLMAP_MODELS[model_id]
        n = len(names)
        if len(raw) < offset + 8 * n:
            raise truncated(f"camera {cid}'s parameters")
        values = list(struct.unpack_from(f"<{n}d", raw, offset))
        offset += 8 * n
        _colmap_camera(build, str(cid), f"camera {cid}", name, int(width), int(height), values)
    if offset != len(raw):
        raise ValueError(f"{build.where}: {len(raw) - offset} bytes after the {count} cameras "
                         f"the header announces (not a cameras.bin?)")


def _pycolmap_camera(build, camera) -> None:
    model = camera.model
    model_name = getattr(model, "name", str(model)).split(".")[-1]
    cid = getattr(camera, "camera_id", 1)
    _colmap_camera(build, str(cid), f"camera {cid}", model_name, int(camera.width),
                   int(camera.height), [float(v) for v in np.asarray(camera.params).ravel()])


# --------------------------------------------------------------------------------------------
# Project Aria
# --------------------------------------------------------------------------------------------

def _aria(build, data) -> None:
    cameras = _get(build, data, "CameraCalibrations")
    if not isinstance(cameras, list):
        raise ValueError(f"{build.where}: CameraCalibrations: expected a list of cameras")
    # MPS online calibrations list the sizes beside the cameras, [W, H] each
    sizes = data.get("ImageSizes") if isinstance(data.get("ImageSizes"), list) else []
    for i, entry in enumerate(cameras):
        key = f"CameraCalibrations[{i}]"
        label = str(_get(build, entry, "Label", key + "."))
        projection = _get(build, entry, "Projection", key + ".")
        kind = _get(build, projection, "Name", key + ".Projection.")
        values = _numbers(build, key + ".Projection.Params",
                          _get(build, projection, "Params", key + ".Projection."))
        pkey = key + ".Projection.Params"
        if kind in ("FisheyeRadTanThinPrism", "Fisheye624", "Fisheye62"):
            model = build.model("fisheye624", key + ".Projection.Name", f"Aria's {kind}")
            counts = {"FisheyeRadTanThinPrism": (15, 16), "Fisheye624": (15, 16),
                      "Fisheye62": (11, 12)}[kind]
            if len(values) not in counts:
                raise ValueError(f"{build.where}: {pkey}: {kind} takes {counts[0]} values (f, "
                                 f"cx, cy, k0..k5, p0, p1{', s0..s3' if counts[0] == 15 else ''})"
                                 f" or {counts[1]} (fx, fy first), got {len(values)}")
            if len(values) == counts[0]:   # one focal length: fx = fy
                values = values[:1] + values
            values = (values + [0.0] * 4)[:16]
        elif kind == "KannalaBrandtK3":
            if len(values) != 8:
                raise ValueError(f"{build.where}: {pkey}: KannalaBrandtK3 takes 8 values (fx, "
                                 f"fy, cx, cy, k0..k3), got {len(values)}")
            model = "kannala_brandt"
        else:
            raise ValueError(f"{build.where}: {key}.Projection.Name: {kind!r} has no registry "
                             f"model (read: FisheyeRadTanThinPrism, Fisheye624, Fisheye62, "
                             f"KannalaBrandtK3)")
        if entry.get("ImageSize") is not None:
            size = _size(build, key + ".ImageSize", entry["ImageSize"])
        elif i < len(sizes):
            size = _size(build, f"ImageSizes[{i}]", sizes[i])
        else:
            size = _ARIA_SIZES.get(label)
        build.make(label, pkey, model, values, size)


# --------------------------------------------------------------------------------------------
# WoodScape
# --------------------------------------------------------------------------------------------

def _woodscape(build, data) -> None:
    """The intrinsic part of a WoodScape calibration file (``woodscape_files.parse``)."""
    found = woodscape_files.parse(data, build.where)
    build.make(found["name"], "intrinsic", "woodscape", found["params"], found["size_wh"],
               area=found["area"])
