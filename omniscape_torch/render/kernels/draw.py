"""The fisheye (and catadioptric) cameras and attitudes the augmentation modules draw: one draw,
from one block of uniforms, for `RandomOmniCamera` and `RandomReproject` alike.

The stream: a call draws `STREAM_WIDTH * n` float64 uniforms in one `torch.rand` call of its
generator, read family by family (`STREAM`: the family, its first row and its row count, in
units of `n` values), every family for every sample whatever its model, so a seed's batch does
not depend on which branch a sample takes:

| family | rows | read as |
|---|---|---|
| `model` | 0 | `(n,)`: catadioptric or not (`mode="mixed"`), then the fisheye model |
| `fov` | 1 | `(n,)` in `fov_range` |
| `k` | 2-5 | `(n, 4)` Kannala-Brandt `k1..k4` in `+-kb_distortion` |
| `lens` | 6-7 | `(n, 2)` the lens parameters of the model (`FisheyeDraw.ranges`) |
| `scale` | 8 | `(n,)` in `focal_scale_range` |
| `jitter` | 9-10 | `(n, 2)` in `+-center_jitter` |
| `attitude` | 11-13 | `(3, n)` yaw, pitch, roll in their ranges |
| `applied` | 14 | `(n,)`: a random attitude where `< p` |
| `coverage` | 15 | `(n,)` in `coverage_range` (`RandomReproject` framed to a pinhole source) |
| `cata_fov` | 16 | `(n,)` in `cata_fov_range` |
| `xi` | 17 | `(n,)` the mirror's `xi` in `xi_range` |

The arithmetic runs in float64 NumPy, a few operations per family for the whole batch (on a
few samples torch's dispatch costs more than it). One case has a C++ twin, the op
`frame_lens`: a fisheye of one model without lens parameters (a radius table, `unit_lens`)
framed to a pinhole source, which is `RandomReproject`'s default; it reads the same stream, its
offsets generated from `STREAM` into the build (`layout.layout_header`), and computes what
`draw_cameras` computes (the rotations within 1e-15, the focals within 1e-12, relative:
`tests/test_draw.py`). `backend` chooses as everywhere in this package.
"""

from __future__ import annotations

from typing import Mapping, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ...cameras.presets import rotation_rows
from ...cameras.registry import MODELS, get_model
from ...cubemap.faces import FACES, face_rotations
from . import framing
from ._backend import choose
from .camera import radial_table
from .layout import SPEC_RANGES, STREAM, STREAM_WIDTH

__all__ = ["DrawSpec", "FISHEYE_MODELS", "MAX_PARAMS", "STREAM", "STREAM_WIDTH", "UnitLens",
           "draw_cameras", "unit_lens", "unit_radius"]

#: The fisheye models the modules draw (`fisheye_models`): those of the registry that say how
#: (`CameraModel.fisheye_draw`), in the registry's order.
FISHEYE_MODELS = tuple(name for name, model in MODELS.items() if model.fisheye_draw is not None)
#: Largest parameter count of the models drawn (unified: fx, fy, cx, cy, xi, k1, k2, p1, p2): the
#: width of `camera_params`, whatever the models drawn.
MAX_PARAMS = 9
#: Kannala-Brandt coefficients are halved (at most this many times, then zeroed) until the
#: polynomial stays monotonic past the drawn half field of view.
KB_SHRINK_STEPS = 8
#: Margin (radians) kept between the drawn half field of view and a model's `max_angle`.
ANGLE_MARGIN = 1e-3
#: The kind of a sample drawn as a catadioptric camera (a unified model under its mirror).
CATADIOPTRIC = "catadioptric"
#: Angles of a lens's radius at focal 1 in `unit_lens` (linear between them: within 1e-9 of the
#: model's radius, relative, out to 200 degrees).
UNIT_ANGLES = 16384
class DrawSpec(NamedTuple):
    """What a draw depends on: the augmentation module's arguments (their docs are the
    modules'), angles in radians.

    `lens_ranges`: per fisheye model with lens parameters, their `(min, max)` ranges in the
    order of `CameraModel.fisheye_draw.ranges`. `coverage_range`: framing to a pinhole source
    (`RandomReproject`); None: the image circle inscribed, times `focal_scale_range`.
    `camera`: a fixed target camera `(model, params, fov or None)` (the modules' `camera`):
    every sample is that camera, its focal scaled by `1 + focal_jitter (2 u - 1)` (`u`: the
    `scale` row) and its centre moved by the `jitter` rows, the attitude drawn as for the
    others; no lens is drawn and no framing applied.
    """

    image_size: tuple[int, int]
    fisheye_models: tuple[str, ...]
    fov_range: tuple[float, float]
    kb_distortion: float
    lens_ranges: Mapping[str, tuple[tuple[float, float], ...]]
    focal_scale_range: tuple[float, float]
    center_jitter: float
    yaw_range: tuple[float, float]
    pitch_range: tuple[float, float]
    roll_range: tuple[float, float]
    p: float
    coverage_range: tuple[float, float] | None = None
    mode: str = "fisheye"
    cata_fov_range: tuple[float, float] = (0.0, 0.0)
    xi_range: tuple[float, float] = (0.0, 0.0)
    blind_fov: float | None = None
    looking: str = "down"
    catadioptric_prob: float = 0.0
    camera: tuple[str, tuple[float, ...], float | None] | None = None
    focal_jitter: float = 0.0


def unit_radius(model: str, extra: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    """Image radius at focal 1 of rays `theta (n,)` from the axis, and its validity, for the
    model's parameters after (fx, fy, cx, cy) `extra (n, E)` (float64)."""
    n = theta.shape[0]
    head = torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64).expand(n, 4)
    params = torch.cat((head, extra), dim=-1)
    points = torch.stack((torch.sin(theta), torch.zeros_like(theta), torch.cos(theta)), -1)
    pixels, valid = get_model(model).project(points, params)
    radius = torch.linalg.vector_norm(pixels, dim=-1)
    return radius, valid & (radius > 0) & torch.isfinite(radius)


class UnitLens(NamedTuple):
    """`unit_lens`: the radius at focal 1 `radius (A,)` at the angles `j / per_angle` and its
    steps `slope (A,)` to the next (float64 NumPy; `tensors`: both as tensors, for the C++
    draw), a row of the cameras' `limits_row (5,)` `scale, root, end` of the table, 0 for
    `cos(fov / 2)`, 2 for no blind cone, and its `tables (1, 2, K)` by dtype (float64,
    float32)."""

    per_angle: float
    radius: np.ndarray
    slope: np.ndarray
    limits_row: np.ndarray
    tables: dict
    tensors: tuple

    def radius_at(self, theta: np.ndarray) -> np.ndarray:
        """The radius at focal 1 at the angles `theta` (within the table), linear between
        its entries (`np.interp`'s values, without its search)."""
        at = theta * self.per_angle
        j = np.minimum(at.astype(np.intp), len(self.radius) - 2)
        return self.radius[j] + (at - j) * self.slope[j]


def unit_lens(name: str, max_fov: float, image_size: tuple[int, int], cache: dict
              ) -> UnitLens | None:
    """For a lens without parameters (`FisheyeDraw.fixed_reach`: equidistant, equisolid,
    stereographic), None for the others: its radius at focal 1 at `UNIT_ANGLES` angles out past
    the widest half field of view drawn (`max_fov / 2`), and its radius -> ray table
    (`camera.radial_table` of the camera of focal 1 out to that radius, whatever each call's
    focal; the pixels beyond are invalid, outside every drawn field of view). Made once per
    `(name, max_fov, image_size)` and kept in `cache` (the module's)."""
    draw = get_model(name).fisheye_draw
    if draw is None or not draw.fixed_reach:
        return None
    key = (name, max_fov, image_size)
    unit = cache.get(key)
    if unit is None:
        f64 = dict(dtype=torch.float64)
        half = 0.5 * max_fov     # < the model's reach (the modules' range checks)
        limit = float(get_model(name).max_angle(torch.ones(1, 4, **f64)))
        step = min(half + 0.02, 0.5 * (half + limit)) / (UNIT_ANGLES - 1)
        theta = torch.arange(UNIT_ANGLES, **f64) * step
        radius, _ = unit_radius(name, torch.zeros(UNIT_ANGLES, 0, **f64), theta)
        radius[0] = 0.0
        _, limits, table = radial_table(name, torch.tensor([[1.0, 1.0, 0.0, 0.0]], **f64),
                                        image_size, reach=float(radius[-1]))
        limits = limits[0, :3].clone()
        limits[2] = limits[2].clamp_max(radius[-1])   # valid within the table only
        radius = radius.numpy()
        slope = np.append(np.diff(radius), 0.0)
        unit = UnitLens(1 / step, radius, slope, np.append(limits.numpy(), (0.0, 2.0)),
                        {torch.float64: table, torch.float32: table.float()},
                        (torch.from_numpy(radius), torch.from_numpy(slope)))
        cache[key] = unit
    return unit


def _rows(u: np.ndarray, n: int, family: str) -> np.ndarray:
    """The family's uniforms, `(n, rows)` (`attitude`: `(3, n)`)."""
    first, rows = STREAM[family]
    block = u[first * n:(first + rows) * n]
    return block.reshape(rows, n) if family == "attitude" else block.reshape(n, rows)


def _scaled(u: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    """Uniforms `u` in `[0, 1)` to `[lo, hi]` (exactly `lo` when `lo == hi`)."""
    lo, hi = bounds
    return lo + (hi - lo) * u


def _monotonic_kb(k: Tensor, half: Tensor) -> Tensor:
    """`(n, 4)` coefficients halved until `max_angle > half + margin` (zero at worst): every
    halving judged in one call of `max_angle` (a polynomial root per row), the first good one
    kept."""
    n, steps = k.shape[0], KB_SHRINK_STEPS + 1
    scales = 0.5 ** torch.arange(steps, dtype=k.dtype)
    candidates = k[:, None, :] * scales[None, :, None]                   # (n, steps, 4)
    params = torch.cat((torch.ones(n, steps, 4, dtype=k.dtype), candidates), -1)
    good = get_model("kannala_brandt").max_angle(params) > (half + ANGLE_MARGIN)[:, None]
    first = torch.where(good.any(-1), good.int().argmax(-1), steps)      # (n,)
    chosen = candidates.gather(1, first.clamp_max(steps - 1)[:, None, None].expand(n, 1, 4))
    return torch.where((first < steps)[:, None], chosen[:, 0], torch.zeros_like(k))


def fisheye_lens(spec: DrawSpec, name: str, half: np.ndarray, k: np.ndarray, lens: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The parameters after (fx, fy, cx, cy) `(n, E)` of `n` fisheye lenses of model `name`
    with half fields of view `half (n,)`, and the half fields of view they see: distorted
    lenses (`FisheyeDraw.distortion`, Kannala-Brandt) with `k (n, 4)` halved until monotonic
    past `half`; the parameters of the others from the uniforms `lens (n, 2)` in their ranges,
    `half` capped `ANGLE_MARGIN` inside the reach of the drawn lens."""
    draw = get_model(name).fisheye_draw
    n = half.shape[0]
    if draw.distortion:
        return _monotonic_kb(torch.from_numpy(k), torch.from_numpy(half)).numpy(), half
    if not draw.ranges:
        return np.zeros((n, 0)), half
    columns = [_scaled(lens[:, j], bounds) for j, bounds in enumerate(spec.lens_ranges[name])]
    extra = np.concatenate((np.stack(columns, -1), np.zeros((n, draw.zeros))), -1)
    reach = get_model(name).max_angle(torch.from_numpy(
        np.concatenate((np.ones((n, 4)), extra), -1))).numpy()
    return extra, np.minimum(half, reach - ANGLE_MARGIN)


def to_edge(spec: DrawSpec, centre: np.ndarray, cache: dict) -> np.ndarray:
    """`framing.to_edge` of the output from `centre (n, 2)`: `(1, D)` made once per image
    size where every centre is the image's (no `center_jitter`), else `(n, D)`."""
    if spec.center_jitter != 0:
        return framing.to_edge(centre, spec.image_size)
    key = ("to_edge", spec.image_size)
    edges = cache.get(key)
    if edges is None:
        edges = cache[key] = framing.to_edge(centre[:1], spec.image_size)
    return edges


def _framed_focal(spec: DrawSpec, name: str, extra: np.ndarray, half: np.ndarray,
                  rotation: np.ndarray, intrinsics: np.ndarray, source_size: tuple[int, int],
                  centre: np.ndarray, coverage: np.ndarray, cache: dict, backend: str
                  ) -> np.ndarray:
    """`(n,)` focals at which the pinhole sources fill the shares `coverage` of the output
    (`framing`), for lenses `extra`, `half` centred at `centre (n, 2)`. The lens radius at focal
    1 of a lens without parameters comes from its table (`unit_lens`, linear between its
    angles: within 1e-9 of the model's), of the others from the model's projection."""
    theta = framing.reach(rotation, intrinsics, source_size, half, backend=backend)   # (n, D)
    unit = unit_lens(name, spec.fov_range[1], spec.image_size, cache)
    if unit is not None:
        radius = unit.radius_at(theta)
    else:
        n, d = theta.shape
        radius = unit_radius(name, torch.from_numpy(extra).repeat_interleave(d, 0),
                             torch.from_numpy(theta.reshape(-1)))[0].numpy().reshape(n, d)
    return framing.focal_for_coverage(radius, to_edge(spec, centre, cache), coverage,
                                      spec.image_size, backend=backend)


def _centres(spec: DrawSpec, u: np.ndarray, n: int, cache: dict) -> np.ndarray:
    """`(n, 2)` principal points: the image's centre plus the drawn jitter (`(1, 2)`, made once,
    without jitter)."""
    h, w = spec.image_size
    key = ("centre", spec.image_size)
    centre = cache.get(key)
    if centre is None:
        centre = cache[key] = np.array([[(w - 1) / 2, (h - 1) / 2]])
    if spec.center_jitter == 0:
        return centre
    return (2 * _rows(u, n, "jitter") - 1) * spec.center_jitter + centre


def _draw_one_lens(spec: DrawSpec, ops, u: Tensor, n: int, source: Tensor,
                   source_size: tuple[int, int], cache: dict) -> dict:
    """`draw_cameras` of `n` fisheyes of the one lens of `fisheye_models`, which has a table,
    framed to the pinholes `source (n, 4)`, by the C++ op `frame_lens`."""
    name = spec.fisheye_models[0]
    unit = unit_lens(name, spec.fov_range[1], spec.image_size, cache)
    h, w = spec.image_size
    key = ("spec", spec.fov_range, spec.yaw_range, spec.pitch_range, spec.roll_range,
           spec.coverage_range, spec.p)
    spec_t = cache.get(key)
    if spec_t is None:   # the ranges and p as the op reads them
        values = [v for field in SPEC_RANGES for v in getattr(spec, field)] + [spec.p]
        spec_t = cache[key] = torch.tensor(values, dtype=torch.float64)
    centre = _centres(spec, u.numpy(), n, cache)
    edges = torch.from_numpy(to_edge(spec, centre, cache))
    f64 = dict(dtype=torch.float64)
    params, fov, attitude, applied, rotation, coverage = (
        torch.zeros(n, MAX_PARAMS, **f64), torch.empty(n, **f64), torch.empty(3, n, **f64),
        torch.empty(n, dtype=torch.bool), torch.empty(n, 3, 3, **f64), torch.empty(n, **f64))
    ops.frame_lens(u, spec_t, source.contiguous(), torch.from_numpy(centre), *framing.COS_SIN,
                   *source_size, *unit.tensors, unit.per_angle, edges, h, w, params, fov,
                   attitude, applied, rotation, coverage)
    yaw, pitch, roll = attitude
    return {"camera_params": params, "num_params": torch.full((n,), 4), "fov": fov,
            "blind_fov": torch.zeros(n, **f64), "yaw": yaw, "pitch": pitch, "roll": roll,
            "applied": applied, "rotation": rotation, "model": (name,) * n,
            "coverage": coverage}


def scaled_params(model: str) -> tuple[int, ...]:
    """The parameters of `model` that scale with the image (a focal jitter): `fx, fy`, or the
    polynomial in pixels of `woodscape` (`k1..k4`) and `scaramuzza` (`a0..`: its image
    radius); `()` where there are none."""
    names = get_model(model).param_names
    focal = tuple(i for i, n in enumerate(names) if n in ("fx", "fy"))
    if focal or model not in ("woodscape", "scaramuzza"):
        return focal
    return tuple(i for i, n in enumerate(names) if n[0] in "ka" and n[1:].isdigit())


def _fixed_camera(spec: DrawSpec, u: np.ndarray, n: int) -> dict:
    """`draw_cameras` of a fixed target camera (`DrawSpec.camera`): its parameters per sample
    with the focal and centre jitter, its field of view (or its model's reach)."""
    name, base, fov = spec.camera
    p = len(base)
    rows = np.tile(np.asarray(base, dtype=np.float64), (n, 1))
    if spec.focal_jitter:
        scale = 1 + spec.focal_jitter * (2 * _rows(u, n, "scale")[:, 0] - 1)
        index = list(scaled_params(name))
        rows[:, index] *= scale[:, None]
    if spec.center_jitter:   # the camera's own centre, moved
        names = get_model(name).param_names
        jitter = (2 * _rows(u, n, "jitter") - 1) * spec.center_jitter
        rows[:, [names.index("cx"), names.index("cy")]] += jitter
    if fov is None:
        reach = get_model(name).max_angle(torch.from_numpy(rows)).numpy()
        fovs = np.minimum(2 * reach, 2 * np.pi)
    else:
        fovs = np.full(n, float(fov))
    params = np.zeros((n, max(MAX_PARAMS, p)))
    params[:, :p] = rows
    return {"camera_params": torch.from_numpy(params),
            "num_params": torch.full((n,), p, dtype=torch.int64),
            "fov": torch.from_numpy(fovs), "blind_fov": torch.zeros(n, dtype=torch.float64),
            "model": (name,) * n}


def draw_cameras(spec: DrawSpec, u: Tensor, n: int, *, source: Tensor | None = None,
                 source_size: tuple[int, int] | None = None, cache: dict | None = None,
                 backend: str = "auto") -> dict:
    """`n` cameras and attitudes from the uniforms `u (STREAM_WIDTH n,)` (module docstring).

    Args:
        spec: the module's ranges.
        u: `(STREAM_WIDTH * n,)` float64 uniforms in `[0, 1)`, on the CPU.
        n: the samples drawn.
        source: `(n, 4)` float64 pinhole `fx, fy, cx, cy` of the sources the focal is framed to
            (`spec.coverage_range`), or None: the image circle inscribed.
        source_size: `(Hs, Ws)` of those sources.
        cache: what depends on `spec` alone, kept between calls (the module's dict).
        backend: `"auto"`, `"cpp"` or `"torch"` (the package's `_backend`): the C++ op
            `frame_lens` for the one case it covers (module docstring), else NumPy.

    Returns:
        dict, float64 CPU tensors: `model` (tuple of `n` names), `camera_params (n, 9)`
        (zero-padded), `num_params (n,)`, `fov`, `blind_fov`, `yaw`, `pitch`, `roll (n,)`,
        `applied (n,)` bool, `rotation (n, 3, 3)` camera -> cube (or source) frame; framed:
        `coverage (n,)`.
    """
    if not (isinstance(u, Tensor) and u.dtype == torch.float64 and u.shape == (STREAM_WIDTH * n,)):
        raise ValueError(f"u: expected ({STREAM_WIDTH} n,) = ({STREAM_WIDTH * n},) float64 "
                         f"uniforms, got {getattr(u, 'dtype', type(u).__name__)} "
                         f"{tuple(getattr(u, 'shape', ()))}")
    framed = source is not None and spec.coverage_range is not None
    if framed and (source_size is None or tuple(source.shape) != (n, 4)):
        raise ValueError(f"source: expected (n, 4) = ({n}, 4) intrinsics with source_size, got "
                         f"{tuple(source.shape)} and {source_size}")
    cache = {} if cache is None else cache
    one_table = (framed and spec.camera is None and spec.mode == "fisheye"
                 and len(spec.fisheye_models) == 1
                 and unit_lens(spec.fisheye_models[0], spec.fov_range[1], spec.image_size,
                               cache) is not None)
    ops = choose(backend, u, what="draw_cameras") if one_table else None
    if ops is not None:
        return _draw_one_lens(spec, ops, u, n, source, source_size, cache)
    u = u.numpy()
    h, w = spec.image_size
    u_model = _rows(u, n, "model")[:, 0]
    fov = _scaled(_rows(u, n, "fov")[:, 0], spec.fov_range)
    k = (2 * _rows(u, n, "k") - 1) * spec.kb_distortion
    lens = _rows(u, n, "lens")
    scale = _scaled(_rows(u, n, "scale")[:, 0], spec.focal_scale_range)
    applied = _rows(u, n, "applied")[:, 0] < spec.p
    bounds = np.array((spec.yaw_range, spec.pitch_range, spec.roll_range))     # (3, 2)
    attitude = np.where(applied, _scaled(_rows(u, n, "attitude"), bounds.T[..., None]), 0.0)
    yaw, pitch, roll = attitude
    coverage = _scaled(_rows(u, n, "coverage")[:, 0], spec.coverage_range) if framed else None
    cos, sin = np.cos(attitude), np.sin(attitude)
    rotation = np.stack([entry for row in rotation_rows(
        cos[0], sin[0], cos[1], sin[1], cos[2], sin[2]) for entry in row], -1).reshape(n, 3, 3)
    centre = np.broadcast_to(_centres(spec, u, n, cache), (n, 2))
    if spec.camera is not None:
        out = _fixed_camera(spec, u, n)
        out.update({key: torch.from_numpy(np.ascontiguousarray(value)) for key, value in (
            ("yaw", yaw), ("pitch", pitch), ("roll", roll), ("applied", applied),
            ("rotation", rotation))})
        return out

    # catadioptric or fisheye; the same uniform picks the fisheye model, rescaled to [0, 1)
    # on the fisheye branch
    if spec.mode == "fisheye":
        cata, u_fish = np.zeros(n, dtype=bool), u_model
    elif spec.mode == "catadioptric":
        cata, u_fish = np.ones(n, dtype=bool), u_model
    else:
        prob = spec.catadioptric_prob
        cata, u_fish = u_model < prob, (u_model - prob) / max(1 - prob, 1e-12)
    index = (np.clip(u_fish, 0, 1 - 1e-12) * len(spec.fisheye_models)).astype(np.int64)
    kinds = np.where(cata, -1, index)   # -1: catadioptric
    if cata.any():
        fov = np.where(cata, _scaled(_rows(u, n, "cata_fov")[:, 0], spec.cata_fov_range), fov)
        mount = face_rotations(torch.float64)[FACES.index(spec.looking)].numpy()
        rotation = np.where(cata[:, None, None], rotation @ mount, rotation)
    source = None if source is None else source[:n].numpy()
    params = np.zeros((n, MAX_PARAMS))
    num_params = np.zeros(n, dtype=np.int64)
    present = np.unique(kinds).tolist()
    for kind in present:
        idx = slice(None) if len(present) == 1 else kinds == kind
        half = 0.5 * fov[idx]
        if kind < 0:   # under or over its mirror: xi_range, no distortion
            name = "unified"
            xi = _scaled(_rows(u, n, "xi")[idx, 0], spec.xi_range)
            extra = np.concatenate((xi[:, None], np.zeros((len(half), 4))), -1)
        else:
            name = spec.fisheye_models[kind]
            extra, half = fisheye_lens(spec, name, half, k[idx], lens[idx])
            fov[idx] = 2 * half
        if framed and kind >= 0:
            focal = _framed_focal(spec, name, extra, half, rotation[idx], source[idx],
                                  source_size, centre[idx], coverage[idx], cache, backend)
        else:
            radius, ok = unit_radius(name, torch.from_numpy(extra), torch.from_numpy(half))
            if not bool(ok.all()):   # guarded by the modules' range checks: a bug if so
                raise RuntimeError(f"{name}: drawn field of view outside the model's domain")
            focal = scale[idx] * (min(h, w) / 2 - 0.5) / radius.numpy()
        row = np.concatenate((focal[:, None], focal[:, None], centre[idx], extra), -1)
        params[idx, :row.shape[-1]] = row
        num_params[idx] = row.shape[-1]
    blind = np.where(cata, spec.blind_fov or 0.0, 0.0)
    out = {key: torch.from_numpy(np.ascontiguousarray(value)) for key, value in (
        ("camera_params", params), ("num_params", num_params), ("fov", fov),
        ("blind_fov", blind), ("yaw", yaw), ("pitch", pitch), ("roll", roll),
        ("applied", applied), ("rotation", rotation))}
    out["model"] = tuple("unified" if kind < 0 else spec.fisheye_models[kind]
                         for kind in kinds.tolist())
    if framed:
        out["coverage"] = torch.from_numpy(coverage)
    return out
