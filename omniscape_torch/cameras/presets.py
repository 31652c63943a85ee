"""Ready-made cameras like the OmniScape dataset's, and the rig's yaw/pitch/roll rotations.

Rig convention (``DESIGN.md``): frames are OpenCV (x right, y down, z forward) and a rotation
``R`` maps camera-frame rays into the cube (vehicle) frame, ``ray_cube = R @ ray_cam``. Angles
are radians here (degrees only at I/O and CLI boundaries), with the signs of a driver::

    R = R_yaw(yaw) @ R_pitch(pitch) @ R_roll(roll)

* yaw about the down axis (+y), positive = turn right: +z goes to +x (the "right" face);
* pitch about the right axis (+x), positive = look up: +z goes to -y (the "up" face);
* roll about the forward axis (+z), positive = the camera rotates clockwise as seen from
  behind (a motorcycle leaning right): its right axis +x goes to +y (down).

Roll is applied first, then pitch, then yaw (intrinsic yaw-pitch-roll), so the six face rig
rotations of ``DESIGN.md`` are yaw 0, 180, -90, +90 deg and pitch +90, -90 deg. This is CARLA's
``carla.Rotation(pitch, yaw, roll)`` (degrees; LibCarla ``geom/Transform.h``, ``GetMatrix``),
whose frame is Unreal's left-handed x forward, y right, z up: with ``P`` the axis permutation
``(x, y, z)_ours = (y, -z, x)_UE``, ``R = P M_carla P^T`` for the same three angles, so a CARLA
attitude converts as ``yaw_pitch_roll_to_matrix(radians(yaw), radians(pitch), radians(roll))``
(tests/test_presets.py checks it against CARLA's matrix).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from .camera import Camera, _check_fov, _check_image_size
from .registry import get_model
from .unified import unified_from_mirror

__all__ = [
    "FISHEYE_DEFAULTS",
    "catadioptric",
    "fisheye",
    "matrix_to_yaw_pitch_roll",
    "yaw_pitch_roll_to_matrix",
]

#: Parameters after (fx, fy, cx, cy) of each fisheye preset model. Double sphere and EUCM are
#: typical of 190-degree lenses in Usenko et al. (3DV 2018); Kannala-Brandt with k = 0 is the
#: equidistant model.
FISHEYE_DEFAULTS: dict[str, tuple[float, ...]] = {
    "equidistant": (),
    "equisolid": (),
    "stereographic": (),
    "orthographic": (),
    "kannala_brandt": (0.0, 0.0, 0.0, 0.0),
    "double_sphere": (-0.2, 0.6),
    "eucm": (0.6, 1.1),
}

#: Default mirror parameter of `catadioptric`: a hyperbolic mirror (0 < xi < 1; xi = 1
#: is parabolic).
CATADIOPTRIC_XI = 0.9


# --------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------

def _angles(**angles) -> tuple[Tensor, ...]:
    """The angles as floating tensors of one dtype and device, broadcast together."""
    tensors = [a for a in angles.values() if isinstance(a, Tensor)]
    for name, value in angles.items():
        if isinstance(value, Tensor):
            if not value.is_floating_point():
                raise TypeError(f"{name}: expected a floating-point tensor, got {value.dtype}")
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(f"{name}: expected a number or a tensor of radians, got "
                            f"{type(value).__name__}")
    dtype = torch.get_default_dtype()
    device = None
    if tensors:
        dtype = tensors[0].dtype
        for t in tensors[1:]:
            dtype = torch.promote_types(dtype, t.dtype)
        device = tensors[0].device
    out = [torch.as_tensor(v, dtype=dtype, device=device) for v in angles.values()]
    try:
        return tuple(torch.broadcast_tensors(*out))
    except RuntimeError:
        raise ValueError("yaw, pitch, roll: shapes do not broadcast: "
                         f"{[tuple(t.shape) for t in out]}") from None


def yaw_pitch_roll_to_matrix(yaw: float | Tensor, pitch: float | Tensor,
                             roll: float | Tensor) -> Tensor:
    """Rotation ``R = R_yaw R_pitch R_roll`` of the rig convention (module docstring).

    With ``c_, s_`` the cosines and sines of yaw (y), pitch (p) and roll (r)::

        R_yaw   = [[ cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]   (+z -> +x for yaw = +90 deg)
        R_pitch = [[1, 0, 0], [0, cp, -sp], [0, sp, cp]]    (+z -> -y for pitch = +90 deg)
        R_roll  = [[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]]    (+x -> +y for roll = +90 deg)

    Args:
        yaw: radians, a number or a floating tensor; the three angles broadcast together.
        pitch: radians, likewise.
        roll: radians, likewise.

    Returns:
        ``(..., 3, 3)`` rotations (camera to cube frame), differentiable, in the angles' dtype
        (the default dtype for numbers) and device.

    Examples:
        >>> R = yaw_pitch_roll_to_matrix(math.pi / 2, 0.0, 0.0)   # turn right
        >>> (R @ torch.tensor([0.0, 0.0, 1.0])).round().tolist()  # forward -> right
        [1.0, 0.0, -0.0]
    """
    yaw, pitch, roll = _angles(yaw=yaw, pitch=pitch, roll=roll)
    rows = rotation_rows(torch.cos(yaw), torch.sin(yaw), torch.cos(pitch), torch.sin(pitch),
                         torch.cos(roll), torch.sin(roll))
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


def rotation_rows(cy, sy, cp, sp, cr, sr) -> tuple:
    """The entries of `yaw_pitch_roll_to_matrix`'s ``R``, row by row, from the cosines and
    sines of yaw, pitch and roll: tensors or NumPy arrays (``augment.RandomReproject`` draws its
    attitudes in NumPy: on a few samples, torch's dispatch costs more than the arithmetic)."""
    return ((cy * cr + sy * sp * sr, sy * sp * cr - cy * sr, sy * cp),
            (cp * sr, cp * cr, -sp),
            (cy * sp * sr - sy * cr, sy * sr + cy * sp * cr, cy * cp))


def matrix_to_yaw_pitch_roll(rotation: Tensor, *, eps: float | None = None
                             ) -> tuple[Tensor, Tensor, Tensor]:
    """Inverse of `yaw_pitch_roll_to_matrix`.

    ``pitch = atan2(-R[1, 2], hypot(R[0, 2], R[2, 2]))`` in ``[-pi/2, pi/2]``,
    ``yaw = atan2(R[0, 2], R[2, 2])`` and ``roll = atan2(R[1, 0], R[1, 1])`` in ``(-pi, pi]``.
    At pitch = +-90 deg (gimbal lock: ``cos(pitch) < eps``) only yaw - roll or yaw + roll is
    defined; roll is set to 0 and ``yaw = atan2(-R[2, 0], R[0, 0])``.

    Args:
        rotation: ``(..., 3, 3)`` floating rotation matrices.
        eps: gimbal-lock threshold on ``cos(pitch)``; default ``sqrt`` of the dtype's
            machine epsilon (1.5e-8 in float64, 3.5e-4 in float32).

    Returns:
        ``(yaw, pitch, roll)``, each ``(...)`` radians, differentiable away from the lock.
    """
    if not isinstance(rotation, Tensor):
        raise TypeError(f"rotation: expected a torch.Tensor, got {type(rotation).__name__}")
    if not rotation.is_floating_point():
        raise TypeError(f"rotation: expected a floating-point tensor, got {rotation.dtype}")
    if rotation.dim() < 2 or rotation.shape[-2:] != (3, 3):
        raise ValueError(f"rotation: expected shape (..., 3, 3), got {tuple(rotation.shape)}")
    if eps is None:
        eps = math.sqrt(torch.finfo(rotation.dtype).eps)
    elif isinstance(eps, bool) or not isinstance(eps, (int, float)) or not 0 < eps < 1:
        raise ValueError(f"eps: expected a number in (0, 1), got {eps!r}")
    r = rotation
    cos_pitch = torch.hypot(r[..., 0, 2], r[..., 2, 2])
    pitch = torch.atan2(-r[..., 1, 2], cos_pitch)
    lock = cos_pitch < eps
    one, zero = torch.ones_like(cos_pitch), torch.zeros_like(cos_pitch)
    # atan2(0, 0) has a NaN gradient: feed the unused branch safe arguments before calling it.
    yaw_free = torch.atan2(torch.where(lock, zero, r[..., 0, 2]),
                           torch.where(lock, one, r[..., 2, 2]))
    roll_free = torch.atan2(torch.where(lock, zero, r[..., 1, 0]),
                            torch.where(lock, one, r[..., 1, 1]))
    yaw_lock = torch.atan2(torch.where(lock, -r[..., 2, 0], zero),
                           torch.where(lock, r[..., 0, 0], one))
    yaw = torch.where(lock, yaw_lock, yaw_free)
    roll = torch.where(lock, zero, roll_free)
    return yaw, pitch, roll


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------

def _rim_radius(image_size: tuple[int, int]) -> float:
    h, w = image_size
    if min(h, w) < 2:
        raise ValueError(f"image_size: needs at least 2 x 2 pixels, got {(h, w)}")
    return min(h, w) / 2 - 0.5


def _normalised_radius(model_name: str, extra: Sequence[float], theta: float) -> float:
    """Image radius, in focal units, of a ray at ``theta`` from the axis, from the model's own
    projection (fx = fy = 1, centre 0); ValueError if the model cannot see that far."""
    model = get_model(model_name)
    params = torch.tensor([1.0, 1.0, 0.0, 0.0, *extra], dtype=torch.float64)
    limit = float(model.max_angle(params))
    point = torch.tensor([math.sin(theta), 0.0, math.cos(theta)], dtype=torch.float64)
    pixel, valid = model.project(point, params)
    radius = float(torch.linalg.vector_norm(pixel))
    if not bool(valid) or theta > limit or not radius > 0 or not math.isfinite(radius):
        raise ValueError(f"fov: the {model_name} model with parameters {tuple(extra)} sees at "
                         f"most {math.degrees(limit):.2f} deg from its axis, the preset asks for "
                         f"{math.degrees(theta):.2f} deg (fov / 2)")
    return radius


def fisheye(image_size: tuple[int, int], *, fov: float = math.radians(190),
            model: str = "equidistant", distortion: Sequence[float] | None = None,
            dtype: torch.dtype = torch.float32) -> Camera:
    """A fisheye whose image circle (the ``fov`` cone) is inscribed in the image.

    Centre ``((W - 1) / 2, (H - 1) / 2)``, ``fx = fy = f`` with ``f r1(fov / 2) = min(H, W) / 2
    - 0.5``: the rim of the field of view passes through the outermost pixel centres of the
    shorter side, ``r1(theta)`` being the model's image radius at focal 1 (``theta`` for
    equidistant, ``2 sin(theta / 2)`` equisolid, ``2 tan(theta / 2)`` stereographic, ``sin``
    orthographic; from the model's projection for the others). Pixels beyond the rim are
    invalid (``Camera.fov``). The optical axis is +z: with ``R = I`` it looks forward.

    Args:
        image_size: ``(H, W)`` in pixels, at least 2 x 2.
        fov: full field of view in radians (default 190 degrees).
        model: ``"equidistant"``, ``"equisolid"``, ``"stereographic"``, ``"orthographic"``
            (fov <= 180 deg), ``"kannala_brandt"``, ``"double_sphere"`` or ``"eucm"``.
        distortion: the model's parameters after (fx, fy, cx, cy): k1..k4, (xi, alpha) or
            (alpha, beta); default `FISHEYE_DEFAULTS`.
        dtype: floating dtype of the camera's parameters.

    Returns:
        The ``Camera``.

    Examples:
        >>> cam = fisheye((1024, 1024))
        >>> round(float(cam.params[0]), 2)   # 511.5 / radians(95)
        308.49
    """
    size = _check_image_size(image_size)
    if not isinstance(model, str):
        raise TypeError(f"model: expected a model name, got {type(model).__name__}")
    if model not in FISHEYE_DEFAULTS:
        raise ValueError(f"model: expected one of {tuple(FISHEYE_DEFAULTS)}, got {model!r}")
    fov = _check_fov(fov)
    if fov is None:
        raise ValueError("fov: a fisheye preset needs a field of view")
    _check_dtype(dtype)
    extra = FISHEYE_DEFAULTS[model] if distortion is None else tuple(distortion)
    if len(extra) != len(FISHEYE_DEFAULTS[model]):
        raise ValueError(f"distortion: the {model} model takes {len(FISHEYE_DEFAULTS[model])} "
                         f"parameters after fx, fy, cx, cy, got {len(extra)}")
    focal = _rim_radius(size) / _normalised_radius(model, extra, 0.5 * fov)
    h, w = size
    params = torch.tensor([focal, focal, (w - 1) / 2, (h - 1) / 2, *extra], dtype=dtype)
    return Camera(model, params, size, fov=fov)


def catadioptric(image_size: tuple[int, int], *, xi: float | None = None,
                 fov: float = math.radians(220), blind_fov: float | None = math.radians(40),
                 looking: str = "down", mirror: dict | None = None,
                 dtype: torch.dtype = torch.float32) -> tuple[Camera, Tensor]:
    """A central catadioptric camera (unified model) like the OmniScape dataset's, and its attitude.

    The unified model (Geyer-Daniilidis; ``xi`` = 1 parabolic mirror, 0 < xi < 1 hyperbolic)
    puts a ray at ``theta`` from the axis at radius ``gamma sin(theta) / (cos(theta) + xi)``.
    The image is centred, ``((W - 1) / 2, (H - 1) / 2)``, and the generalised focal ``gamma`` puts
    the outer rim of the mirror (``theta = fov / 2``) at ``min(H, W) / 2 - 0.5`` pixels from the
    centre, the outermost pixel centres of the shorter side; the image sees 360 degrees around
    the axis. The centre of a catadioptric image shows the camera itself, reflected by the
    mirror: ``blind_fov`` (the full angle of that central cone) masks it.

    Orientation: the unified camera's axis points from the mirror's focus towards the camera
    (``unified_from_mirror``). The OmniScape paper places the camera on top of the mirror, or the
    contrary; here:

    * ``looking="down"``: the camera under its mirror, looking up into it (the usual roof
      mount). The axis points down, +y in the cube frame; the image shows the ground and the
      surroundings up to ``fov / 2 - 90`` degrees above the horizon (20 by default), the front
      of the vehicle at the top of the image. The rotation is the "down" face's (pitch -90 deg).
    * ``looking="up"``: the camera on top of the mirror, looking down into it. The axis points
      up, -y; the image shows the sky and the surroundings down to ``fov / 2 - 90`` degrees
      below the horizon, the front at the bottom of the image. The "up" face's rotation (pitch
      +90 deg).

    Defaults (xi = 0.9, rim 110 degrees from the axis, a 40-degree blind cone) resemble the
    dataset's hyperbolic-mirror images; the radius of the blind disc is then 11 percent of the
    rim's.

    Args:
        image_size: ``(H, W)`` in pixels, at least 2 x 2.
        xi: the mirror parameter, >= 0 (default 0.9); not with ``mirror``.
        fov: full field of view in radians: twice the rim's angle from the axis; below
            ``2 acos(-xi)`` (``2 acos(-1 / xi)`` for xi > 1), where the model ends.
        blind_fov: full angle in radians of the central blind cone, or None for none.
        looking: ``"down"`` or ``"up"``.
        mirror: alternatively, the mirror, ``dict(kind="hyperbolic" | "parabolic" | "elliptic" |
            "planar", d=..., p=...)`` (foci ``d`` apart, latus rectum ``4 p``); ``xi`` comes from
            ``unified_from_mirror``. The focal of the camera behind the mirror does not matter
            here: the image is scaled to fit the rim.
        dtype: floating dtype of the parameters and the rotation.

    Returns:
        ``(camera, rotation)``: a ``unified`` ``Camera`` (params fx = fy = gamma, cx, cy, xi,
        0, 0, 0, 0) and its ``(3, 3)`` camera-to-cube rotation.

    Examples:
        >>> cam, R = catadioptric((1024, 1024))
        >>> R.tolist()   # camera +z (its axis) -> cube +y (down)
        [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]
    """
    size = _check_image_size(image_size)
    _check_dtype(dtype)
    if looking not in ("down", "up"):
        raise ValueError(f"looking: expected 'down' or 'up', got {looking!r}")
    if mirror is not None:
        if xi is not None:
            raise ValueError("xi: give xi or mirror, not both")
        xi = _xi_of_mirror(mirror)
    elif xi is None:
        xi = CATADIOPTRIC_XI
    if isinstance(xi, bool) or not isinstance(xi, (int, float)) or not math.isfinite(xi):
        raise TypeError(f"xi: expected a finite number, got {xi!r}")
    if xi < 0:
        raise ValueError(f"xi: expected >= 0, got {xi}")
    fov = _check_fov(fov)
    if fov is None:
        raise ValueError("fov: a catadioptric preset needs a field of view")
    blind_fov = _check_fov(blind_fov, "blind_fov")
    if blind_fov is not None and blind_fov >= fov:
        raise ValueError(f"blind_fov: must be smaller than fov, got {blind_fov} >= {fov}")
    extra = (float(xi), 0.0, 0.0, 0.0, 0.0)
    gamma = _rim_radius(size) / _normalised_radius("unified", extra, 0.5 * fov)
    h, w = size
    params = torch.tensor([gamma, gamma, (w - 1) / 2, (h - 1) / 2, *extra], dtype=dtype)
    camera = Camera("unified", params, size, fov=fov, blind_fov=blind_fov)
    # a pitch of -90 degrees (down) or +90 degrees (up), written exactly: the camera's axis
    # along the world's +y (down) or -y, its image-down along -z or +z (DESIGN.md's down and up
    # faces)
    s = 1.0 if looking == "down" else -1.0
    rotation = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, s], [0.0, -s, 0.0]], dtype=dtype)
    return camera, rotation


def _xi_of_mirror(mirror: object) -> float:
    if not isinstance(mirror, dict):
        raise TypeError(f"mirror: expected a dict(kind=..., d=..., p=...), got "
                        f"{type(mirror).__name__}")
    unknown = set(mirror) - {"kind", "d", "p"}
    if "kind" not in mirror or unknown:
        raise ValueError(f"mirror: expected keys 'kind' and optionally 'd', 'p', got "
                         f"{sorted(mirror)}")
    try:
        params = unified_from_mirror(mirror["kind"], p=mirror.get("p", 0.0),
                                     d=mirror.get("d", 0.0), focal=1.0, cx=0.0, cy=0.0)
    except (TypeError, ValueError) as err:
        raise type(err)(f"mirror: {err}") from None
    return float(params[4])


def _check_dtype(dtype: object) -> None:
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype: expected a floating torch.dtype, got {dtype!r}")
