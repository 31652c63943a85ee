"""WoodScape's calibration files, read and written: the ``woodscape`` camera and its extrinsic.

WoodScape (``valeoai/WoodScape``, ``scripts/calibration/calibration_readme.txt``, MIT licence)
gives every image a JSON file::

    {"extrinsic": {"quaternion": [qx, qy, qz, qw], "translation": [tx, ty, tz]},
     "intrinsic": {"aspect_ratio", "cx_offset", "cy_offset", "height", "k1", "k2", "k3", "k4",
                   "model": "radial_poly", "poly_order": 4, "width"},
     "name": "FV"}

* Intrinsic: the ``woodscape`` model (``cameras/woodscape.py``) with ``cx = width / 2 - 0.5 +
  cx_offset`` and ``cy = height / 2 - 0.5 + cy_offset`` (WoodScape's ``projection.Camera``:
  the top-left pixel's centre at (0, 0), as here). The keys are written in the order of
  WoodScape's own files (alphabetical): OmniDet's loader reads the intrinsic values by position
  (``list(data["intrinsic"].values())``, the offsets first, then ``k1..k4`` at 4..7).
* Extrinsic: ``T (4, 4)``, the transform from the camera frame (OpenCV axes: x right, y down,
  z forward) to the vehicle frame (ISO 8855: x forward, y left, z up, the origin on the ground
  below the middle of the rear axle), translation in metres: ``X_vehicle = R X_camera + t``.
  The quaternion is scalar-last, ``(x, y, z, w)``, as WoodScape's ``projection.py`` reads it
  (``scipy.spatial.transform.Rotation.from_quat``); loaders that read it scalar-first turn the
  front camera's optical axis 23 degrees to the left and level, where the scalar-last reading
  has it forward and 23 degrees down, its x axis to the vehicle's right.
* SynWoodScape (Sekkat et al., RA-L 2022: WoodScape's cameras in CARLA) writes the same file
  with the translation under ``"translation used in CARLA (CARLA reference)"``, in CARLA's
  vehicle frame (x forward, y right, z up): it is read with ``y`` negated into the vehicle
  frame above. Its mirror cameras (``MVL``, ``MVR``) hold the lateral and vertical components
  swapped (``MVL``: ``[0.8, 1.0, -0.9]``, 0.9 m below the ground and on the right as written):
  read as ``(x, z, y)``, they sit 1.0 m up and 0.9 m out, each on the side its optical axis
  looks to. The origin stays CARLA's (the vehicle's centre on the ground, not WoodScape's rear
  axle: the offset is the car's, which the file does not give); the rotation is read as
  WoodScape's (its axes are already the vehicle frame's: ``FV`` looks forward, ``MVL`` left).
  ``write_woodscape`` writes WoodScape's key, in the vehicle frame.
* The imaged area: ``fov_deg`` / ``blind_fov_deg`` after ``name`` (full angles; where
  WoodScape's readers never look), as the package's other writers keep a camera's ``fov``.

Bad files are a ``ValueError`` naming the file, the key and what was expected.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from ..io.atomic import atomic_write_text
from ._checks import check_one_camera

#: WoodScape's translation key, and SynWoodScape's (in CARLA's frame).
TRANSLATION_KEY = "translation"
CARLA_TRANSLATION_KEY = "translation used in CARLA (CARLA reference)"
#: SynWoodScape's cameras whose translation holds y and z swapped (module docstring).
_SWAPPED = ("MVL", "MVR")
#: The intrinsic keys, in the order of WoodScape's files.
INTRINSIC_KEYS = ("aspect_ratio", "cx_offset", "cy_offset", "height", "k1", "k2", "k3", "k4",
                  "model", "poly_order", "width")


def is_woodscape(data) -> bool:
    """Whether a parsed JSON document looks like a WoodScape calibration file."""
    return (isinstance(data, dict) and isinstance(data.get("intrinsic"), dict)
            and isinstance(data.get("extrinsic"), dict))


def _number(where: str, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}: {key}: expected a number, got {value!r}")
    if not math.isfinite(value):
        raise ValueError(f"{where}: {key}: expected a finite number, got {value!r}")
    return float(value)


def _numbers(where: str, key: str, values, count: int) -> list[float]:
    if not isinstance(values, (list, tuple)) or len(values) != count:
        raise ValueError(f"{where}: {key}: expected a list of {count} numbers, got {values!r}")
    return [_number(where, f"{key}[{i}]", v) for i, v in enumerate(values)]


def _get(where: str, data: dict, key: str, prefix: str = ""):
    if key not in data:
        raise ValueError(f"{where}: {prefix}{key}: missing (WoodScape's calibration files have it)")
    return data[key]


def parse(data, where: str) -> dict:
    """The numbers of a WoodScape (or SynWoodScape) calibration document ``data``.

    Returns:
        ``{"params": [cx, cy, aspect_ratio, k1, k2, k3, k4], "size_wh": (W, H), "T": (4, 4)
        float64 ndarray, "name": str, "area": {"fov"/"blind_fov": radians}}``.

    Raises:
        ValueError: naming ``where`` (the file) and the key.
    """
    if not is_woodscape(data):
        raise ValueError(f"{where}: expected a WoodScape calibration JSON (an object with "
                         f"'extrinsic' and 'intrinsic' objects)")
    intr, extr = data["intrinsic"], data["extrinsic"]
    model = _get(where, intr, "model", "intrinsic.")
    if model != "radial_poly":
        raise ValueError(f"{where}: intrinsic.model: expected 'radial_poly' (WoodScape's "
                         f"model), got {model!r}")
    order = intr.get("poly_order", 4)
    if isinstance(order, bool) or order != 4:
        raise ValueError(f"{where}: intrinsic.poly_order: expected 4 (k1..k4), got {order!r}")
    value = {k: _number(where, f"intrinsic.{k}", _get(where, intr, k, "intrinsic."))
             for k in INTRINSIC_KEYS if k not in ("model", "poly_order")}
    for k in ("width", "height"):
        if value[k] <= 0 or value[k] != int(value[k]):
            raise ValueError(f"{where}: intrinsic.{k}: expected a positive whole number of "
                             f"pixels, got {intr[k]!r}")
    w, h = int(value["width"]), int(value["height"])
    params = [w / 2 - 0.5 + value["cx_offset"], h / 2 - 0.5 + value["cy_offset"],
              value["aspect_ratio"], value["k1"], value["k2"], value["k3"], value["k4"]]

    name = _get(where, data, "name")
    if not isinstance(name, str) or not name:
        raise ValueError(f"{where}: name: expected the camera's name (FV, MVL, MVR or RV), got "
                         f"{name!r}")
    quaternion = _numbers(where, "extrinsic.quaternion",
                          _get(where, extr, "quaternion", "extrinsic."), 4)
    norm = math.sqrt(sum(q * q for q in quaternion))
    if norm < 1e-6:
        raise ValueError(f"{where}: extrinsic.quaternion: expected a unit quaternion (x, y, z, "
                         f"w), got {quaternion}")
    keys = [k for k in (TRANSLATION_KEY, CARLA_TRANSLATION_KEY) if k in extr]
    if len(keys) != 1:
        raise ValueError(f"{where}: extrinsic: expected one of {TRANSLATION_KEY!r} "
                         f"(WoodScape) or {CARLA_TRANSLATION_KEY!r} (SynWoodScape), got "
                         f"{'both' if keys else 'neither'}")
    t = np.array(_numbers(where, f"extrinsic.{keys[0]}", extr[keys[0]], 3))
    if keys[0] == CARLA_TRANSLATION_KEY:   # CARLA's frame (y right): module docstring
        if name in _SWAPPED:
            t = t[[0, 2, 1]]
        t[1] = -t[1]
    transform = np.eye(4)
    transform[:3, :3] = quaternion_to_matrix(np.array(quaternion) / norm)
    transform[:3, 3] = t

    area = {}
    for key, out in (("fov_deg", "fov"), ("blind_fov_deg", "blind_fov")):
        if data.get(key) is not None:
            area[out] = math.radians(_number(where, key, data[key]))
    return {"params": params, "size_wh": (w, h), "T": transform, "name": name, "area": area}


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """``(3, 3)`` rotation of the unit quaternion ``q = (x, y, z, w)`` (scalar last)."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """The unit quaternion ``(x, y, z, w)``, ``w >= 0``, of a rotation ``r (3, 3)`` (Shepperd's
    method: the largest of the four squared components first, so no division by a small one)."""
    trace = np.trace(r)
    squares = [1 + 2 * r[0, 0] - trace, 1 + 2 * r[1, 1] - trace, 1 + 2 * r[2, 2] - trace,
               1 + trace]   # 4 x^2, 4 y^2, 4 z^2, 4 w^2
    i = int(np.argmax(squares))
    s = 2 * math.sqrt(squares[i])
    if i == 3:
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif i == 0:
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif i == 1:
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def read(cls, path: str | Path, *, dtype: torch.dtype = torch.float64, **kwargs):
    """Read a WoodScape (or SynWoodScape) calibration file (module docstring): the function
    behind ``ot.cameras.read_woodscape``, with the camera class to build (this module imports
    no ``camera.py``, which imports the readers, which import it).

    Args:
        cls: ``ot.Camera``.
        path: the JSON file (``calibration_data/{frame}_{CAM}.json``, ``front.json``).
        dtype: the camera's parameter dtype.
        **kwargs: for ``ot.Camera`` (``fov``, ``blind_fov``, ``learnable``), above the file's.

    Returns:
        ``(camera, T, name)``: the ``woodscape`` camera, ``T (4, 4)`` float64 tensor from the
        camera frame (OpenCV axes) to the vehicle frame (ISO 8855, metres), and the file's
        camera name (``FV``, ``MVL``, ``MVR``, ``RV``).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not valid JSON, a key missing or of the wrong kind (named).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such WoodScape calibration file")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    found = parse(data, str(path))
    w, h = found["size_wh"]
    options = {**found["area"], **kwargs}
    try:
        camera = cls("woodscape", torch.tensor(found["params"], dtype=dtype), (h, w),
                     **options)
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}: intrinsic: {err}") from None
    return camera, torch.from_numpy(found["T"]), found["name"]


def _check_transform(T) -> np.ndarray:
    try:
        t = np.array(T.detach().cpu().double().numpy() if isinstance(T, torch.Tensor) else T,
                     dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"T: expected a (4, 4) array or tensor, got {type(T).__name__}") from None
    if t.shape != (4, 4):
        raise ValueError(f"T: expected shape (4, 4), got {t.shape}")
    if not np.isfinite(t).all():
        raise ValueError("T: expected finite values")
    if np.abs(t[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise ValueError(f"T: expected a rigid transform, last row (0, 0, 0, 1), got "
                         f"{t[3].tolist()}")
    r = t[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-6 or np.linalg.det(r) <= 0:
        raise ValueError("T: its upper-left 3 x 3 block is not a rotation (orthonormal to "
                         "1e-6, determinant +1)")
    return t


def write_woodscape(path: str | Path, camera, T, name: str) -> Path:
    """Write one camera as WoodScape's calibration JSON, atomically (module docstring): keys
    and their order as WoodScape's files, the quaternion scalar-last, the principal point as
    offsets from the image centre.

    Args:
        path: the file to write.
        camera: one ``woodscape`` camera (convert others first: ``ot.calibration.convert``,
            ``omniscape-torch convert-model --to woodscape``).
        T: ``(4, 4)`` transform from the camera frame (OpenCV axes) to the vehicle frame
            (ISO 8855), metres.
        name: the camera's name (WoodScape's: ``FV``, ``MVL``, ``MVR``, ``RV``).

    Returns:
        The path written.
    """
    model = getattr(getattr(camera, "model", None), "name", None)
    if model is None or not hasattr(camera, "params"):
        raise TypeError(f"camera: expected an ot.Camera, got {type(camera).__name__}")
    if model != "woodscape":
        raise ValueError(f"camera: WoodScape's files hold the woodscape model, got {model}; "
                         f"convert it first (ot.calibration.convert(camera, 'woodscape'), "
                         f"omniscape-torch convert-model --to woodscape)")
    check_one_camera(camera)
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: expected the camera's name (e.g. FV, MVL, MVR, RV), got "
                         f"{name!r}")
    t = _check_transform(T)
    cx, cy, aspect, k1, k2, k3, k4 = camera.params.detach().double().cpu().tolist()
    h, w = camera.image_size
    data = {
        "extrinsic": {"quaternion": matrix_to_quaternion(t[:3, :3]).tolist(),
                      TRANSLATION_KEY: t[:3, 3].tolist()},
        # the offsets to 1e-12 px: a file read and written again keeps its decimals
        "intrinsic": {"aspect_ratio": aspect, "cx_offset": round(cx - (w / 2 - 0.5), 12),
                      "cy_offset": round(cy - (h / 2 - 0.5), 12), "height": float(h), "k1": k1,
                      "k2": k2, "k3": k3, "k4": k4, "model": "radial_poly", "poly_order": 4,
                      "width": float(w)},
        "name": name,
    }
    if camera.fov is not None:
        data["fov_deg"] = math.degrees(float(camera.fov))
    if camera.blind_fov is not None:
        data["blind_fov_deg"] = math.degrees(float(camera.blind_fov))
    return atomic_write_text(path, json.dumps(data, indent=2) + "\n")
