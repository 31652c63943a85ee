"""The one check of the rotations that map camera rays into the cube frame.

Every path that takes an attitude (the layer, its fast and reference samplers, the
augmentation's replayed parameters, the stereo rig, ``reproject``, the sizing functions) calls
`check_rotation` at its entry, so a bad matrix gets the same error everywhere instead of
a black, mirrored or silently rescaled image (the cube projection is scale invariant, so a
scaled matrix would otherwise render as its rotation).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["ROTATION_ATOL", "check_rotation"]

#: Largest ``|R R^T - I|`` entry accepted, for float32 and float64 matrices: 1e-3 is a shear
#: of 0.06 degrees, far above the rounding of matrices built from angles in float32 (about
#: 1e-7) and far below any mistake (a scale, a reflection, a wrong convention). Lower
#: precisions get 4 machine epsilons of their dtype when that is larger (float16 3.9e-3,
#: bfloat16 0.031).
ROTATION_ATOL = 1e-3


#: Up to this many matrices are checked one by one in Python floats (7 us for one, where the
#: numpy of a batch takes 40 us whatever its size; every call of the layer checks).
_FEW = 16


def _is_rotation(m: list[float], tol: float) -> bool:
    """Whether the row-major 3 x 3 matrix ``m`` is a rotation: every entry of ``M M^T - I``
    within ``tol`` and ``det M > 0`` (NaN fails both)."""
    a, b, c, d, e, f, g, h, i = m
    error = max(abs(a * a + b * b + c * c - 1), abs(d * d + e * e + f * f - 1),
                abs(g * g + h * h + i * i - 1), abs(a * d + b * e + c * f),
                abs(a * g + b * h + c * i), abs(d * g + e * h + f * i))
    return error <= tol and a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0


def check_rotation(rotation: object, name: str = "rotation", *,
                   atol: float = ROTATION_ATOL) -> Tensor:
    """Check that ``rotation (..., 3, 3)`` holds rotation matrices; return it unchanged.

    A rotation is finite, orthonormal (every entry of ``R R^T - I`` within ``atol``, or 4
    epsilons of its dtype if larger) and proper (``det R = +1``: a reflection mirrors the
    image).

    Args:
        rotation: a floating-point tensor of shape ``(..., 3, 3)``.
        name: the argument's name, for the error message.
        atol: the orthonormality tolerance (`ROTATION_ATOL`).

    Raises:
        TypeError: not a floating-point tensor.
        ValueError: another shape, or a matrix that is not a rotation; the message names the
            first such batch index and what is wrong with it.
    """
    if not isinstance(rotation, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor of shape (..., 3, 3), got "
                        f"{type(rotation).__name__}")
    if not rotation.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {rotation.dtype}")
    if rotation.dim() < 2 or rotation.shape[-2:] != (3, 3):
        raise ValueError(f"{name}: expected shape (..., 3, 3), got {tuple(rotation.shape)}")
    if rotation.numel() == 0 or rotation.device.type == "meta":   # no values to check
        return rotation
    tol = max(float(atol), 4 * torch.finfo(rotation.dtype).eps)
    if rotation.device.type == "cpu" and rotation.numel() <= 9 * _FEW and \
            all(_is_rotation(m, tol) for m in rotation.detach().reshape(-1, 9).tolist()):
        return rotation
    r = rotation.detach().reshape(-1, 3, 3).to(torch.float64)
    # Every call of the layer checks: on the CPU in numpy (40 us; torch's small ops took 200 us,
    # 6% of rendering a 1024 x 1024 uint8 frame), elsewhere in torch (one sync).
    a = r.numpy() if r.device.type == "cpu" else r
    with np.errstate(invalid="ignore", over="ignore"):   # NaN, inf: refused below
        gram = a @ a.swapaxes(-1, -2)
        gram[:, [0, 1, 2], [0, 1, 2]] -= 1   # R R^T - I
        error = abs(gram).reshape(-1, 9).max(1)
        error = error if isinstance(error, np.ndarray) else error.values
        x, y, z = a[:, 0], a[:, 1], a[:, 2]   # det R: the triple product x . (y cross z)
        det = (x[:, 0] * (y[:, 1] * z[:, 2] - y[:, 2] * z[:, 1])
               - x[:, 1] * (y[:, 0] * z[:, 2] - y[:, 2] * z[:, 0])
               + x[:, 2] * (y[:, 0] * z[:, 1] - y[:, 1] * z[:, 0]))
    ok = (error <= tol) & (det > 0)   # NaN compares false: not ok
    if bool(ok.all()):
        return rotation
    ok, error, det = torch.as_tensor(ok), torch.as_tensor(error), torch.as_tensor(det)
    i = int((~ok).nonzero()[0, 0])
    index = tuple(int(k) for k in torch.unravel_index(torch.tensor(i), rotation.shape[:-2]))
    where = f"{name}[{', '.join(map(str, index))}]" if index else name
    if not bool(torch.isfinite(r[i]).all()):
        what = "has a NaN or infinite entry"
    elif float(det[i]) <= 0:
        what = (f"has det {float(det[i]):.3g} (a reflection or a degenerate matrix; a rotation "
                f"has det +1)")
    else:
        what = (f"is not orthonormal: R R^T differs from I by {float(error[i]):.3g} (a scaled "
                f"or sheared matrix?)")
    raise ValueError(f"{where} {what}; expected a rotation matrix (R R^T = I within {tol:.3g}, "
                     f"det +1)")
