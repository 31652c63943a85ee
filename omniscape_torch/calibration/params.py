"""Free variables of a fit: constraints by reparametrisation, conditioning by scaling, poses.

An optimiser moves an unconstrained vector ``z``; every natural parameter is a smooth function
of its own entry of ``z``, chosen so that the model's range holds by construction and a unit
step in ``z`` moves the image by a comparable amount for every parameter:

=================================== ================================ ========================
parameter                           natural value from z             keeps
=================================== ================================ ========================
fx, fy (woodscape: k1,              f0 exp(z)                        f > 0
aspect_ratio)
cx, cy                              c0 + s z (s: half the larger     --
                                    image side)
xi (unified), omega (fov)           softplus(z)                      xi >= 0, omega >= 0
alpha (eucm, double_sphere)         sigmoid(z)                       0 < alpha < 1
beta (eucm)                         beta0 exp(z)                     beta > 0
xi (double_sphere)                  tanh(z)                          -1 < xi < 1
a_i (scaramuzza)                    a_i0 + s^(1 - i) z_i             --
everything else                     p0 + z                           --
=================================== ================================ ========================

The Scaramuzza polynomial is fitted in a normalised radius: with ``s`` the radius scale (the
image half-diagonal), ``f(rho) = f0(rho) + s * sum_i z_i (rho / s)^i``, so every ``z_i`` is of
order one where a raw ``a4 rho^4`` with rho in the hundreds spans ten orders of magnitude.
``z = 0`` is the initial value for the first two rows and the last two; bounded parameters start
at their inverse transform (clamped inside the range).

A pose is ``(r, t)``: axis-angle ``r`` (radians) and translation ``t`` (the unit of the target
points), ``X_cam = R(r) X + t``, moved as ``r = r0 + z_r`` and ``t = t0 + s_t z_t``.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor
from torch.nn import functional as F

from ..cameras import CameraModel
from ..cameras._base import safe_sqrt

#: Parameter groups a fit can freeze, beyond single parameter names.
GROUPS = ("focal", "center", "distortion", "affine")

#: Transform kinds by model and parameter name (anything not listed is ``"shift"``).
_KINDS = {
    "fx": "log", "fy": "log", "cx": "center", "cy": "center",
    ("unified", "xi"): "softplus", ("fov", "omega"): "softplus", ("double_sphere", "xi"): "tanh",
    ("eucm", "alpha"): "sigmoid", ("double_sphere", "alpha"): "sigmoid", ("eucm", "beta"): "log",
    ("woodscape", "aspect_ratio"): "log", ("woodscape", "k1"): "log",
}

#: How far inside an open range a bounded parameter starts when its initial value is on the edge.
_EDGE = 1e-6


def _kind(model: str, name: str) -> str:
    if model == "scaramuzza" and name.startswith("a"):
        return "poly"
    return _KINDS.get((model, name), _KINDS.get(name, "shift"))


def frozen_indices(model: CameraModel, names: Sequence[str], freeze: Sequence[str]) -> list[int]:
    """Indices of the parameters named by ``freeze``: group names (``GROUPS``) or parameter names.

    Raises:
        ValueError: an entry that is neither a group of the model nor one of ``names``.
    """
    if isinstance(freeze, str):
        freeze = (freeze,)
    out: set[int] = set()
    for item in freeze:
        if item in model.groups:   # an optional group (the skew) counts where present
            out.update(i for i in model.groups[item] if i < len(names))
        elif item in names:
            out.add(names.index(item))
        else:
            raise ValueError(f"freeze: {item!r} is neither a parameter group of the {model.name} "
                             f"model ({', '.join(model.groups)}) nor one of its parameters "
                             f"({', '.join(names)})")
    return sorted(out)


class IntrinsicsMap:
    """Natural intrinsics ``(P,)`` from the free vector ``z (n_free,)``; frozen ones held.

    Args:
        model: the camera model.
        init: ``(P,)`` initial natural parameters (float64), inside the model's range.
        image_size: ``(H, W)``: sets the centre and polynomial scales.
        frozen: indices of parameters held at ``init``.
    """

    def __init__(self, model: CameraModel, init: Tensor, image_size: tuple[int, int],
                 frozen: Sequence[int] = ()) -> None:
        self.model = model
        self.names = model.names_for(init.shape[-1])
        self.init = init.detach().clone()
        h, w = image_size
        self.center_scale = 0.5 * max(h, w)
        self.radius_scale = 0.5 * math.hypot(h, w)
        self.kinds = [_kind(model.name, n) for n in self.names]
        self.free = [i for i in range(len(self.names)) if i not in set(frozen)]
        scales = []
        for i, (name, kind) in enumerate(zip(self.names, self.kinds)):
            if kind == "center":
                scales.append(self.center_scale)
            elif kind == "poly":
                scales.append(self.radius_scale ** (1 - int(name[1:])))
            else:
                scales.append(1.0)
        self.scales = torch.tensor(scales, dtype=init.dtype)

    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(self.names[i] for i in self.free)

    def z0(self) -> Tensor:
        """The free vector of ``init``."""
        z = torch.zeros(len(self.free), dtype=self.init.dtype)
        for j, i in enumerate(self.free):
            x, kind = float(self.init[i]), self.kinds[i]
            if kind == "softplus":
                x = max(x, _EDGE)
                z[j] = x + math.log(-math.expm1(-x))
            elif kind == "sigmoid":
                x = min(max(x, _EDGE), 1 - _EDGE)
                z[j] = math.log(x / (1 - x))
            elif kind == "tanh":
                z[j] = math.atanh(min(max(x, -1 + _EDGE), 1 - _EDGE))
        return z

    def natural(self, z: Tensor) -> Tensor:
        """``(P,)`` natural parameters of ``z (n_free,)``, differentiable."""
        values = list(self.init.unbind(-1))
        for j, i in enumerate(self.free):
            kind, x0, zj = self.kinds[i], self.init[i], z[j]
            if kind == "log":
                values[i] = x0 * torch.exp(zj)
            elif kind == "softplus":
                values[i] = F.softplus(zj)
            elif kind == "sigmoid":
                values[i] = torch.sigmoid(zj)
            elif kind == "tanh":
                values[i] = torch.tanh(zj)
            else:
                values[i] = x0 + self.scales[i] * zj
        return torch.stack(values, dim=-1)

    def jacobian(self, z: Tensor) -> Tensor:
        """``(P, n_free)`` d natural / d z (zero rows for frozen parameters).

        Each natural parameter depends on its own free variable only, so the matrix holds one
        derivative per column, written out here: ``torch.func`` would give the same values, but
        its first call imports ``torch._dynamo`` (about 2 s, paid by every one-off fit).
        """
        z = z.detach()
        out = torch.zeros(len(self.names), len(self.free), dtype=self.init.dtype,
                          device=z.device)
        for j, i in enumerate(self.free):
            kind, zj = self.kinds[i], z[j]
            if kind == "log":
                d = self.init[i] * torch.exp(zj)
            elif kind == "softplus":
                d = torch.sigmoid(zj)
            elif kind == "sigmoid":
                s = torch.sigmoid(zj)
                d = s * (1 - s)
            elif kind == "tanh":
                d = 1 - torch.tanh(zj) ** 2
            else:
                d = self.scales[i]
            out[i, j] = d
        return out


def axis_angle_to_matrix(r: Tensor) -> Tensor:
    """Rodrigues' formula ``R = I + a K + b K^2``, ``a = sin t / t``, ``b = (1 - cos t) / t^2``.

    Near ``t = 0`` both factors switch to their Taylor series (exact to rounding below
    ``t^2 < sqrt(eps)``), so the value and gradient are finite at the identity.

    Args:
        r: ``(..., 3)`` axis times angle (radians).

    Returns:
        ``(..., 3, 3)`` rotation matrices.
    """
    t2 = (r * r).sum(-1)
    small = t2 < math.sqrt(torch.finfo(r.dtype).eps)
    t = safe_sqrt(t2, ~small)
    safe_t = torch.where(small, torch.ones_like(t), t)
    a = torch.where(small, 1 - t2 / 6, torch.sin(safe_t) / safe_t)
    b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(safe_t)) / (safe_t * safe_t))
    x, y, z = r.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), dim=-1).reshape(r.shape + (3,))
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def matrix_to_axis_angle(rotation: Tensor) -> Tensor:
    """Axis-angle ``(..., 3)`` of rotation matrices ``(..., 3, 3)`` (via kornia's quaternion)."""
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle
    return rotation_matrix_to_axis_angle(rotation)


def transform(poses: Tensor, points: Tensor) -> Tensor:
    """``R(r) X + t`` for poses ``(..., 6)`` = (r, t) and points ``(..., 3)``."""
    rotation = axis_angle_to_matrix(poses[..., :3])
    return (rotation @ points.unsqueeze(-1)).squeeze(-1) + poses[..., 3:]
