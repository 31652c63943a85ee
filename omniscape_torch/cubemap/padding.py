"""Padded cube: every face carries a border resampled from its neighbours.

A padded face of border ``p`` is ``(F + 2p) x (F + 2p)``; padded texel ``[i, j]`` is the face's
own pinhole pixel ``(u, v) = (j - p, i - p)`` extended beyond the edge. A border texel is not
copied from the nearest edge texel: its ray is looked up on the face it hits and interpolated
there. With that border, bilinear sampling of a face at any ``uv`` in ``[-0.5, F - 0.5]`` (and
bicubic for ``p >= 2``) reads only texels of that padded face and is continuous across seams
and corners.

The border is linear in the cube, so it is precomputed once per ``(F, p, mode)`` as a
`BorderPlan` (source indices and weights into the unpadded cube) and applied with one
gather.

Self-reference near edges and corners: a border texel's ray lands on its source face at
``uv`` in ``[-0.5, F - 0.5]``, and bilinear interpolation there may need a texel of the source
face's own border (the half-texel strip along every edge, and the corners, where three faces
meet and the corner texels refer to each other). The border ``B`` is therefore defined as the
solution of ``B = W_i X + W_b B`` (``X`` the cube's texels, ``W_i``/``W_b`` the bilinear weights
on interior/border texels), a self-consistent padding: sampling the padded cube at a border
texel's ray on its source face gives back that border texel. The plan solves it by expanding
border taps (a Neumann series: ``W_b`` has row sums < 1 and every chain reaches the interior
within a few steps; 4 to 21 steps for F from 1024 down to 1) until the weight left on border
texels is below ``tol / 2`` in every row, dropping taps below ``tol / 100`` on the way; what is
left or dropped (``BorderPlan.residual``, about 1e-13 for the default ``tol = 1e-12``) is
removed and the row renormalised, so the solve adds an error below
``2 * residual * max|X|``, far below float32 resolution. What remains is the ordinary bilinear
interpolation error at the source point, ``O(1 / F^2)`` of the signal's curvature: for
degree-2 spherical harmonics at F = 32, pad 2, 1.2e-3 worst case on the border (6.6e-4 in
the corner blocks) against 1.7e-1 for a border copied from the edge texels, and at most the
textbook bilinear bound ``(|g_uu| + |g_vv|) / 8`` (tests/test_cubemap.py). Near seams the
border is bilinear-accurate, not bicubic-accurate; with torch's bicubic kernel the difference
to an exact border was 2e-4 in that test.

``mode="nearest"`` takes the nearest texel of the source face (clamped to the face), with one
tap and no self-reference: labels are never blended.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from .faces import _check_face_size, _check_pad, face_rays, ray_to_face

__all__ = ["PAD_MODES", "BorderPlan", "border_plan", "pad_faces", "check_cubemap"]

PAD_MODES = ("bilinear", "nearest")


@dataclass(frozen=True)
class BorderPlan:
    """Precomputed border of a padded cube for one ``(face_size, pad, mode)``.

    Border texel ``n`` of the padded cube (flat index ``dst_index[n]`` into the padded faces
    flattened as ``(6, F + 2p, F + 2p)``) is ``sum_k weight[n, k] * cube[src_index[n, k]]`` with
    the cube flattened as ``(6, F, F)``. Rows are zero-padded to a common ``K``.

    Attributes:
        face_size: ``F``.
        pad: ``p``.
        mode: ``"bilinear"`` or ``"nearest"``.
        dst_index: ``(N,)`` int64, ``N = 6 ((F + 2p)^2 - F^2)``.
        src_index: ``(N, K)`` int64 into ``6 F F``.
        weight: ``(N, K)`` floating; rows sum to 1.
        residual: largest weight per row left on border texels or dropped as negligible when
            the self-referencing solve stopped (0 for ``"nearest"``).
        iterations: expansion steps the solve took.
    """

    face_size: int
    pad: int
    mode: str
    dst_index: Tensor
    src_index: Tensor
    weight: Tensor
    residual: float
    iterations: int

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> "BorderPlan":
        """Plan with its tensors on ``device`` and weights in ``dtype`` (``self`` if unchanged)."""
        device = self.weight.device if device is None else torch.device(device)
        dtype = self.weight.dtype if dtype is None else dtype
        if self.weight.device == device and self.weight.dtype == dtype:
            return self
        return BorderPlan(
            self.face_size,
            self.pad,
            self.mode,
            self.dst_index.to(device),
            self.src_index.to(device),
            self.weight.to(device=device, dtype=dtype),
            self.residual,
            self.iterations,
        )


def border_plan(
    face_size: int, pad: int, mode: str = "bilinear", *, tol: float = 1e-12, max_iter: int = 200
) -> BorderPlan:
    """Source indices and weights of the border of a padded cube.

    Computed once in float64 on the CPU and cached per ``(face_size, pad, mode, tol,
    max_iter)``; move it with `BorderPlan.to` (a layer keeps the result as buffers). The
    returned tensors are shared by every caller: do not modify them in place.

    Args:
        face_size: ``F``, texels per face side.
        pad: border width ``p >= 1`` in texels.
        mode: ``"bilinear"`` (self-consistent bilinear border, see the module docstring) or
            ``"nearest"`` (nearest texel of the source face).
        tol: stop the bilinear self-reference solve when every row has less than ``tol`` of its
            weight left on border texels.
        max_iter: bound on the solve's expansion steps; ``RuntimeError`` if not converged.

    Returns:
        The `BorderPlan`, CPU, float64 weights.
    """
    _check_face_size(face_size)
    _check_pad(pad)
    if pad < 1:
        raise ValueError(f"pad must be >= 1 for a border plan, got {pad}")
    if mode not in PAD_MODES:
        raise ValueError(f"mode must be one of {PAD_MODES}, got {mode!r}")
    if not tol > 0:
        raise ValueError(f"tol must be > 0, got {tol}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
        raise ValueError(f"max_iter must be an int >= 1, got {max_iter!r}")
    return _border_plan(face_size, pad, mode, float(tol), max_iter)


class BorderTaps(NamedTuple):
    """The border texels of a padded cube and the bilinear taps of their rays (`border_taps`).

    Attributes:
        dst: `(N,)` int64 padded flat index of each border texel (`BorderPlan.dst_index`).
        src_face: `(N,)` int64 the face its ray hits.
        uv: `(N, 2)` float64 where, on that face (in `[-0.5, F - 0.5]`).
        tap_col: `(N, 4)` int64 padded flat index of its four bilinear taps there.
        tap_w: `(N, 4)` float64 their weights (rows sum to 1).
        border_pos: `(6 (F + 2p)^2,)` int64 padded flat index -> position in `dst`, -1 for
            interior texels.
    """

    dst: Tensor
    src_face: Tensor
    uv: Tensor
    tap_col: Tensor
    tap_w: Tensor
    border_pos: Tensor


def border_taps(F: int, p: int) -> BorderTaps:
    """The border texels of a cube of face `F` padded by `p` and their bilinear taps: the
    system `B = W_i X + W_b B` that `border_plan` solves (module docstring), float64."""
    n = F + 2 * p
    dtype = torch.float64
    t = torch.arange(n)
    inside_1d = (t >= p) & (t < p + F)
    inside = (inside_1d[:, None] & inside_1d[None, :]).expand(6, n, n).reshape(-1)  # [6 n n]
    dst = torch.nonzero(~inside).squeeze(1)  # [N] padded flat index of border texels
    num_border = dst.numel()

    rays = face_rays(F, pad=p, dtype=dtype).reshape(-1, 3)[dst]  # [N, 3]
    src_face, uv = ray_to_face(rays, F)  # [N], [N, 2]

    # Bilinear taps on the source face's padded grid: uv in [-0.5, F - 0.5] reads texels
    # -1 .. F, which a padded face with p >= 1 holds.
    uv0 = torch.floor(uv)
    w = uv - uv0  # [N, 2]
    i0 = uv0.long() + p  # padded column, row
    tap_col = []
    tap_w = []
    for dv in (0, 1):
        for du in (0, 1):
            col = i0[:, 0] + du
            row = i0[:, 1] + dv
            if bool(((col < 0) | (col >= n) | (row < 0) | (row >= n)).any()):
                raise AssertionError("bilinear tap outside the padded face")  # pragma: no cover
            tap_col.append((src_face * n + row) * n + col)
            wu = w[:, 0] if du else 1 - w[:, 0]
            wv = w[:, 1] if dv else 1 - w[:, 1]
            tap_w.append(wu * wv)

    # Padded flat index -> position among border texels (-1 for interior texels).
    border_pos = torch.full((6 * n * n,), -1, dtype=torch.long)
    border_pos[dst] = torch.arange(num_border)
    return BorderTaps(dst, src_face, uv, torch.stack(tap_col, 1), torch.stack(tap_w, 1),
                      border_pos)


@functools.lru_cache(maxsize=32)
def _border_plan(F: int, p: int, mode: str, tol: float, max_iter: int) -> BorderPlan:
    n = F + 2 * p
    dtype = torch.float64
    dst, src_face, uv, tap_col, tap_w, border_pos = border_taps(F, p)
    num_border = dst.numel()

    if mode == "nearest":
        uv_int = torch.floor(uv + 0.5).long().clamp(0, F - 1)
        src = (src_face * F + uv_int[:, 1]) * F + uv_int[:, 0]
        return BorderPlan(
            F, p, mode, dst, src.unsqueeze(1), torch.ones(num_border, 1, dtype=dtype), 0.0, 0
        )

    # Entries (row, padded column, weight) of B = W_i X + W_b B, expanded until the weight on
    # border columns is below tol / 2 in every row. Weights below tol / 100 are dropped along
    # the way (chains along mid-edges decay like (1 / 2F)^k and would only add taps).
    rows = torch.arange(num_border).repeat_interleave(4)
    cols = tap_col.reshape(-1)
    vals = tap_w.reshape(-1)
    dropped = torch.zeros(num_border, dtype=dtype)
    iterations = 0
    while True:
        small = vals.abs() < tol / 100
        dropped.index_add_(0, rows[small], vals[small].abs())
        rows, cols, vals = rows[~small], cols[~small], vals[~small]
        on_border = border_pos[cols] >= 0
        mass = torch.zeros(num_border, dtype=dtype).index_add_(
            0, rows[on_border], vals[on_border].abs()
        )
        if num_border == 0 or float(mass.max()) < tol / 2:
            break
        if iterations == max_iter:
            raise RuntimeError(
                f"border solve did not converge in {max_iter} steps "
                f"(border weight left {float(mass.max()):.3g})"
            )
        iterations += 1
        b = border_pos[cols[on_border]]
        new_rows = rows[on_border].repeat_interleave(4)
        new_cols = tap_col[b].reshape(-1)
        new_vals = (vals[on_border, None] * tap_w[b]).reshape(-1)
        rows = torch.cat([rows[~on_border], new_rows])
        cols = torch.cat([cols[~on_border], new_cols])
        vals = torch.cat([vals[~on_border], new_vals])
        key, inverse = torch.unique(rows * (6 * n * n) + cols, return_inverse=True)
        vals = torch.zeros(key.numel(), dtype=dtype).index_add_(0, inverse, vals)
        rows, cols = key // (6 * n * n), key % (6 * n * n)
    residual = float((mass + dropped).max()) if num_border else 0.0

    # Drop what is left on the border, renormalise, and map padded columns to the unpadded cube.
    keep = border_pos[cols] < 0
    rows, cols, vals = rows[keep], cols[keep], vals[keep]
    face, rem = cols // (n * n), cols % (n * n)
    src = (face * F + (rem // n - p)) * F + (rem % n - p)
    order = torch.argsort(rows, stable=True)
    rows, src, vals = rows[order], src[order], vals[order]
    counts = torch.bincount(rows, minlength=num_border)
    k = int(counts.max())
    start = torch.cumsum(counts, 0) - counts
    slot = torch.arange(rows.numel()) - start[rows]
    src_index = torch.zeros(num_border, k, dtype=torch.long)
    weight = torch.zeros(num_border, k, dtype=dtype)
    src_index[rows, slot] = src
    weight[rows, slot] = vals
    weight = weight / weight.sum(1, keepdim=True)
    return BorderPlan(F, p, mode, dst, src_index, weight, residual, iterations)


def check_cubemap(cubemap: object, name: str = "cubemap") -> Tensor:
    """Check that ``cubemap`` is a ``(B, 6, C, F, F)`` tensor and return it.

    Raises:
        TypeError: not a tensor.
        ValueError: wrong shape.
    """
    if not isinstance(cubemap, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(cubemap).__name__}")
    if cubemap.ndim != 5 or cubemap.shape[1] != 6 or cubemap.shape[3] != cubemap.shape[4]:
        raise ValueError(f"{name} must have shape (B, 6, C, F, F), got {tuple(cubemap.shape)}")
    if cubemap.shape[3] < 1:
        raise ValueError(f"{name} must have F >= 1, got {tuple(cubemap.shape)}")
    return cubemap


def _resolve_plan(cubemap: Tensor, pad: int, mode: str, plan: BorderPlan | None) -> BorderPlan:
    face_size = cubemap.shape[-1]
    if mode not in PAD_MODES:
        raise ValueError(f"mode must be one of {PAD_MODES}, got {mode!r}")
    if mode == "bilinear" and not cubemap.is_floating_point():
        raise TypeError(f"mode='bilinear' needs a floating point cubemap, got {cubemap.dtype}")
    if plan is None:
        plan = border_plan(face_size, pad, mode)
    elif not isinstance(plan, BorderPlan):
        raise TypeError(f"plan must be a BorderPlan, got {type(plan).__name__}")
    elif (plan.face_size, plan.pad, plan.mode) != (face_size, pad, mode):
        raise ValueError(
            f"plan is for (face_size, pad, mode) = {(plan.face_size, plan.pad, plan.mode)}, "
            f"the call needs {(face_size, pad, mode)}"
        )
    return plan


@functools.lru_cache(maxsize=64)
def _applied(plan: BorderPlan, device: torch.device, dtype: torch.dtype | None
             ) -> tuple[Tensor, Tensor, Tensor | None]:
    """``(dst, src, weight)`` ready to apply: ``src`` re-indexed into the padded layout (the
    interior of the output, already filled), flattened; ``weight`` None for one-tap plans."""
    f, p = plan.face_size, plan.pad
    n = f + 2 * p
    src = plan.src_index
    face, pix = src // (f * f), src % (f * f)
    src = face * n * n + (pix // f + p) * n + (pix % f + p)
    if plan.mode == "nearest":
        return plan.dst_index.to(device), src[:, 0].to(device).contiguous(), None
    weight = plan.weight.to(device=device, dtype=dtype)
    return plan.dst_index.to(device), src.reshape(-1).to(device), weight


def _pad_flat(cubemap: Tensor, pad: int, mode: str, plan: BorderPlan | None) -> Tensor:
    """Padded cube as ``(B, C, 6 (F + 2p) (F + 2p))``, faces outermost after C.

    One strided copy writes the interior in channel-major order; the border is then gathered
    from that interior and written in place.
    """
    batch, _, channels, face_size, _ = cubemap.shape
    n = face_size + 2 * pad
    per_channel = cubemap.transpose(1, 2)  # [B, C, 6, F, F]
    if pad == 0:
        return per_channel.reshape(batch, channels, 6 * n * n)
    plan = _resolve_plan(cubemap, pad, mode, plan)
    dtype = cubemap.dtype if cubemap.is_floating_point() else None
    dst, src, weight = _applied(plan, cubemap.device, dtype)
    out = cubemap.new_empty(batch, channels, 6, n, n)
    out[..., pad:pad + face_size, pad:pad + face_size] = per_channel
    flat = out.view(batch * channels, 6 * n * n)
    taps = flat[:, src]  # [B C, N K] or [B C, N]; 10x faster than index_select on dim -1
    if weight is None:
        border = taps
    else:
        border = (taps.view(batch * channels, *weight.shape) * weight).sum(-1)
    # Out of place when autograd records: the border is computed from the same tensor.
    if torch.is_grad_enabled() and cubemap.requires_grad:
        flat = flat.index_copy(-1, dst, border)
    else:
        flat.index_copy_(-1, dst, border)
    return flat.view(batch, channels, 6 * n * n)


def pad_faces(
    cubemap: Tensor, pad: int, mode: str = "bilinear", *, plan: BorderPlan | None = None
) -> Tensor:
    """Pad every face with a border resampled from its neighbours.

    Padded texel ``[k, :, i, j]`` is face ``k`` pixel ``(u, v) = (j - pad, i - pad)``; border texels
    hold the cube's value along their own ray (see the module docstring for the bilinear
    border's self-consistent definition near edges and corners). Interior texels are the input.

    Args:
        cubemap: ``(B, 6, C, F, F)`` cube, faces in ``FACES`` order. Floating for
            ``"bilinear"``; any dtype (e.g. integer labels) for ``"nearest"``.
        pad: border width ``p >= 0`` in texels; bilinear sampling needs ``p >= 1``, bicubic
            ``p >= 2``. ``p = 0`` returns the input.
        mode: ``"bilinear"`` or ``"nearest"``.
        plan: a precomputed `border_plan` for ``(F, pad, mode)``, e.g. a layer's buffer;
            default: the cached plan, moved to the cubemap's device and dtype.

    Returns:
        ``(B, 6, C, F + 2p, F + 2p)``, dtype and device of ``cubemap``; differentiable (linear)
        with respect to ``cubemap``.

    Examples:
        >>> cube = torch.rand(2, 6, 3, 16, 16)
        >>> pad_faces(cube, 2).shape
        torch.Size([2, 6, 3, 20, 20])
        >>> labels = torch.randint(0, 13, (2, 6, 1, 16, 16))
        >>> pad_faces(labels, 1, mode="nearest").dtype
        torch.int64
    """
    check_cubemap(cubemap)
    _check_pad(pad)
    if pad == 0:
        if mode not in PAD_MODES:
            raise ValueError(f"mode must be one of {PAD_MODES}, got {mode!r}")
        return cubemap
    batch, _, channels, face_size, _ = cubemap.shape
    n = face_size + 2 * pad
    flat = _pad_flat(cubemap, pad, mode, plan)
    return flat.reshape(batch, channels, 6, n, n).transpose(1, 2)
