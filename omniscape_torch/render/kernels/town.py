"""The built-in town's shading (`omniscape_torch.scenes.Town`): its four C++ ops, their schemas
and fake implementations, and their torch reference twins, side by side.

After Embree's closest hit of each ray (`omniscape_torch.scenes.mesh`), the town calls:

- `backfaces`: which hits a ray meets from behind their face (it started inside a primitive);
- `shade`: labels, range, normal and colour of every ray, with one shadow ray towards the sun
  per lit hit (traced by the caller's `occluded`, Embree's occlusion query);
- `store`: a batch of a cube face's rays written into the face's planes (RGB, range, labels,
  planar depth).

Each checks its arguments, then runs the C++ op (`torch.ops.omniscape_torch.town_*`,
`render/csrc/town_shade.cpp`) or its torch twin, as `backend` says (`"auto"`, `"cpp"` or
`"torch"`; the package's `_backend.choose` decides `"auto"`). The two give the same labels,
ranges, depths and hits, and colours and normals within a few float32 roundings: the same
operations in the same order, but torch's `sqrt` is not correctly rounded on every CPU.
The hits come from Embree, on the CPU: the town always calls these on the CPU (the twins run on
any device, and take the route every call takes on a GPU).

Exactness: every ray is shaded on its own with `+ - * /`, `sqrt`, comparisons and integer
hashing (no transcendental functions, no reductions), so a ray's result does not depend on the
batch it is in.

Layouts (shared with the C++ loops, which name them in enums of the same order):

- `attr (len(ATTRIBUTES), T)` float32: one column per triangle, the rows `ATTRIBUTES` (the
  outward face normal, class id, part kind, albedo, road paint, a box's centre, the index in
  its kind, smooth normals);
- `tris (T, 3)` int32 corners and `vn (V, 3)` float32 vertex normals; `lamps (L, 3)` float32;
- `weather (len(WEATHER),)` float32: the entries `WEATHER` (`weather_vector`).

The schemas are defined here (the C++ source only implements them for the CPU), so that each
op's schema, fake implementation (for `torch.compile`) and wrapper live together.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ...io.labels import CLASSES
from . import build
from ._backend import choose

__all__ = ["ATTRIBUTES", "BOX", "CYLINDER", "GROUND", "LANE_EDGE", "LINE_HALF", "OPS",
           "SHADOW_BIAS", "SHADOW_BIAS_PER_M", "SPHERE", "TownTables", "WEATHER", "backfaces",
           "shade", "store", "weather_vector"]

_C = {name: i for i, name in enumerate(CLASSES)}

#: The rows of the triangles' attribute table ``attr`` (``A_*`` in the C++ source).
ATTRIBUTES = ("nx", "ny", "nz", "label", "kind", "r", "g", "b", "paint", "off", "cx", "cy",
              "index", "smooth")
#: The entries of the weather vector (``W_*`` in the C++ source): `weather_vector`.
WEATHER = ("sun_x", "sun_y", "sun_z", "sun_r", "sun_g", "sun_b", "ambient_r", "ambient_g",
           "ambient_b", "zenith_r", "zenith_g", "zenith_b", "horizon_r", "horizon_g",
           "horizon_b", "fog_r", "fog_g", "fog_b", "fog_per_256", "lamps", "windows", "puddles",
           "darken", "rain_sky", "haze", "far")
_W = {name: i for i, name in enumerate(WEATHER)}

#: Part kinds (row ``kind`` of ``attr``).
GROUND, BOX, CYLINDER, SPHERE = 0, 1, 2, 3
#: Road paint (metres across a street's centre line): the lane edges' lines at ``LANE_EDGE``,
#: every line ``2 * LINE_HALF`` wide.
LANE_EDGE, LINE_HALF = 3.5, 0.08
#: A shadow ray starts ``SHADOW_BIAS + SHADOW_BIAS_PER_M * range`` metres off the surface,
#: along its normal: far above the rounding of the hit point (about ``1e-7 * range``).
SHADOW_BIAS, SHADOW_BIAS_PER_M = 1e-3, 1e-5

# Ground colours by class (the road markings' RoadLine, the lots' Other).
_GROUND_COLOUR = torch.zeros(13, 3)
_GROUND_COLOUR[_C["Road"]] = torch.tensor([0.26, 0.26, 0.27])
_GROUND_COLOUR[_C["RoadLine"]] = torch.tensor([0.85, 0.85, 0.8])
_GROUND_COLOUR[_C["Sidewalk"]] = torch.tensor([0.62, 0.60, 0.56])
_GROUND_COLOUR[_C["Other"]] = torch.tensor([0.42, 0.38, 0.28])


class TownTables(NamedTuple):
    """What the shading reads of a town's mesh (module docstring: layouts)."""

    #: ``(len(ATTRIBUTES), T)`` float32: the triangles' attributes.
    attr: Tensor
    #: ``(T, 3)`` int32: the triangles' corners.
    tris: Tensor
    #: ``(V, 3)`` float32: the vertex normals.
    vn: Tensor
    #: ``(L, 3)`` float32: the street lamps (world, metres).
    lamps: Tensor


def weather_vector(*, sun_direction, sun_colour, ambient, sky_zenith, sky_horizon, fog_colour,
                   fog_density: float, lamps: float, windows: float, wetness: float,
                   darken: float, rain_sky: float, far: float) -> Tensor:
    """The ``(len(WEATHER),)`` float32 weather vector that `shade` reads.

    Args:
        sun_direction: unit vector towards the sun (world frame, y down).
        sun_colour: the sun's linear RGB.
        ambient: the ambient light's linear RGB.
        sky_zenith: the sky's linear RGB straight up.
        sky_horizon: the sky's linear RGB at the horizon.
        fog_colour: the fog's linear RGB.
        fog_density: per metre (the fog weight is about ``1 - exp(-fog_density * range)``).
        lamps: street-lamp intensity (0: off).
        windows: emission of lit windows (0: none).
        wetness: 0..1, the share of the road and sidewalk that puddles (mirroring the sky)
            cover.
        darken: the albedo factor of wet surfaces (1: dry).
        rain_sky: the sky's brightness factor under rain (1: none).
        far: range (metres) reported for the sky.
    """
    values = [*sun_direction, *sun_colour, *ambient, *sky_zenith, *sky_horizon, *fog_colour,
              fog_density / 256.0, lamps * 30.0, windows, 0.75 * wetness, darken, rain_sky,
              min(1.0, fog_density * 40.0), far]
    return torch.tensor(np.array(values, dtype=np.float32))


# ------------------------------------------------------------------------------------------
# The ops: schemas and fake implementations
# ------------------------------------------------------------------------------------------

#: The ops' schemas, defined here in the package's namespace (implemented in C++ for the CPU).
OPS = {
    "town_backfaces": "(Tensor d, Tensor tri, Tensor attr, Tensor(a!) out) -> ()",
    "town_prepare": "(Tensor o, Tensor d, Tensor t, Tensor tri, Tensor u, Tensor v, "
                    "Tensor attr, Tensor tris, Tensor vn, Tensor weather, float bias0, "
                    "float bias_per_m, Tensor(a!) need, Tensor(b!) origin, "
                    "Tensor(c!) shadow) -> ()",
    "town_shade": "(Tensor o, Tensor d, Tensor t, Tensor tri, Tensor u, Tensor v, Tensor attr, "
                  "Tensor tris, Tensor vn, Tensor weather, Tensor shadow, Tensor lamps, "
                  "Tensor(a!) rgb, Tensor(b!) range, Tensor(c!) labels, "
                  "Tensor(d!) normal) -> ()",
    "town_store": "(Tensor d, Tensor? index, int start, Tensor rgb, Tensor range, "
                  "Tensor labels, Tensor hit, Tensor axis, float far, Tensor(a!) rgb_out, "
                  "Tensor(b!) depth_out, Tensor(c!) range_out, Tensor(d!) labels_out) -> ()",
}


def _check(cond: bool, message: str) -> None:
    torch._check(cond, lambda: f"{build.NAMESPACE}: {message}")


def _fake_rays(o, d, t, tri, u, v, what: str) -> None:
    n = d.shape[0]
    _check(d.dim() == 2 and d.shape[1] == 3 and o.dim() == 2 and o.shape[1] == 3
           and o.shape[0] in (1, n) and t.shape == tri.shape == u.shape == v.shape == (n,),
           f"{what}: expected o (n or 1, 3), d (n, 3), t, tri, u, v (n,)")


def _fake_town_backfaces(d, tri, attr, out) -> None:
    _check(d.dim() == 2 and d.shape[1] == 3 and tri.shape == out.shape == (d.shape[0],),
           "town_backfaces: expected d (n, 3), tri and out (n,)")


def _fake_town_prepare(o, d, t, tri, u, v, attr, tris, vn, weather, bias0, bias_per_m, need,
                       origin, shadow) -> None:
    _fake_rays(o, d, t, tri, u, v, "town_prepare")
    _check(need.shape == shadow.shape == (d.shape[0],) and origin.shape == d.shape,
           "town_prepare: expected need, shadow (n,) and origin (n, 3)")


def _fake_town_shade(o, d, t, tri, u, v, attr, tris, vn, weather, shadow, lamps, rgb, range_,
                     labels, normal) -> None:
    _fake_rays(o, d, t, tri, u, v, "town_shade")
    _check(rgb.shape == normal.shape == d.shape and range_.shape == labels.shape
           == shadow.shape == (d.shape[0],),
           "town_shade: expected rgb, normal (n, 3), shadow, range, labels (n,)")


def _fake_town_store(d, index, start, rgb, range_, labels, hit, axis, far, rgb_out, depth_out,
                     range_out, labels_out) -> None:
    _check(rgb.shape == d.shape and rgb_out.dim() == 2 and rgb_out.shape[0] == 3
           and depth_out.shape == range_out.shape == labels_out.shape == (rgb_out.shape[1],),
           "town_store: expected d, rgb (n, 3), rgb_out (3, P), depth_out, range_out and "
           "labels_out (P,)")


#: The ops' fake implementations (for ``torch.compile``), registered with their schemas.
_FAKES = {"town_backfaces": _fake_town_backfaces, "town_prepare": _fake_town_prepare,
         "town_shade": _fake_town_shade, "town_store": _fake_town_store}
_LIBRARY = build.define(OPS, _FAKES)   # the registration's handle: the ops live while it does


# ------------------------------------------------------------------------------------------
# Argument checks
# ------------------------------------------------------------------------------------------

def _expect(name: str, t: object, dtype: torch.dtype, shape: tuple) -> Tensor:
    """``t`` if it is a tensor of ``dtype`` and ``shape`` (-1: any size), else a ValueError
    naming ``name``."""
    if not isinstance(t, Tensor):
        raise TypeError(f"{name}: expected a tensor, got {type(t).__name__}")
    if t.dtype != dtype or t.dim() != len(shape) or any(
            s >= 0 and size != s for s, size in zip(shape, t.shape)):
        want = ", ".join("n" if s < 0 else str(s) for s in shape)
        raise ValueError(f"{name}: expected ({want}) {dtype}, got {tuple(t.shape)} {t.dtype}")
    return t


def _check_tri(tri: Tensor, triangles: int) -> None:
    if tri.numel() and (int(tri.min()) < -1 or int(tri.max()) >= triangles):
        raise ValueError(f"tri: expected triangle indices in [-1, {triangles}), got some in "
                         f"[{int(tri.min())}, {int(tri.max())}]")


def _check_tables(tables: TownTables) -> None:
    if not isinstance(tables, TownTables):
        raise TypeError(f"tables: expected a TownTables, got {type(tables).__name__}")
    _expect("tables.attr", tables.attr, torch.float32, (len(ATTRIBUTES), -1))
    _expect("tables.tris", tables.tris, torch.int32, (tables.attr.shape[1], 3))
    _expect("tables.vn", tables.vn, torch.float32, (-1, 3))
    _expect("tables.lamps", tables.lamps, torch.float32, (-1, 3))


def _check_hits(o: Tensor, d: Tensor, t: Tensor, tri: Tensor, u: Tensor, v: Tensor) -> int:
    """The number of rays ``n`` of the rays and their hits (`shade`'s Args)."""
    n = _expect("d", d, torch.float32, (-1, 3)).shape[0]
    _expect("o", o, torch.float32, (-1, 3))
    if o.shape[0] not in (1, n):
        raise ValueError(f"o: expected (1, 3) or ({n}, 3) like d, got {tuple(o.shape)}")
    for name, x in (("t", t), ("u", u), ("v", v)):
        _expect(name, x, torch.float32, (n,))
    _expect("tri", tri, torch.int64, (n,))
    return n


# ------------------------------------------------------------------------------------------
# The computations
# ------------------------------------------------------------------------------------------

def backfaces(d: Tensor, tri: Tensor, attr: Tensor, *, backend: str = "auto") -> Tensor:
    """``(n,)`` bool: the hits ``tri (n,)`` int64 (-1: none) that rays ``d (n, 3)`` float32
    meet from behind their face (``attr``'s rows ``nx, ny, nz``: the outward face normal).

    Args:
        d: ``(n, 3)`` float32 ray directions.
        tri: ``(n,)`` int64 triangle hit by each ray, -1 for none.
        attr: ``(len(ATTRIBUTES), T)`` float32 triangle attributes.
        backend: ``"auto"``, ``"cpp"`` or ``"torch"`` (module docstring).
    """
    n = _expect("d", d, torch.float32, (-1, 3)).shape[0]
    _expect("tri", tri, torch.int64, (n,))
    _expect("attr", attr, torch.float32, (len(ATTRIBUTES), -1))
    _check_tri(tri, attr.shape[1])
    ops = choose(backend, d, tri, attr, what="town backfaces")
    if ops is None:
        return _backfaces_torch(d, tri, attr)
    out = torch.empty(n, dtype=torch.bool)
    ops.town_backfaces(d.contiguous(), tri.contiguous(), attr.contiguous(), out)
    return out


def _backfaces_torch(d: Tensor, tri: Tensor, attr: Tensor) -> Tensor:
    """`backfaces` in torch."""
    fn = attr[:3].index_select(1, tri.clamp(min=0))
    return (tri >= 0) & (fn[0] * d[:, 0] + fn[1] * d[:, 1] + fn[2] * d[:, 2] > 0)


def shade(o: Tensor, d: Tensor, t: Tensor, tri: Tensor, u: Tensor, v: Tensor,
          tables: TownTables, weather: Tensor,
          occluded: Callable[[np.ndarray, np.ndarray], np.ndarray], *,
          backend: str = "auto") -> dict[str, Tensor]:
    """Labels, range, normal and colour of rays from their closest hits.

    Colour is ``albedo(class, world point) * (ambient + sun * lambert * lit) + emission``
    (street lamps, lit windows; puddles mirror the sky), then distance fog; ``lit`` is 0 where
    the shadow ray towards the sun meets anything (``occluded``). The sky's colour where a ray
    hits nothing.

    Args:
        o: ``(n, 3)`` or ``(1, 3)`` float32 ray origins (world, metres).
        d: ``(n, 3)`` float32 unit directions.
        t: ``(n,)`` float32 range of each hit (any value where none).
        tri: ``(n,)`` int64 triangle hit, -1 for none.
        u: ``(n,)`` float32 first barycentric coordinate of the hits.
        v: ``(n,)`` float32 second barycentric coordinate of the hits.
        tables: the town's `TownTables`.
        weather: ``(len(WEATHER),)`` float32, `weather_vector`.
        occluded: ``occluded(origins (m, 3), directions (m, 3)) -> (m,)`` bool, float32 numpy
            arrays: whether each shadow ray meets anything (Embree's occlusion query).
        backend: ``"auto"``, ``"cpp"`` or ``"torch"`` (module docstring).

    Returns:
        dict with ``rgb (n, 3)`` float32 in [0, 1], ``range (n,)`` metres (``far`` of the
        weather vector for the sky), ``labels (n,)`` int64, ``normal (n, 3)`` (facing the ray;
        ``-d`` for the sky) and ``hit (n,)`` bool.
    """
    n = _check_hits(o, d, t, tri, u, v)
    _check_tables(tables)
    _expect("weather", weather, torch.float32, (len(WEATHER),))
    _check_tri(tri, tables.attr.shape[1])
    ops = choose(backend, o, d, t, tri, u, v, *tables, weather, what="town shade")
    if ops is None:
        return _shade_torch(o, d, t, tri, u, v, tables, weather, occluded)
    common = [x.contiguous() for x in (o, d, t, tri, u, v, tables.attr, tables.tris, tables.vn,
                                       weather)]
    need = torch.empty(n, dtype=torch.bool)
    origin = torch.empty(n, 3)
    shadow = torch.empty(n, dtype=torch.bool)
    ops.town_prepare(*common, SHADOW_BIAS, SHADOW_BIAS_PER_M, need, origin, shadow)
    lit = np.flatnonzero(need.numpy())
    if lit.size:
        towards = np.broadcast_to(weather[:3].numpy(), (lit.size, 3))
        shadow.numpy()[lit] = occluded(origin.numpy()[lit], towards)
    rgb = torch.empty(n, 3)
    rng = torch.empty(n)
    labels = torch.empty(n, dtype=torch.int64)
    normal = torch.empty(n, 3)
    lamps = tables.lamps if float(weather[_W["lamps"]]) > 0 else tables.lamps[:0]
    ops.town_shade(*common, shadow, lamps.contiguous(), rgb, rng, labels, normal)
    return {"rgb": rgb, "range": rng, "labels": labels, "normal": normal, "hit": tri >= 0}


# Procedural textures (integer hashing and floor only: exact on every code path)

def _hash(*ints: Tensor, salt: int = 0) -> Tensor:
    """Integer hash of int64 tensors -> float in [0, 1)."""
    h = torch.full_like(ints[0], 0x9E3779B9 + salt * 0x632BE5AB)
    for k, v in zip((73856093, 19349663, 83492791), ints):
        h = (h ^ (v * k)) & 0xFFFFFFFF
        h = (h * 0x45D9F3B) & 0xFFFFFFFF
        h = h ^ (h >> 16)
    return (h & 0xFFFF).to(torch.float32) / 65536.0


def _cell(x: Tensor, scale: float) -> Tensor:
    return torch.floor(x * scale).to(torch.int64)


def _frac(x: Tensor) -> Tensor:
    return x - torch.floor(x)


def _noise(x: Tensor, y: Tensor, z: Tensor, scale: float, salt: int) -> Tensor:
    """Value noise in [0, 1): a hash of the cell of ``(x, y, z)`` on a grid of ``1 / scale``
    metres."""
    h = ((_cell(x, scale) * 73856093) ^ (_cell(y, scale) * 19349663)
         ^ (_cell(z, scale) * 83492791) ^ (0x9E3779B9 + salt * 0x632BE5AB))
    h = (h * 0x45D9F3B) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    h = (h * 0x45D9F3B) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return (h & 0xFFFF).to(torch.float32) * (1.0 / 65536.0)


def _smooth_noise(x: Tensor, z: Tensor, scale: float, salt: int) -> Tensor:
    """Smooth value noise in [0, 1) over the ground: the hashes of the four corners of the cell
    of ``(x, z)`` on a grid of ``1 / scale`` metres, blended with smoothstep weights."""
    sx, sz = x * scale, z * scale
    ix, iz = torch.floor(sx), torch.floor(sz)
    fx, fz = sx - ix, sz - iz
    wx, wz = fx * fx * (3.0 - 2.0 * fx), fz * fz * (3.0 - 2.0 * fz)
    ix, iz = ix.to(torch.int64), iz.to(torch.int64)
    zero = torch.zeros_like(ix)
    h00, h10 = _hash(ix, zero, iz, salt=salt), _hash(ix + 1, zero, iz, salt=salt)
    h01, h11 = _hash(ix, zero, iz + 1, salt=salt), _hash(ix + 1, zero, iz + 1, salt=salt)
    a = h00 + (h10 - h00) * wx
    b = h01 + (h11 - h01) * wx
    return a + (b - a) * wz


def _column(*values: float) -> Tensor:
    """A colour as a ``(3, 1)`` column, to broadcast over ``(3, N)`` rows."""
    return torch.tensor(values, dtype=torch.float32).reshape(-1, 1)


def _dot(a: Tensor, b) -> Tensor:
    """Row-wise dot product of ``(N, 3)`` with ``(N, 3)`` or ``(3,)``, as explicit sums (the
    same rounding whatever the batch)."""
    return a[:, 0] * b[..., 0] + a[:, 1] * b[..., 1] + a[:, 2] * b[..., 2]


def _shade_torch(o: Tensor, d: Tensor, t: Tensor, tri: Tensor, u: Tensor, v: Tensor,
                 tables: TownTables, weather: Tensor,
                 occluded: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> dict[str, Tensor]:
    """`shade` in torch: the C++ loops' operations in the same order, over rows of rays
    (``x (N,)``, colours ``(3, N)``)."""
    w = weather.tolist()

    def entries(name: str, count: int = 1) -> list[float]:
        return w[_W[name]:_W[name] + count]

    hit = tri >= 0
    tri0 = torch.where(hit, tri, 0)
    tt = torch.where(hit, t, 0.0)
    dx, dy, dz = d.T.contiguous()
    ox, oy, oz = o.T.contiguous()
    px, py, pz = ox + tt * dx, oy + tt * dy, oz + tt * dz
    a = tables.attr.index_select(1, tri0)  # (K, N)
    nfx, nfy, nfz = a[0], a[1], a[2]  # flat, outward (towards the ray)
    label, kind, col = a[3], torch.where(hit, a[4], -1.0), a[5:8]
    nx, ny, nz = nfx.clone(), nfy.clone(), nfz.clone()
    # smooth normals on cylinders and spheres: the vertex normals, interpolated
    sm = torch.nonzero(hit & (a[13] > 0)).flatten()
    if sm.numel():
        corners = tables.tris.index_select(0, tri0[sm])
        us, vs = u[sm].unsqueeze(-1), v[sm].unsqueeze(-1)
        vn = tables.vn
        ns = ((1.0 - us - vs) * vn.index_select(0, corners[:, 0])
              + us * vn.index_select(0, corners[:, 1]) + vs * vn.index_select(0, corners[:, 2]))
        ns = ns / torch.sqrt(_dot(ns, ns)).unsqueeze(-1)
        nx[sm], ny[sm], nz[sm] = ns.T

    # ground: the cell's class, road markings painted on a street's road
    g = kind == GROUND
    paint, off = a[8], a[9]
    along = torch.where(paint == 2, px, pz)
    across = torch.where(paint == 2, pz, px) - off
    aa = across.abs()
    centre = (aa < LINE_HALF) & (_frac(along / 6.0) < 0.5)
    edge = (aa - LANE_EDGE).abs() < LINE_HALF
    cross = ((_frac((along - 20.0) / 60.0) < 4.0 / 60.0) & (aa < LANE_EDGE)
             & (_frac(across) < 0.5))
    line = g & (paint > 0) & (centre | edge | cross)
    label = torch.where(line, float(_C["RoadLine"]), label)
    walk = g & (label == _C["Sidewalk"])
    tiles = walk & ((_frac(px / 0.6) < 0.06) | (_frac(pz / 0.6) < 0.06))
    gcol = _GROUND_COLOUR.T.index_select(1, torch.where(g, label, 0.0).to(torch.int64))
    col = torch.where(g, gcol * torch.where(tiles, 0.75, 1.0), col)

    # textures: noise everywhere, patterns per class on the boxes' faces
    fine = _noise(px, py, pz, 6.0, 1)
    coarse = _noise(px, py, pz, 0.7, 2)
    col = col * (0.8 + 0.25 * fine + 0.15 * coarse)
    b = kind == BOX
    facade_u = torch.where(nfx.abs() > 0.5, pz, px)
    side = b & (nfy == 0)
    fu, fy = _frac(facade_u / 2.5), _frac(py / 3.0)
    win = (side & (label == _C["Building"]) & (fu > 0.25) & (fu < 0.75) & (fy > 0.3)
           & (fy < 0.8) & (py < -1.0))
    col = torch.where(win, _column(0.12, 0.16, 0.22) * (0.7 + 0.6 * fine), col)
    roof = b & (nfy < 0) & (label == _C["Building"])
    col = torch.where(roof, col * 0.45, col)
    row = torch.floor(py / 0.25)
    brick_u = facade_u / 0.5 + 0.5 * (row - 2 * torch.floor(row / 2))
    mortar = side & (label == _C["Wall"]) & ((_frac(py / 0.25) < 0.12)
                                             | (_frac(brick_u) < 0.06))
    col = torch.where(mortar, _column(0.7, 0.68, 0.62), col)
    slat = side & (label == _C["Fence"]) & (_frac(facade_u / 0.15) > 0.75)
    col = torch.where(slat, col * 0.5, col)
    sign = b & (label == _C["TrafficSign"])
    border = torch.maximum((px - a[10]).abs(), (py - a[11]).abs()) > 0.27
    col = torch.where(sign & (border | (nfz > 0)), _column(0.85, 0.85, 0.85), col)

    # wet weather: darker surfaces; puddles on the road and sidewalk mirror the sky
    (darken,) = entries("darken")
    if darken != 1.0:
        col = col * darken

    # light: ambient, the sun unless a shadow ray meets something, street lamps
    sx, sy, sz = entries("sun_x", 3)
    lam = torch.clamp(nx * sx + ny * sy + nz * sz, min=0.0)
    shadow = hit & (lam > 0)
    lit = torch.nonzero(shadow & (nfx * sx + nfy * sy + nfz * sz > 0)).flatten()
    if lit.numel():
        bias = SHADOW_BIAS + SHADOW_BIAS_PER_M * tt[lit]
        origin = torch.stack([px[lit] + nfx[lit] * bias, py[lit] + nfy[lit] * bias,
                              pz[lit] + nfz[lit] * bias], -1)
        towards = torch.tensor([[sx, sy, sz]], dtype=torch.float32).expand(lit.numel(), 3)
        shadow[lit] = torch.from_numpy(occluded(origin.numpy(), towards.numpy()))
    lam = torch.where(shadow, 0.0, lam)
    sun_c = _column(*entries("sun_r", 3))
    light = _column(*entries("ambient_r", 3)) * (0.75 - 0.25 * ny) + sun_c * lam
    (lamps,) = entries("lamps")
    if lamps > 0:
        acc = torch.zeros_like(px)
        for lx, ly, lz in tables.lamps.tolist():
            vx, vy, vz = lx - px, ly - py, lz - pz
            d2 = vx * vx + vy * vy + vz * vz + 0.25
            ndv = torch.clamp(nx * vx + ny * vy + nz * vz, min=0.0)
            acc = acc + ndv / (d2 * torch.sqrt(d2))
        light = light + lamps * acc * _column(1.0, 0.8, 0.5)
    rgb = col * light
    (windows,) = entries("windows")
    if windows > 0:
        lit_win = win & (_hash(_cell(facade_u, 0.4), _cell(py, 1 / 3.0),
                               a[12].to(torch.int64), salt=3) > 0.55)
        rgb = torch.where(lit_win, _column(1.0, 0.82, 0.5) * windows, rgb)

    # the sky of a direction
    fog = _column(*entries("fog_r", 3))
    sky_h, sky_z = _column(*entries("horizon_r", 3)), _column(*entries("zenith_r", 3))
    (hf_scale,) = entries("haze")
    (rain_sky,) = entries("rain_sky")

    def sky_of(ex: Tensor, ey: Tensor, ez: Tensor) -> Tensor:
        up = torch.clamp(-ey, min=0.0)
        h = 1.0 - up
        h = 1.0 - h * h * h
        sky = sky_h + (sky_z - sky_h) * h
        cs = torch.clamp(ex * sx + ey * sy + ez * sz, min=0.0)
        g8 = cs * cs
        g8 = g8 * g8
        g8 = g8 * g8
        g256 = g8
        for _ in range(5):
            g256 = g256 * g256
        sky = sky + sun_c * (0.15 * g8 + 0.8 * g256)
        sky = torch.where(cs > 0.99995, sun_c * 4.0, sky)
        # the sky takes the fog colour near the horizon, more so in thicker fog
        hf = torch.clamp(1.0 - up * 8.0, min=0.0) * hf_scale
        sky = sky + (fog - sky) * hf
        return sky * rain_sky if rain_sky != 1.0 else sky

    (puddles,) = entries("puddles")
    if puddles > 0:
        blot = _smooth_noise(px, pz, 0.35, 4) * 0.65 + _smooth_noise(px, pz, 1.3, 5) * 0.35
        puddle = g & ((label == _C["Road"]) | (label == _C["Sidewalk"])
                      | (label == _C["RoadLine"])) & (blot < puddles)
        q = torch.nonzero(puddle).flatten()
        if q.numel():  # the mirror direction of a horizontal puddle: d with y flipped
            rgb[:, q] = rgb[:, q] * 0.35 + sky_of(dx[q], -dy[q], dz[q]) * 0.55

    # fog: exp(-x) as (1 + x / 256)^-256 (no transcendental, exact across code paths)
    (fog_per_256,) = entries("fog_per_256")
    qf = 1.0 / (1.0 + fog_per_256 * tt)
    for _ in range(8):
        qf = qf * qf
    rgb = rgb * qf + fog * (1.0 - qf)
    rgb = torch.where(hit, rgb, sky_of(dx, dy, dz)).clamp_(0.0, 1.0)
    rng = torch.where(hit, t, entries("far")[0])
    labels = torch.where(hit, label, 0.0).to(torch.int64)
    normal = torch.where(hit, torch.stack([nx, ny, nz]), -d.T)
    return {"rgb": rgb.T, "range": rng, "labels": labels, "normal": normal.T, "hit": hit}


def store(d: Tensor, index: Tensor | None, start: int, shaded: dict[str, Tensor], axis: Tensor,
          far: float, rgb_out: Tensor, depth_out: Tensor, range_out: Tensor,
          labels_out: Tensor, *, backend: str = "auto") -> None:
    """Write a batch of a cube face's rays into the face's planes, in place: their colour,
    range and labels, and the planar depth (range times the ray's component along the face's
    axis; ``far`` for the sky).

    Args:
        d: ``(n, 3)`` float32 ray directions.
        index: ``(n,)`` int64 texels in ``[0, P)`` of the rays, or None for
            ``start .. start + n - 1``.
        start: the first texel where ``index`` is None (else unused).
        shaded: `shade`'s ``rgb (n, 3)``, ``range``, ``labels`` and ``hit (n,)`` of the rays.
        axis: ``(3,)`` float32 the face's axis (world frame).
        far: planar depth of the sky, metres.
        rgb_out: ``(3, P)`` float32, the face's RGB planes (the four planes contiguous where
            ``backend`` is ``"cpp"``).
        depth_out: ``(P,)`` float32, its planar depth.
        range_out: ``(P,)`` float32, its range.
        labels_out: ``(P,)`` int64, its labels.
        backend: ``"auto"``, ``"cpp"`` or ``"torch"`` (module docstring).
    """
    n = _expect("d", d, torch.float32, (-1, 3)).shape[0]
    rgb = _expect("shaded['rgb']", shaded["rgb"], torch.float32, (n, 3))
    rng = _expect("shaded['range']", shaded["range"], torch.float32, (n,))
    labels = _expect("shaded['labels']", shaded["labels"], torch.int64, (n,))
    hit = _expect("shaded['hit']", shaded["hit"], torch.bool, (n,))
    _expect("axis", axis, torch.float32, (3,))
    plane = _expect("rgb_out", rgb_out, torch.float32, (3, -1)).shape[1]
    _expect("depth_out", depth_out, torch.float32, (plane,))
    _expect("range_out", range_out, torch.float32, (plane,))
    _expect("labels_out", labels_out, torch.int64, (plane,))
    if index is not None:
        _expect("index", index, torch.int64, (n,))
        if n and (int(index.min()) < 0 or int(index.max()) >= plane):
            raise ValueError(f"index: expected texels in [0, {plane}), got some in "
                             f"[{int(index.min())}, {int(index.max())}]")
    elif not 0 <= start <= plane - n:
        raise ValueError(f"start: expected 0 <= start <= {plane - n} ({n} rays into {plane} "
                         f"texels), got {start}")
    outs = (rgb_out, depth_out, range_out, labels_out)
    ops = choose(backend, d, index, rgb, rng, labels, hit, axis, *outs, what="town store")
    if ops is None:
        at = slice(start, start + n) if index is None else index
        depth = torch.where(hit, rng * (d[:, 0] * axis[0] + d[:, 1] * axis[1]
                                        + d[:, 2] * axis[2]), far)
        rgb_out[:, at] = rgb.T
        depth_out[at], range_out[at], labels_out[at] = depth, rng, labels
        return
    for name, x in zip(("rgb_out", "depth_out", "range_out", "labels_out"), outs):
        if not x.is_contiguous():
            raise ValueError(f"{name}: backend='cpp' writes contiguous planes only, got strides "
                             f"{x.stride()}")
    ops.town_store(d.contiguous(), None if index is None else index.contiguous(), start,
                   *(x.contiguous() for x in (rgb, rng, labels, hit, axis)), far, *outs)
