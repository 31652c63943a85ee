"""A small procedural town of triangle meshes, traced by Embree and shaded in C (or torch).

World frame (metres): x east, y down (gravity is +y, like the OpenCV camera's y), z north. The
ground is the plane ``y = 0``; things above the ground have ``y < 0``. Streets share one
cross-section, ``across`` metres from their centre line: two driving lanes (``|across| < 3.5``,
centre line dashed, lane edges solid, zebra crossings every 60 m), a parking strip on each side
(``3.5 < |across| < 5.25``), sidewalks (``5.25 < |across| < 8.5``), and beyond them buildings,
walls, fences and open lots (ground labelled ``Other``). Layouts (:data:`LAYOUTS`, ``layout=``):

1. main street: one street along z, centred on ``x = 0`` (the default);
2. crossroads: the main street and a cross street along x, centred on ``z = 0``;
3. blocks: two streets along z (``x = 0`` and ``x = 70``) and two along x (``z = -40`` and
   ``z = 40``), a block between them.

The town's objects line the streets over ``|z| < length / 2`` (and the cross streets' own
extents); the ground and the roads go on beyond, to ``far + length`` metres. A camera with
identity rotation at ``(0, -1.2, 0)`` stands on the main street's centre line at eye height and
looks north, along the road.

Geometry: the objects are primitives (axis-aligned boxes: buildings, walls, fences, vehicles,
sign plates, bins; vertical cylinders with a top cap: poles, tree trunks, pedestrians' bodies;
spheres: tree crowns, pedestrians' heads; ground rectangles: road, sidewalk, lots), turned into
one triangle mesh (:mod:`.mesh`: 32-sided prisms, icospheres of 1280 triangles) in which every
triangle knows its primitive, so its class and colour. Primitives are seen from outside: a ray
that meets a triangle from behind (it started inside) goes on through it. Moving vehicles and
pedestrians go straight along z at constant speed and wrap around the town's length
(:meth:`Town.moving_objects`); the mesh at time ``t`` is traced by an Embree scene built for
``t`` (the last one is kept).

Outputs (:meth:`Town.render_rays`, :meth:`Town.render_cubemap`): RGB in ``[0, 1]``, the range
(Euclidean distance along the ray; for the sky: ``town.far``, default 1000 m) or the cubemap's
planar depth (along each face's axis; for the sky: ``town.far``, the far plane of a simulator's
depth camera), and CARLA's 13 class ids (sky is ``Unlabeled``; road markings are ``RoadLine``,
painted on the road by world coordinates). Colour is
``albedo(class, world point) * (ambient + sun * lambert * lit) + emission``, then distance fog,
where ``lit`` is 0 when a shadow ray towards the sun (traced by Embree as well) meets anything;
the weather preset (:data:`WEATHERS`) changes light, colour, wetness and fog, never geometry or
labels.

Shading runs in C++ (the ops ``torch.ops.omniscape_torch.town_*``, ``render/csrc/town_shade.cpp``,
built with the fast sampler into one library by :mod:`omniscape_torch.render.kernels.build`) where a
compiler builds it, else in torch (:meth:`Town._shade_reference`, the same operations in the
same order: the same labels and depths, colours within a few float32 roundings, torch's
``sqrt`` not being correctly rounded on every CPU).

Exactness: every ray is traced and shaded on its own (Embree's closest hit, which does not
depend on the batch; then ``+ - * /``, ``sqrt``, comparisons and integer hashing, no
transcendental functions and no reductions), so the result of a ray does not depend on the batch
it is in, the chunking or the threads: ``render_rays`` of the cube's own texel rays
(:meth:`Town.cubemap_rays`) equals ``render_cubemap`` bit for bit, and so do any two runs.
With ``antialias=k`` (:meth:`Town.render_cubemap`) a texel on an edge (:func:`edge_texels`) is
the mean of ``k x k`` sub-texel rays, built and summed the same way whatever the batch; its
labels and depth stay the centre ray's. A ray's last bit can matter: a hit point on a surface
that lies on a texture cell's boundary (the ground, ``y = 0``, for the noise cells) falls on
either side by its rounding.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..cameras._base import broadcast_shapes
from ..cubemap.faces import face_axes, face_pixel_to_ray, face_rays
from ..render.kernels import build as _extension
from . import mesh as _mesh

__all__ = ["CARLA_PRESETS", "CARLA_WEATHERS", "CLASS_IDS", "LAYOUTS", "Street", "Town", "Weather",
           "WEATHERS", "carla_weather", "edge_texels"]

CLASS_IDS = {name: i for i, name in enumerate(
    ("Unlabeled", "Building", "Fence", "Other", "Pedestrian", "Pole", "RoadLine", "Road",
     "Sidewalk", "Vegetation", "Vehicle", "Wall", "TrafficSign"))}
_C = CLASS_IDS

# Street cross-section (|across|, metres).
LANE_EDGE = 3.5
ROAD_HALF = 5.25
SIDEWALK_HALF = 8.5
LINE_HALF = 0.08
#: Half-width of the band around a crossing street kept free of a street's buildings, metres.
CROSSING_BAND = SIDEWALK_HALF + 1.0

#: Tessellation: sides of a cylinder, subdivisions of an icosphere (1280 triangles).
CYLINDER_SEGMENTS = 32
SPHERE_SUBDIVISIONS = 3

#: A shadow ray starts ``SHADOW_BIAS + SHADOW_BIAS_PER_M * range`` metres off the surface,
#: along its normal: far above the rounding of the hit point (about ``1e-7 * range``).
SHADOW_BIAS, SHADOW_BIAS_PER_M = 1e-3, 1e-5
#: A ray that meets a triangle from behind goes on from this far past it (metres), at most
#: ``MAX_PASSES`` times.
PASS_STEP, MAX_PASSES = 1e-4, 4
#: Rays traced and shaded per task (the tasks run on ``threads`` threads).
CHUNK = 65536
#: Anti-aliased cubemaps (``render_cubemap(antialias=k)``, :func:`edge_texels`): two
#: neighbouring texels on a face straddle an edge, and both are supersampled, where their labels
#: differ, their ranges by more than ``AA_RANGE_STEP`` of the nearer, or a colour channel by more
#: than ``AA_RGB_STEP``. Measured (benchmarks/bench_town.py's cameras at 256 x 256, their
#: default faces, frames 0 and 2, k = 2, against 8 x 8 rays a pixel): supersampling every texel
#: gives 40.4 dB (fisheye) and 42.3 dB (catadioptric); a colour step of 8/255 supersamples
#: 44 % / 37 % of the texels for 0.1 dB less, 10/255 35 % / 28 % for 0.25 / 0.15 dB less
#: (k = 3: 41.3 / 43.1 dB against 41.7 / 43.4), 16/255 18 % / 13 % for 0.55 / 0.4 dB less; the
#: range step adds under 1 % of the texels (it finds occlusions of like colours).
AA_RANGE_STEP, AA_RGB_STEP = 0.05, 10.0 / 255


# --------------------------------------------------------------------------------------------
# Weather
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Weather:
    """Light, sky, wetness and fog of a weather / time-of-day preset. Colours are linear RGB in
    [0, 1] (emission and sun may exceed 1; the result is clamped).

    ``sun_elevation`` and ``sun_azimuth`` are in degrees (azimuth from north, z, towards east,
    x). ``fog_density`` is per metre: the fog weight is ``1 - exp(-fog_density * range)``.
    ``lamps``: street-lamp intensity (0: off). ``windows``: emission of lit windows.
    ``wetness`` (0..1): puddles on the ground (the share of the road and sidewalk they cover,
    mirroring the sky) and darker, wet surfaces; ``rain`` (0..1): falling rain, which darkens
    and greys the scene (its haze is in ``fog_density``)."""

    sun_elevation: float
    sun_azimuth: float
    sun_colour: tuple[float, float, float]
    ambient: tuple[float, float, float]
    sky_zenith: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]
    fog_colour: tuple[float, float, float]
    fog_density: float
    lamps: float = 0.0
    windows: float = 0.0
    wetness: float = 0.0
    rain: float = 0.0

    def sun_direction(self) -> tuple[float, float, float]:
        """Unit vector towards the sun in the world frame (y down, so up is -y)."""
        e, a = math.radians(self.sun_elevation), math.radians(self.sun_azimuth)
        return (math.sin(a) * math.cos(e), -math.sin(e), math.cos(a) * math.cos(e))

    def surface_factor(self) -> float:
        """Albedo factor of wet surfaces: ``1 - 0.35 rain - 0.3 wetness``."""
        return 1.0 - 0.35 * self.rain - 0.3 * self.wetness

    def sky_factor(self) -> float:
        """Brightness of the sky under rain: ``1 - 0.45 rain``."""
        return 1.0 - 0.45 * self.rain


#: CARLA's 14 weather presets (``carla.WeatherParameters.ClearNoon`` etc., CARLA 0.9.x), with
#: the parameters this town uses: cloudiness, precipitation, precipitation_deposits and
#: fog_density in percent, sun_altitude_angle in degrees (sun_azimuth_angle is -1 in all of
#: them: the map's default, here 150 deg).
CARLA_WEATHERS: dict[str, dict[str, float]] = {
    name: dict(zip(("cloudiness", "precipitation", "precipitation_deposits",
                    "sun_altitude_angle", "fog_density"), values))
    for name, values in {
        "ClearNoon": (5, 0, 0, 45, 2), "CloudyNoon": (60, 0, 0, 45, 3),
        "WetNoon": (5, 0, 50, 45, 3), "WetCloudyNoon": (60, 0, 50, 45, 3),
        "MidRainyNoon": (60, 60, 60, 45, 3), "HardRainNoon": (100, 100, 90, 45, 7),
        "SoftRainNoon": (20, 30, 50, 45, 3),
        "ClearSunset": (5, 0, 0, 15, 2), "CloudySunset": (60, 0, 0, 15, 3),
        "WetSunset": (5, 0, 50, 15, 2), "WetCloudySunset": (60, 0, 50, 15, 2),
        "MidRainSunset": (60, 60, 60, 15, 3), "HardRainSunset": (100, 100, 90, 15, 7),
        "SoftRainSunset": (20, 30, 50, 15, 2),
    }.items()}


def _mix(a, b, w: float) -> tuple[float, float, float]:
    return tuple(float(x + (y - x) * w) for x, y in zip(a, b))


def _scale(a, s: float) -> tuple[float, float, float]:
    return tuple(float(x * s) for x in a)


def carla_weather(cloudiness: float, precipitation: float, precipitation_deposits: float,
                  sun_altitude_angle: float, fog_density: float, *,
                  sun_azimuth_angle: float = 150.0) -> Weather:
    """The town's :class:`Weather` for CARLA's weather parameters (percent and degrees, as
    ``carla.WeatherParameters``): the sun's colour reddens towards the horizon (noon white at
    45 deg and above, orange at 15 deg) and dims under clouds (by up to 85 %) and rain; the
    ambient light and the sky grey with clouds; fog is ``0.00075 * fog_density`` per metre plus
    ``0.012`` at full rain (the rain's haze); ``wetness`` is the deposits' share, ``rain`` the
    precipitation's (:meth:`Weather.surface_factor`, :meth:`Weather.sky_factor`)."""
    c, p, q = cloudiness / 100.0, precipitation / 100.0, precipitation_deposits / 100.0
    low = min(1.0, max(0.0, (45.0 - sun_altitude_angle) / 30.0))  # 0 at noon, 1 at 15 deg
    sun = _mix((1.0, 0.96, 0.88), (1.0, 0.55, 0.25), low)
    sun = _scale(sun, (1.0 - 0.85 * c) * (1.0 - 0.5 * p))
    ambient = _mix((0.30, 0.34, 0.42), (0.26, 0.22, 0.26), low)
    ambient = _scale(_mix(ambient, (0.42, 0.43, 0.46), 0.8 * c), 1.0 + 0.5 * c - 0.35 * p)
    zenith = _mix((0.22, 0.42, 0.85), (0.18, 0.24, 0.52), low)
    horizon = _mix((0.68, 0.80, 0.95), (1.0, 0.58, 0.32), low)
    grey = _scale((0.62, 0.63, 0.66), 1.0 - 0.35 * p - 0.2 * low)
    zenith, horizon = _mix(zenith, grey, 0.9 * c), _mix(horizon, grey, 0.85 * c)
    fog = _mix(_mix((0.72, 0.80, 0.92), (0.88, 0.62, 0.46), low), grey, max(c, p))
    return Weather(float(max(sun_altitude_angle, 1.0)), float(sun_azimuth_angle), sun, ambient,
                   zenith, horizon, fog, 0.00075 * fog_density + 0.012 * p,
                   wetness=float(q), rain=float(p))


def _snake(name: str) -> str:
    return "".join("_" + ch.lower() if ch.isupper() and i else ch.lower()
                   for i, ch in enumerate(name))


#: CARLA's 14 presets by their names here, in CARLA's order (``generate``'s default weathers).
CARLA_PRESETS: tuple[str, ...] = tuple(_snake(name) for name in CARLA_WEATHERS)

#: The weather presets: CARLA's 14 (:data:`CARLA_WEATHERS`, in snake case: ``clear_noon``,
#: ``cloudy_noon``, ..., ``soft_rain_sunset``) and four of this town's own: ``overcast``,
#: ``sunset`` (a low, red sun, 6 deg), ``night`` (street lamps and lit windows) and ``fog``.
WEATHERS: dict[str, Weather] = {
    **{_snake(name): carla_weather(**p) for name, p in CARLA_WEATHERS.items()},
    "overcast": Weather(50.0, 150.0, (0.18, 0.18, 0.19), (0.62, 0.63, 0.66),
                        (0.52, 0.54, 0.58), (0.74, 0.75, 0.77), (0.70, 0.71, 0.73), 0.010),
    "sunset": Weather(6.0, 260.0, (1.0, 0.52, 0.22), (0.28, 0.22, 0.26),
                      (0.18, 0.24, 0.52), (1.0, 0.56, 0.30), (0.88, 0.60, 0.45), 0.004),
    "night": Weather(40.0, 120.0, (0.07, 0.08, 0.12), (0.03, 0.035, 0.06),
                     (0.005, 0.008, 0.025), (0.03, 0.04, 0.08), (0.04, 0.05, 0.08), 0.008,
                     lamps=1.0, windows=0.9),
    "fog": Weather(40.0, 150.0, (0.12, 0.12, 0.12), (0.66, 0.67, 0.69),
                   (0.72, 0.73, 0.75), (0.78, 0.79, 0.80), (0.76, 0.77, 0.78), 0.05),
}


def _get_weather(weather: str | Weather) -> Weather:
    if isinstance(weather, Weather):
        return weather
    try:
        return WEATHERS[weather]
    except (KeyError, TypeError):
        raise ValueError(f"weather: unknown preset {weather!r}; presets: "
                         f"{', '.join(WEATHERS)}") from None


# --------------------------------------------------------------------------------------------
# Layouts
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Street:
    """A straight street of the town's cross-section, endless on the ground.

    ``axis``: ``"z"`` (it runs north-south, its centre line at ``x = offset``) or ``"x"``
    (east-west, at ``z = offset``). ``frontage``: the interval along the street (metres) lined
    with buildings, lamps, trees and parked vehicles (less the crossing streets' bands)."""

    axis: str
    offset: float
    frontage: tuple[float, float]

    def world(self, across, along) -> tuple:
        """World ``(x, z)`` of a point ``across`` metres from the centre line (towards +x for
        a z street, +z for an x street) and ``along`` metres along it."""
        if self.axis == "z":
            return self.offset + across, along
        return along, self.offset + across


#: The town layouts, by number: a name and a description.
LAYOUTS = {1: "main street", 2: "crossroads", 3: "blocks"}


def layout_streets(layout: int, length: float) -> tuple[Street, ...]:
    """The streets of ``layout`` (:data:`LAYOUTS`) for a town of ``length`` metres."""
    h = length / 2
    if layout == 1:
        return (Street("z", 0.0, (-h, h)),)
    if layout == 2:
        return (Street("z", 0.0, (-h, h)), Street("x", 0.0, (-h, h)))
    if layout == 3:
        return (Street("z", 0.0, (-h, h)), Street("z", 70.0, (-h, h)),
                Street("x", -40.0, (-h / 2, 70.0 + h / 2)),
                Street("x", 40.0, (-h / 2, 70.0 + h / 2)))
    raise ValueError(f"layout: expected one of {sorted(LAYOUTS)}, got {layout!r}")


def _bands(street: Street, streets) -> list[tuple[float, float]]:
    """Intervals along ``street`` crossed by the other streets (with their sidewalks)."""
    return [(s.offset - CROSSING_BAND, s.offset + CROSSING_BAND) for s in streets
            if s.axis != street.axis]


def _free(a: float, b: float, bands) -> list[tuple[float, float]]:
    """``[a, b]`` less the bands, as a list of intervals (in order)."""
    out = [(a, b)]
    for lo, hi in sorted(bands):
        nxt = []
        for x, y in out:
            if hi <= x or lo >= y:
                nxt.append((x, y))
                continue
            if lo > x:
                nxt.append((x, lo))
            if hi < y:
                nxt.append((hi, y))
        out = nxt
    return out


def _in_bands(x: float, bands, margin: float = 0.0) -> bool:
    return any(lo - margin < x < hi + margin for lo, hi in bands)


def _ground_cells(streets, extent: float):
    """The ground as axis-aligned rectangles of one class each: ``(x0, x1, z0, z1, label,
    paint axis, paint offset)``, the paint axis ``"z"`` or ``"x"`` on a single street's road
    (where its markings are painted), ``""`` elsewhere (sidewalks, lots, crossings)."""
    xs, zs = {-extent, extent}, {-extent, extent}
    for s in streets:
        cuts = {s.offset + k * w for k in (-1, 1) for w in (ROAD_HALF, SIDEWALK_HALF)}
        (xs if s.axis == "z" else zs).update(cuts)
    xs, zs = sorted(xs), sorted(zs)
    cells = []
    for x0, x1 in zip(xs[:-1], xs[1:]):
        # merge the runs of equal cells along z
        run = None
        for z0, z1 in zip(zs[:-1], zs[1:]):
            cx, cz = (x0 + x1) / 2, (z0 + z1) / 2
            roads = [s for s in streets
                     if abs((cx if s.axis == "z" else cz) - s.offset) < ROAD_HALF]
            walks = [s for s in streets
                     if abs((cx if s.axis == "z" else cz) - s.offset) < SIDEWALK_HALF]
            if roads:
                label = _C["Road"]
                axis, off = (roads[0].axis, roads[0].offset) if len(roads) == 1 else ("", 0.0)
            else:
                label, axis, off = (_C["Sidewalk"] if walks else _C["Other"]), "", 0.0
            key = (label, axis, off)
            if run is not None and run[1] == key:
                run = (run[0], key, z1)
            else:
                if run is not None:
                    cells.append((x0, x1, run[0], run[2]) + run[1])
                run = (z0, key, z1)
        cells.append((x0, x1, run[0], run[2]) + run[1])
    return cells


# --------------------------------------------------------------------------------------------
# Procedural texture helpers (integer hashing and floor only: exact on every code path)
# --------------------------------------------------------------------------------------------

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
    h = (_cell(x, scale) * 73856093) ^ (_cell(y, scale) * 19349663) ^ \
        (_cell(z, scale) * 83492791) ^ (0x9E3779B9 + salt * 0x632BE5AB)
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


def _ops():
    """The C++ shading ops (``torch.ops.omniscape_torch``), built on the first call; None where
    they cannot be built (after the extension's one warning): the town shades with torch."""
    return _extension.ops()


def _t(a: np.ndarray) -> Tensor:
    """A numpy array as a tensor on its memory (no copy), for the ops."""
    return torch.from_numpy(a)


def _native_weather(w: Weather, far: float) -> np.ndarray:
    """The weather's numbers as the C++ loops read them (``W_*`` in
    ``render/csrc/town_shade.cpp``), float32 as torch rounds Python numbers in
    :meth:`Town._shade_reference`."""
    values = [*w.sun_direction(), *w.sun_colour, *w.ambient, *w.sky_zenith, *w.sky_horizon,
              *w.fog_colour, w.fog_density / 256.0, w.lamps * 30.0, w.windows,
              0.75 * w.wetness,
              w.surface_factor() if (w.rain > 0 or w.wetness > 0) else 1.0,
              w.sky_factor() if w.rain > 0 else 1.0, min(1.0, w.fog_density * 40.0), far]
    return np.array(values, dtype=np.float32)


def edge_texels(labels: Tensor, rng: Tensor, rgb: Tensor, rendered: Tensor | None = None
                ) -> Tensor:
    """``(F, F)`` bool: the texels of one cube face that :meth:`Town.render_cubemap`'s
    ``antialias`` supersamples. Two neighbouring texels (each of the 8 neighbours), both
    ``rendered`` (default: all), straddle an edge where their ``labels (F, F)`` differ, their
    ``rng (F, F)`` differ by more than ``AA_RANGE_STEP`` of the nearer, or a channel of their
    ``rgb (3, F, F)`` by more than ``AA_RGB_STEP``; both are on the edge (it lies in one
    footprint or the other). Across a face's seam nothing is compared."""
    F = labels.shape[-1]
    edge = torch.zeros(F, F, dtype=torch.bool)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):   # each pair of neighbours once
        a = (slice(0, F - dy), slice(max(0, -dx), F - max(0, dx)))
        b = (slice(dy, F), slice(max(0, dx), F + min(0, dx)))
        step = (labels[a] != labels[b]) | \
            ((rng[a] - rng[b]).abs() > AA_RANGE_STEP * torch.minimum(rng[a], rng[b])) | \
            ((rgb[(slice(None),) + a] - rgb[(slice(None),) + b]).abs().amax(0) > AA_RGB_STEP)
        if rendered is not None:
            step &= rendered[a] & rendered[b]
        edge[a] |= step
        edge[b] |= step
    return edge


# Ground colours by class (the road markings' RoadLine, the lots' Other).
_GROUND_COLOUR = torch.zeros(13, 3)
_GROUND_COLOUR[_C["Road"]] = torch.tensor([0.26, 0.26, 0.27])
_GROUND_COLOUR[_C["RoadLine"]] = torch.tensor([0.85, 0.85, 0.8])
_GROUND_COLOUR[_C["Sidewalk"]] = torch.tensor([0.62, 0.60, 0.56])
_GROUND_COLOUR[_C["Other"]] = torch.tensor([0.42, 0.38, 0.28])

# Part kinds.
_GROUND, _BOX, _CYLINDER, _SPHERE = 0, 1, 2, 3


class Town:
    """A procedural town, deterministic by ``seed`` (a ``torch.Generator``; no global RNG).

    Args:
        seed: the random layout (buildings, gaps, parked cars, trees, colours, movers).
        layout: the street plan, a key of :data:`LAYOUTS` (1: main street, 2: crossroads,
            3: blocks).
        length: extent of the town along z (metres), centred on ``z = 0``.
        far: range (and planar depth) reported for the sky, metres; nothing farther is seen.
        threads: threads that trace and shade (default: ``torch.get_num_threads()``); the
            result does not depend on it.

    Attributes hold the primitives as float32 tensors: ``boxes_lo/boxes_hi (Nb, 3)``,
    ``cyl (Nc, 5)`` = (cx, cz, r, ytop, ybot), ``sph (Ns, 4)`` = (cx, cy, cz, r), each with
    ``*_label`` (int64 class ids), ``*_colour (N, 3)`` albedo and ``*_mover`` (index into the
    movers, -1 for static) and ``*_instance`` (int64 instance id, 0 for none).
    ``movers`` is ``(M, 3)`` = (z0, speed m/s, kind 0 vehicle / 1 pedestrian). ``streets``
    the layout's :class:`Street` list; ``mesh`` the triangles at ``t = 0``
    (:class:`.mesh.Mesh`).

    Instances: every vehicle (body and cabin), pedestrian (body and head), pole (a street
    lamp's, a traffic sign's) and traffic sign plate is an object with its own instance id,
    ``1..I`` in the order the town places them (the same ids at every time and from every
    viewpoint, so stable across a ride's frames); the ground, buildings, walls, fences, trees
    and bins have none (0). ``instance_label (I + 1,)`` int64 is the class of each id (0 for
    id 0).
    """

    def __init__(self, seed: int = 0, *, layout: int = 1, length: float = 160.0,
                 far: float = 1000.0, threads: int | None = None):
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
        if isinstance(layout, bool) or layout not in LAYOUTS:
            raise ValueError(f"layout: expected one of {sorted(LAYOUTS)}, got {layout!r}")
        if not (isinstance(length, (int, float)) and 20 <= length <= 2000):
            raise ValueError(f"length: expected 20 to 2000 metres, got {length!r}")
        if not (isinstance(far, (int, float)) and far > 0 and math.isfinite(far)):
            raise ValueError(f"far: expected a positive number of metres, got {far!r}")
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int)
                                    or threads < 1):
            raise ValueError(f"threads: expected a positive integer or None, got {threads!r}")
        self.seed = int(seed)
        self.layout = int(layout)
        self.length = float(length)
        self.far = float(far)
        self.threads = threads
        self.streets = layout_streets(self.layout, self.length)
        g = torch.Generator().manual_seed(self.seed)
        self._build(g)
        self._build_mesh()
        self._lock = threading.Lock()
        self._scene_cache: tuple[float, _mesh.MeshScene] | None = None
        self._rays_cache: dict[int, Tensor] = {}

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_lock"], state["_scene_cache"], state["_rays_cache"] = None, None, {}
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    # ---------------------------------------------------------------- layout
    def _build(self, g: torch.Generator) -> None:
        def U(a: float, b: float) -> float:
            return a + (b - a) * float(torch.rand((), generator=g, dtype=torch.float64))

        boxes, cyls, sphs, movers, lamps = [], [], [], [], []
        instances = [0]   # the objects so far: the last instance id given (0: none)

        def new_instance() -> int:
            instances[0] += 1
            return instances[0]

        def place_box(st, a0, a1, y0, y1, l0, l1, label, colour, mover=-1, instance=0):
            (x0, z0), (x1, z1) = st.world(a0, l0), st.world(a1, l1)
            xa, xb = sorted((x0, x1))
            za, zb = sorted((z0, z1))
            boxes.append(((xa, y0, za), (xb, y1, zb), label, colour, mover, instance))

        def place_cyl(st, a, l, r, ytop, label, colour, mover=-1, instance=0):
            x, z = st.world(a, l)
            cyls.append((x, z, r, ytop, 0.0, label, colour, mover, instance))

        def place_sph(st, a, y, l, r, label, colour, mover=-1, instance=0):
            x, z = st.world(a, l)
            sphs.append((x, y, z, r, label, colour, mover, instance))

        def vehicle(st, ac, lc, colour, mover=-1, flip=1.0):
            instance = new_instance()   # body and cabin: one object
            place_box(st, ac - 0.85, ac + 0.85, -1.05, -0.32, lc - 2.15, lc + 2.15,
                      _C["Vehicle"], colour, mover, instance)
            l0, l1 = sorted((lc - 1.2 * flip, lc + 0.9 * flip))
            place_box(st, ac - 0.75, ac + 0.75, -1.5, -1.05, l0, l1, _C["Vehicle"],
                      (0.10, 0.12, 0.15), mover, instance)

        for si, st in enumerate(self.streets):
            bands = _bands(st, self.streets)
            lo_f, hi_f = st.frontage
            for s in (-1.0, 1.0):
                # buildings along the block, gaps filled with walls, fences or left open;
                # the first gap ahead of the origin on the main street is a wall (east) or a
                # fence (west), so that every class shows from the default pose
                near_done = si > 0
                for a, b in _free(lo_f, hi_f, bands):
                    z = a
                    while z < b - 6:
                        ln = min(U(8, 20), b - z)
                        x0, depth, h = 9.0 + U(0, 1.5), U(8, 16), U(6, 28)
                        grey = U(0.35, 0.75)
                        col = (grey * U(0.9, 1.1), grey * U(0.85, 1.0), grey * U(0.75, 0.95))
                        place_box(st, s * x0, s * (x0 + depth), -h, 0.0, z, z + ln,
                                  _C["Building"], col)
                        z += ln
                        gap = U(2, 7)
                        kind = U(0, 1)
                        if not near_done and z > -4.0:
                            near_done, gap, kind = True, max(gap, 4.0), (0.0 if s > 0 else 0.5)
                        if z + gap < b:
                            if kind < 0.4:
                                place_box(st, s * 9.0, s * 9.35, -U(1.8, 3.0), 0.0, z, z + gap,
                                          _C["Wall"], (U(0.45, 0.6), U(0.25, 0.35),
                                                       U(0.2, 0.28)))
                            elif kind < 0.8:
                                place_box(st, s * 8.9, s * 8.96, -1.5, 0.0, z, z + gap,
                                          _C["Fence"], (U(0.5, 0.7), U(0.45, 0.6),
                                                        U(0.35, 0.45)))
                        z += gap
                # street lamps (poles), staggered
                zl = lo_f + 5 + (5 if s > 0 else 0)
                while zl < hi_f:
                    if not _in_bands(zl, bands):
                        place_cyl(st, s * 7.9, zl, 0.11, -6.5, _C["Pole"], (0.45, 0.46, 0.48),
                                  instance=new_instance())
                        x, z = st.world(s * 7.9, zl)
                        lamps.append((x, -6.6, z))
                    zl += 20
                # trees on the sidewalk
                zt = lo_f + 3
                while zt < hi_f - 2:
                    if U(0, 1) < 0.7:
                        r = U(1.1, 1.9)
                        crown = (0.16 * U(0.8, 1.2), 0.36 * U(0.8, 1.2), 0.10)
                        if not _in_bands(zt, bands, r):
                            place_cyl(st, s * 6.4, zt, 0.18, -2.8, _C["Vegetation"],
                                      (0.30, 0.20, 0.12))
                            place_sph(st, s * 6.4, -(2.8 + 0.7 * r), zt, r, _C["Vegetation"],
                                      crown)
                    zt += 12
                # bins (Other) on the sidewalk
                for _ in range(4):
                    zb = U(lo_f + 4, hi_f - 4)
                    colour = (0.15, U(0.25, 0.4), 0.18)
                    if not _in_bands(zb, bands, 0.6):
                        place_box(st, s * 7.3, s * 7.9, -1.0, 0.0, zb, zb + 0.6, _C["Other"],
                                  colour)
                # parked vehicles on the parking strip
                zp = lo_f + 3
                while zp < hi_f - 3:
                    if U(0, 1) < 0.45:
                        colour = (U(0.1, 0.9), U(0.1, 0.9), U(0.1, 0.9))
                        if not _in_bands(zp, bands, 2.5):
                            vehicle(st, s * 4.4, zp, colour)
                    zp += 6.0
        # traffic signs on the main street: pole + plate facing the traffic; the first is near
        # the origin (moved out of a crossing street's band)
        main = self.streets[0]
        bands = _bands(main, self.streets)
        for i, (s, zs) in enumerate([(1.0, 14.0), (-1.0, -22.0), (1.0, U(30, 70)),
                                     (-1.0, U(-70, -30))]):
            for lo, hi in bands:
                if lo - 1 < zs < hi + 1:
                    zs = hi + 2 if zs > (lo + hi) / 2 else lo - 2
            x = s * 5.6
            # the pole is a Pole instance and the plate a TrafficSign one (an instance has
            # one class)
            place_cyl(main, x, zs, 0.05, -2.9, _C["Pole"], (0.55, 0.55, 0.57),
                      instance=new_instance())
            col = [(0.1, 0.25, 0.7), (0.75, 0.1, 0.1), (0.9, 0.75, 0.1)][i % 3]
            zf = zs - 0.06 if s > 0 else zs + 0.02
            place_box(main, x - 0.35, x + 0.35, -2.95, -2.25, zf, zf + 0.04,
                      _C["TrafficSign"], col, instance=new_instance())
        # movers on every north-south street: vehicles northbound in the east lane,
        # southbound in the west lane; pedestrians on the sidewalks (the first near the origin)
        L2 = self.length / 2
        for st in self.streets:
            if st.axis != "z":
                continue
            for i in range(6):
                s = 1.0 if i % 2 == 0 else -1.0
                z0 = (-30.0 if i == 0 else U(-L2, L2))
                speed = s * U(6, 12)
                movers.append((z0, speed, 0.0))
                vehicle(st, s * 1.75, z0, (U(0.1, 0.9), U(0.1, 0.9), U(0.1, 0.9)),
                        len(movers) - 1, s)
            for i in range(8):
                s = 1.0 if i % 2 == 0 else -1.0
                z0 = 7.0 if i == 0 else U(-L2, L2)
                speed = U(-1.6, 1.6)
                movers.append((z0, speed, 1.0))
                a = s * U(6.9, 7.5)
                instance = new_instance()   # body and head: one object
                place_cyl(st, a, z0, 0.22, -1.45, _C["Pedestrian"],
                          (U(0.1, 0.8), U(0.1, 0.8), U(0.1, 0.8)), len(movers) - 1, instance)
                place_sph(st, a, -1.6, z0, 0.14, _C["Pedestrian"], (0.8, 0.6, 0.48),
                          len(movers) - 1, instance)

        f32 = torch.float32
        self.boxes_lo = torch.tensor([b[0] for b in boxes], dtype=f32)
        self.boxes_hi = torch.tensor([b[1] for b in boxes], dtype=f32)
        self.boxes_label = torch.tensor([b[2] for b in boxes], dtype=torch.int64)
        self.boxes_colour = torch.tensor([b[3] for b in boxes], dtype=f32)
        self.boxes_mover = torch.tensor([b[4] for b in boxes], dtype=torch.int64)
        self.boxes_instance = torch.tensor([b[5] for b in boxes], dtype=torch.int64)
        self.cyl = torch.tensor([c[:5] for c in cyls], dtype=f32)
        self.cyl_label = torch.tensor([c[5] for c in cyls], dtype=torch.int64)
        self.cyl_colour = torch.tensor([c[6] for c in cyls], dtype=f32)
        self.cyl_mover = torch.tensor([c[7] for c in cyls], dtype=torch.int64)
        self.cyl_instance = torch.tensor([c[8] for c in cyls], dtype=torch.int64)
        self.sph = torch.tensor([c[:4] for c in sphs], dtype=f32)
        self.sph_label = torch.tensor([c[4] for c in sphs], dtype=torch.int64)
        self.sph_colour = torch.tensor([c[5] for c in sphs], dtype=f32)
        self.sph_mover = torch.tensor([c[6] for c in sphs], dtype=torch.int64)
        self.sph_instance = torch.tensor([c[7] for c in sphs], dtype=torch.int64)
        self.movers = torch.tensor(movers, dtype=torch.float64).reshape(-1, 3)
        # the class of each instance id (0: none, Unlabeled)
        self.instance_label = torch.zeros(instances[0] + 1, dtype=torch.int64)
        for table, label in ((self.boxes_instance, self.boxes_label),
                             (self.cyl_instance, self.cyl_label),
                             (self.sph_instance, self.sph_label)):
            self.instance_label[table[table > 0]] = label[table > 0]
        self.lamps = torch.tensor(lamps, dtype=f32)
        self.ground = _ground_cells(self.streets, self.far + self.length)

    def _build_mesh(self) -> None:
        """The triangle mesh at ``t = 0`` and the parts' tables: parts are the ground cells,
        then the boxes, the cylinders and the spheres, in their tables' order."""
        cells = self.ground
        ng, nb, nc, ns = len(cells), len(self.boxes_lo), len(self.cyl), len(self.sph)
        first = np.cumsum([0, ng, nb, nc])
        gx0, gx1, gz0, gz1 = (np.array([c[k] for c in cells]) for k in range(4))
        self.mesh = _mesh.concat([
            _mesh.rectangle_mesh(gx0, gx1, gz0, gz1, np.arange(ng)),
            _mesh.box_mesh(self.boxes_lo.numpy(), self.boxes_hi.numpy(),
                           first[1] + np.arange(nb)),
            _mesh.cylinder_mesh(self.cyl.numpy(), first[2] + np.arange(nc), CYLINDER_SEGMENTS),
            _mesh.sphere_mesh(self.sph.numpy(), first[3] + np.arange(ns), SPHERE_SUBDIVISIONS),
        ])
        i64 = torch.int64
        kind = torch.tensor([_GROUND] * ng + [_BOX] * nb + [_CYLINDER] * nc + [_SPHERE] * ns,
                            dtype=i64)
        label = torch.cat([torch.tensor([c[4] for c in cells], dtype=i64), self.boxes_label,
                           self.cyl_label, self.sph_label])
        colour = torch.cat([torch.zeros(ng, 3), self.boxes_colour, self.cyl_colour,
                            self.sph_colour])
        mover = torch.cat([torch.full((ng,), -1, dtype=i64), self.boxes_mover, self.cyl_mover,
                           self.sph_mover])
        paint = torch.tensor([{"": 0, "z": 1, "x": 2}[c[5]] for c in cells]
                             + [0] * (nb + nc + ns), dtype=torch.float32)
        paint_offset = torch.tensor([c[6] for c in cells] + [0.0] * (nb + nc + ns),
                                    dtype=torch.float32)
        centre = torch.zeros(ng + nb + nc + ns, 3)
        centre[first[1]:first[2]] = (self.boxes_lo + self.boxes_hi) / 2
        index = torch.cat([torch.arange(n, dtype=i64) for n in (ng, nb, nc, ns)])
        smooth = (kind == _CYLINDER) | (kind == _SPHERE)
        m = self.mesh
        part = torch.from_numpy(m.part)
        # one row per attribute, one column per triangle: a hit's attributes are one gather
        self._tri_attr = torch.cat([
            torch.from_numpy(m.face_normals).T,                    # 0-2 outward face normal
            label[part].to(torch.float32)[None],                   # 3 class id
            kind[part].to(torch.float32)[None],                    # 4 part kind
            colour[part].T,                                        # 5-7 albedo
            paint[part][None], paint_offset[part][None],           # 8-9 road paint
            centre[part, :2].T,                                    # 10-11 box centre x, y
            index[part].to(torch.float32)[None],                   # 12 index in its kind
            smooth[part].to(torch.float32)[None],                  # 13 smooth normals
        ]).contiguous()
        self._triangles = torch.from_numpy(m.triangles.astype(np.int64))
        self._vertex_normal = torch.from_numpy(m.normals)
        self._vertex_mover = mover[torch.from_numpy(m.vertex_part)]
        # a hit's instance id, one gather by triangle; a miss (triangle -1) reads the last, 0
        instance = torch.cat([torch.zeros(ng, dtype=i64), self.boxes_instance, self.cyl_instance,
                              self.sph_instance])
        self._tri_instance = np.append(instance[part].numpy(), 0).astype(np.int32)
        # what the C++ loops read: attributes (K, T), corners (T, 3) int32, vertex normals, lamps
        self._tables = (self._tri_attr, torch.from_numpy(m.triangles),
                        torch.from_numpy(m.normals), self.lamps.reshape(-1, 3).contiguous())

    @property
    def classes_present(self) -> set[int]:
        """Class ids that the town contains (the ground gives Road, RoadLine, Sidewalk and
        Other; the sky Unlabeled)."""
        ids = {_C["Unlabeled"], _C["Road"], _C["RoadLine"], _C["Sidewalk"], _C["Other"]}
        for t in (self.boxes_label, self.cyl_label, self.sph_label):
            ids |= set(t.tolist())
        return ids

    # ---------------------------------------------------------------- motion
    def moving_objects(self, t: float = 0.0) -> dict[str, Tensor]:
        """Positions at time ``t`` (seconds) of the movers: ``z (M,)`` float64 (straight-line
        motion along z, wrapped into ``[-length/2, length/2)``), ``speed (M,)`` m/s along z and
        ``kind (M,)`` (0 vehicle, 1 pedestrian)."""
        z0, v, kind = self.movers.unbind(-1)
        L = self.length
        z = torch.remainder(z0 + v * float(t) + L / 2, L) - L / 2
        return {"z": z, "speed": v, "kind": kind.to(torch.int64)}

    def _shifts(self, t: float) -> Tensor:
        """``(M + 1,)`` float32 shift along z of each mover at ``t`` (the last: 0, static)."""
        dz = (self.moving_objects(t)["z"] - self.movers[:, 0]).to(torch.float32)
        return torch.cat([dz, torch.zeros(1)])

    def geometry(self, t: float = 0.0) -> dict[str, Tensor]:
        """Primitive parameters at time ``t``: the movers shifted along z."""
        dz = self._shifts(t)
        lo, hi = self.boxes_lo.clone(), self.boxes_hi.clone()
        lo[:, 2] += dz[self.boxes_mover]
        hi[:, 2] += dz[self.boxes_mover]
        cyl = self.cyl.clone()
        cyl[:, 1] += dz[self.cyl_mover]
        sph = self.sph.clone()
        sph[:, 2] += dz[self.sph_mover]
        return {"lo": lo, "hi": hi, "cyl": cyl, "sph": sph}

    def vertices(self, t: float = 0.0) -> Tensor:
        """``(V, 3)`` float32 mesh vertices at time ``t`` (the movers' shifted along z)."""
        v = torch.from_numpy(self.mesh.vertices).clone()
        v[:, 2] += self._shifts(t)[self._vertex_mover]
        return v

    def scene(self, t: float = 0.0) -> _mesh.MeshScene:
        """The Embree scene of the mesh at time ``t`` (built once per ``t``; the last kept)."""
        t = float(t)
        with self._lock:
            if self._scene_cache is None or self._scene_cache[0] != t:
                self._scene_cache = (t, _mesh.MeshScene(self.vertices(t).numpy(),
                                                        self.mesh.triangles))
            return self._scene_cache[1]

    # ---------------------------------------------------------------- tracing
    def _trace(self, scene: _mesh.MeshScene, o: np.ndarray, d: np.ndarray):
        """Closest front-facing hits of rays ``o (N, 3) or (1, 3)``, ``d (N, 3)`` (numpy
        float32) within ``far``: ``t (N,)`` (inf: none), triangle ``(N,)`` (-1: none),
        barycentric ``u, v (N,)``. A ray that meets a triangle from behind (it started inside a
        primitive) goes on from ``PASS_STEP`` past it, up to ``MAX_PASSES`` times (then it sees
        nothing)."""
        n = d.shape[0]
        o = np.broadcast_to(o, (n, 3))
        t, tri, u, v = scene.intersect(o, d, self.far)
        todo = None   # every ray (not gathered)
        for rest in range(MAX_PASSES, -1, -1):
            todo = np.flatnonzero(self._backfaces(d, tri)) if todo is None else \
                todo[self._backfaces(d[todo], tri[todo])]
            if todo.size == 0:
                break
            if rest == 0:
                t[todo], tri[todo] = np.inf, -1
                break
            skip = t[todo] + np.float32(PASS_STEP)
            t2, tri2, u2, v2 = scene.intersect(o[todo] + skip[:, None] * d[todo], d[todo],
                                               np.float32(self.far) - skip)
            t[todo] = np.where(tri2 >= 0, skip + t2, np.float32(np.inf))
            tri[todo], u[todo], v[todo] = tri2, u2, v2
        return t, tri, u, v

    def _backfaces(self, d: np.ndarray, tri: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: the hits ``tri`` that rays ``d`` meet from behind their face."""
        ops = _ops()
        if ops is None:
            fn = self.mesh.face_normals[np.maximum(tri, 0)]
            return (tri >= 0) & (fn[:, 0] * d[:, 0] + fn[:, 1] * d[:, 1] + fn[:, 2] * d[:, 2]
                                 > 0)
        d = np.ascontiguousarray(d, np.float32)
        tri = np.ascontiguousarray(tri, np.int64)
        out = np.empty(d.shape[0], bool)
        ops.town_backfaces(_t(d), _t(tri), self._tables[0], _t(out))
        return out

    # ---------------------------------------------------------------- shading
    def _shade(self, o: np.ndarray, d: np.ndarray, t: np.ndarray, tri: np.ndarray,
               u: np.ndarray, v: np.ndarray, w: Weather, scene: _mesh.MeshScene
               ) -> dict[str, Tensor]:
        """Labels, range, normal and colour of rays ``o (N, 3) or (1, 3)``, ``d (N, 3)`` (numpy
        float32) from their closest hits (:meth:`_trace`), with shadow rays towards the sun
        through ``scene``: the C++ ops (``town_prepare``, ``town_shade``) where they are built,
        else :meth:`_shade_reference` (the same result)."""
        ops = _ops()
        if ops is None:
            return self._shade_reference(*(torch.from_numpy(np.ascontiguousarray(x))
                                           for x in (o, d, t, tri, u, v)), w, scene)
        n = d.shape[0]
        o = np.ascontiguousarray(o, np.float32)
        d = np.ascontiguousarray(d, np.float32)
        tri = np.ascontiguousarray(tri, np.int64)
        tables = self._tables
        common = [_t(o), _t(d), _t(t), _t(tri), _t(u), _t(v), *tables[:3],
                  _t(_native_weather(w, self.far))]
        need = np.empty(n, bool)
        origin = np.empty((n, 3), np.float32)
        shadow = np.empty(n, bool)
        ops.town_prepare(*common, SHADOW_BIAS, SHADOW_BIAS_PER_M, _t(need), _t(origin),
                         _t(shadow))
        lit = np.flatnonzero(need)
        if lit.size:
            towards = np.broadcast_to(np.array(w.sun_direction(), np.float32), (lit.size, 3))
            shadow[lit] = scene.occluded(origin[lit], towards)
        rgb = np.empty((n, 3), np.float32)
        rng = np.empty(n, np.float32)
        labels = np.empty(n, np.int64)
        normal = np.empty((n, 3), np.float32)
        lamps = tables[3] if w.lamps > 0 else tables[3][:0]
        ops.town_shade(*common, _t(shadow), lamps, _t(rgb), _t(rng), _t(labels), _t(normal))
        return {"rgb": torch.from_numpy(rgb), "range": torch.from_numpy(rng),
                "labels": torch.from_numpy(labels), "normal": torch.from_numpy(normal),
                "hit": torch.from_numpy(tri >= 0)}

    def _shade_reference(self, o: Tensor, d: Tensor, t: Tensor, tri: Tensor, u: Tensor,
                         v: Tensor, w: Weather, scene: _mesh.MeshScene) -> dict[str, Tensor]:
        """:meth:`_shade` in torch: the same operations in the same order, over rows of rays
        (``x (N,)``, colours ``(3, N)``)."""
        hit = tri >= 0
        tri0 = torch.where(hit, tri, 0)
        tt = torch.where(hit, t, 0.0)
        dx, dy, dz = d.T.contiguous()
        ox, oy, oz = o.T.contiguous()
        px, py, pz = ox + tt * dx, oy + tt * dy, oz + tt * dz
        a = self._tri_attr.index_select(1, tri0)  # (K, N)
        nfx, nfy, nfz = a[0], a[1], a[2]  # flat, outward (towards the ray)
        label, kind, col = a[3], torch.where(hit, a[4], -1.0), a[5:8]
        nx, ny, nz = nfx.clone(), nfy.clone(), nfz.clone()
        # smooth normals on cylinders and spheres: the vertex normals, interpolated
        sm = torch.nonzero(hit & (a[13] > 0)).flatten()
        if sm.numel():
            corners = self._triangles.index_select(0, tri0[sm])
            us, vs = u[sm].unsqueeze(-1), v[sm].unsqueeze(-1)
            vn = self._vertex_normal
            ns = (1.0 - us - vs) * vn.index_select(0, corners[:, 0]) + \
                us * vn.index_select(0, corners[:, 1]) + vs * vn.index_select(0, corners[:, 2])
            ns = ns / torch.sqrt(_dot(ns, ns)).unsqueeze(-1)
            nx[sm], ny[sm], nz[sm] = ns.T

        # ground: the cell's class, road markings painted on a street's road
        g = kind == _GROUND
        paint, off = a[8], a[9]
        along = torch.where(paint == 2, px, pz)
        across = torch.where(paint == 2, pz, px) - off
        aa = across.abs()
        centre = (aa < LINE_HALF) & (_frac(along / 6.0) < 0.5)
        edge = (aa - LANE_EDGE).abs() < LINE_HALF
        cross = (_frac((along - 20.0) / 60.0) < 4.0 / 60.0) & (aa < LANE_EDGE) & \
            (_frac(across) < 0.5)
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
        b = kind == _BOX
        facade_u = torch.where(nfx.abs() > 0.5, pz, px)
        side = b & (nfy == 0)
        fu, fy = _frac(facade_u / 2.5), _frac(py / 3.0)
        win = side & (label == _C["Building"]) & (fu > 0.25) & (fu < 0.75) & (fy > 0.3) & \
            (fy < 0.8) & (py < -1.0)
        col = torch.where(win, _column(0.12, 0.16, 0.22) * (0.7 + 0.6 * fine), col)
        roof = b & (nfy < 0) & (label == _C["Building"])
        col = torch.where(roof, col * 0.45, col)
        row = torch.floor(py / 0.25)
        brick_u = facade_u / 0.5 + 0.5 * (row - 2 * torch.floor(row / 2))
        mortar = side & (label == _C["Wall"]) & ((_frac(py / 0.25) < 0.12) |
                                                 (_frac(brick_u) < 0.06))
        col = torch.where(mortar, _column(0.7, 0.68, 0.62), col)
        slat = side & (label == _C["Fence"]) & (_frac(facade_u / 0.15) > 0.75)
        col = torch.where(slat, col * 0.5, col)
        sign = b & (label == _C["TrafficSign"])
        border = torch.maximum((px - a[10]).abs(), (py - a[11]).abs()) > 0.27
        col = torch.where(sign & (border | (nfz > 0)), _column(0.85, 0.85, 0.85), col)

        # wet weather: darker surfaces; puddles on the road and sidewalk mirror the sky
        if w.rain > 0 or w.wetness > 0:
            col = col * w.surface_factor()

        # light: ambient, the sun unless a shadow ray meets something, street lamps
        sx, sy, sz = w.sun_direction()
        lam = torch.clamp(nx * sx + ny * sy + nz * sz, min=0.0)
        shadow = hit & (lam > 0)
        lit = torch.nonzero(shadow & (nfx * sx + nfy * sy + nfz * sz > 0)).flatten()
        if lit.numel():
            bias = SHADOW_BIAS + SHADOW_BIAS_PER_M * tt[lit]
            origin = torch.stack([px[lit] + nfx[lit] * bias, py[lit] + nfy[lit] * bias,
                                  pz[lit] + nfz[lit] * bias], -1)
            towards = torch.tensor([[sx, sy, sz]], dtype=torch.float32).expand(lit.numel(), 3)
            shadow[lit] = torch.from_numpy(scene.occluded(origin.numpy(), towards.numpy()))
        lam = torch.where(shadow, 0.0, lam)
        light = _column(*w.ambient) * (0.75 - 0.25 * ny) + _column(*w.sun_colour) * lam
        if w.lamps > 0:
            acc = torch.zeros_like(px)
            for lx, ly, lz in self.lamps.tolist():
                vx, vy, vz = lx - px, ly - py, lz - pz
                d2 = vx * vx + vy * vy + vz * vz + 0.25
                ndv = torch.clamp(nx * vx + ny * vy + nz * vz, min=0.0)
                acc = acc + ndv / (d2 * torch.sqrt(d2))
            light = light + (w.lamps * 30.0) * acc * _column(1.0, 0.8, 0.5)
        rgb = col * light
        if w.windows > 0:
            lit_win = win & (_hash(_cell(facade_u, 0.4), _cell(py, 1 / 3.0),
                                   a[12].to(torch.int64), salt=3) > 0.55)
            rgb = torch.where(lit_win, _column(1.0, 0.82, 0.5) * w.windows, rgb)

        # the sky of a direction
        fog = _column(*w.fog_colour)
        sky_h, sky_z = _column(*w.sky_horizon), _column(*w.sky_zenith)
        sun_c = _column(*w.sun_colour)
        hf_scale = min(1.0, w.fog_density * 40.0)

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
            return sky * w.sky_factor() if w.rain > 0 else sky

        if w.wetness > 0:
            blot = _smooth_noise(px, pz, 0.35, 4) * 0.65 + _smooth_noise(px, pz, 1.3, 5) * 0.35
            puddle = g & ((label == _C["Road"]) | (label == _C["Sidewalk"]) |
                          (label == _C["RoadLine"])) & (blot < 0.75 * w.wetness)
            q = torch.nonzero(puddle).flatten()
            if q.numel():  # the mirror direction of a horizontal puddle: d with y flipped
                rgb[:, q] = rgb[:, q] * 0.35 + sky_of(dx[q], -dy[q], dz[q]) * 0.55

        # fog: exp(-x) as (1 + x / 256)^-256 (no transcendental, exact across code paths)
        qf = 1.0 / (1.0 + (w.fog_density / 256.0) * tt)
        for _ in range(8):
            qf = qf * qf
        rgb = rgb * qf + fog * (1.0 - qf)
        rgb = torch.where(hit, rgb, sky_of(dx, dy, dz)).clamp_(0.0, 1.0)
        rng = torch.where(hit, t, self.far)
        labels = torch.where(hit, label, 0.0).to(torch.int64)
        normal = torch.where(hit, torch.stack([nx, ny, nz]), -d.T)
        return {"rgb": rgb.T, "range": rng, "labels": labels, "normal": normal.T, "hit": hit}

    def _trace_shade(self, o: Tensor, d: Tensor, scene: _mesh.MeshScene, w: Weather
                     ) -> dict[str, Tensor]:
        """:meth:`_trace` then :meth:`_shade` of one batch (``o (N, 3) or (1, 3)``), and the
        hits' instance ids."""
        o, d = o.numpy(), d.numpy()
        hits = self._trace(scene, o, d)
        out = self._shade(o, d, *hits, w, scene)
        out["instances"] = torch.from_numpy(self._tri_instance[hits[1]].astype(np.int64))
        return out

    def _run(self, tasks: list, job) -> None:
        """``job(task)`` for every task, on ``threads`` worker threads (Embree's queries release
        the GIL, and so do torch's kernels). Worker threads even for one: on the caller's thread
        torch may split each small kernel over OpenMP threads, which a busy machine makes up to
        40 times slower (measured on 2 cores at a load of 5)."""
        threads = self.threads or torch.get_num_threads()
        with ThreadPoolExecutor(max(1, min(threads, len(tasks)))) as pool:
            for _ in pool.map(job, tasks):
                pass

    # ---------------------------------------------------------------- public API
    def render_rays(self, origins: Tensor, directions: Tensor, *, t: float = 0.0,
                    weather: str | Weather = "clear_noon", chunk: int = CHUNK
                    ) -> dict[str, Tensor]:
        """Trace arbitrary rays: the exact ground truth.

        Args:
            origins: ``(..., 3)`` or ``(3,)`` ray origins, world frame, metres.
            directions: ``(..., 3)`` unit directions, world frame (not renormalised); the
                leading dimensions of the two broadcast.
            t: time (s) for the moving objects.
            weather: a :data:`WEATHERS` name or a :class:`Weather`.
            chunk: rays per task (results do not depend on it).

        Returns:
            dict with ``rgb (..., 3)`` float32 in [0, 1], ``range (...)`` metres along the ray
            (``self.far`` for the sky), ``labels (...)`` int64 in 0..12, ``normal (..., 3)``
            (world frame, facing the ray; ``-direction`` for the sky), ``hit (...)`` bool,
            ``instances (...)`` int64: the instance id of the object hit (0: none; the
            class of id ``i`` is ``instance_label[i]``).
        """
        w = _get_weather(weather)
        if isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1:
            raise ValueError(f"chunk: expected a positive integer, got {chunk!r}")
        d = torch.as_tensor(directions).to(torch.float32)
        o = torch.as_tensor(origins).to(torch.float32)
        if d.shape[-1:] != (3,):
            raise ValueError(f"directions: expected (..., 3), got {tuple(d.shape)}")
        if o.shape[-1:] != (3,):
            raise ValueError(f"origins: expected (..., 3) or (3,), got {tuple(o.shape)}")
        try:
            shape = broadcast_shapes(o.shape[:-1], d.shape[:-1])
        except RuntimeError:
            raise ValueError(f"origins {tuple(o.shape)} and directions {tuple(d.shape)}: "
                             "their leading dimensions do not broadcast") from None
        d = d.expand(*shape, 3).reshape(-1, 3).contiguous()
        if o.dim() > 1:
            o = o.expand(*shape, 3).reshape(-1, 3).contiguous()
        else:
            o = o.reshape(1, 3)
        n = d.shape[0]
        scene = self.scene(t)
        out = {"rgb": torch.empty(n, 3), "range": torch.empty(n),
               "labels": torch.empty(n, dtype=torch.int64), "normal": torch.empty(n, 3),
               "hit": torch.empty(n, dtype=torch.bool),
               "instances": torch.empty(n, dtype=torch.int64)}

        def job(s: int) -> None:
            e = min(s + chunk, n)
            res = self._trace_shade(o[s:e] if o.shape[0] > 1 else o, d[s:e], scene, w)
            for k, v in res.items():
                out[k][s:e] = v

        self._run(list(range(0, n, chunk)), job)
        return {k: v.reshape(tuple(shape) + tuple(v.shape[1:])) for k, v in out.items()}

    @staticmethod
    def cubemap_rays(face_size: int, rotation: Tensor | None = None) -> Tensor:
        """``(6, F, F, 3)`` unit world-frame rays of the cube's texels, the rays that
        :meth:`render_cubemap` traces (``rotation`` maps cube frame to world)."""
        r = face_rays(face_size, normalize=True, dtype=torch.float32)
        if rotation is not None:
            r = r @ torch.as_tensor(rotation).to(torch.float32).T
        return r

    def _cube_rays(self, face_size: int, rotation: Tensor | None) -> Tensor:
        """:meth:`cubemap_rays`, kept for the last two face sizes when ``rotation`` is None."""
        if rotation is not None:
            return self.cubemap_rays(face_size, rotation)
        with self._lock:
            rays = self._rays_cache.get(face_size)
            if rays is None:
                rays = self.cubemap_rays(face_size)
                if len(self._rays_cache) >= 2:
                    self._rays_cache.pop(next(iter(self._rays_cache)))
                self._rays_cache[face_size] = rays
            return rays

    def render_cubemap(self, position, rotation: Tensor | None = None, face_size: int = 256, *,
                       faces: Tensor | None = None, texels: Tensor | None = None,
                       t: float = 0.0, weather: str | Weather = "clear_noon",
                       chunk: int = CHUNK, out: dict[str, Tensor] | None = None,
                       antialias: int = 1) -> dict[str, Tensor]:
        """Render a cubemap at ``position`` (world, metres).

        Args:
            position: ``(3,)`` cube centre in the world frame.
            rotation: ``(3, 3)`` cube frame -> world (default identity: the front face looks
                north along the road, down is gravity).
            face_size: ``F``.
            faces: optional ``(6,)`` bool mask of the faces to render; the others are left at
                rgb 0, depth 0, label 255 (``IGNORE_INDEX``) and instance 0.
            texels: optional ``(6, F, F)`` bool mask of the texels to render (within
                ``faces``), the others left as the faces not rendered.
            t: time (s) for the moving objects.
            weather: a :data:`WEATHERS` name or a :class:`Weather`.
            chunk: texels per task (results do not depend on it).
            out: contiguous tensors to write the outputs into (some or all of the keys below,
                each of its shape and dtype), reused from call to call instead of new memory;
                the others are allocated.
            antialias: ``k``: the RGB of a texel on an edge is the mean of ``k x k`` rays
                stratified over its footprint on the face (sub-texel ``(u, v)`` at
                ``(i + 0.5) / k - 0.5`` of a texel from its centre, then normalised), where a
                texel's centre ray is a point sample of a hard edge or texture cell (1: the
                centre ray alone, the default). Adaptive (:meth:`_antialias`): only the texels
                that differ from a rendered neighbour on their face (label, range, colour:
                ``AA_RANGE_STEP``, ``AA_RGB_STEP``) are supersampled. Depth, range and labels
                stay those of the centre ray, whatever ``k``.

        Returns:
            dict with ``rgb (1, 6, 3, F, F)`` float32, ``depth (1, 6, F, F)`` planar depth in
            metres (along each face's axis; ``self.far`` for the sky), ``labels (1, 6, F, F)``
            int64, ``range (1, 6, F, F)`` (``self.far`` for the sky) and
            ``instances (1, 6, F, F)`` int32, the centre ray's instance id (0: none).
        """
        w = _get_weather(weather)
        if isinstance(face_size, bool) or not isinstance(face_size, int) or face_size < 1:
            raise ValueError(f"face_size: expected a positive integer, got {face_size!r}")
        if isinstance(antialias, bool) or not isinstance(antialias, int) or antialias < 1:
            raise ValueError(f"antialias: expected a positive integer, got {antialias!r}")
        F = face_size
        origin = torch.as_tensor(position).to(torch.float32).reshape(1, 3)
        rot = None if rotation is None else torch.as_tensor(rotation).to(torch.float32)
        axes = face_axes(torch.float32)[:, 0]  # (6, 3) each face's axis a, cube frame
        if rot is not None:
            axes = axes @ rot.T
        rays = self._cube_rays(F, rot).reshape(6, F * F, 3)
        sel = torch.ones(6, dtype=torch.bool) if faces is None else \
            torch.as_tensor(faces).to(torch.bool).reshape(6)
        if texels is not None:
            texels = torch.as_tensor(texels).to(torch.bool)
            if texels.shape != (6, F, F):
                raise ValueError(f"texels: expected a (6, {F}, {F}) mask, got "
                                 f"{tuple(texels.shape)}")
        out = {} if out is None else out
        buffers = {}
        for key, shape, dtype, fill in (("rgb", (1, 6, 3, F, F), torch.float32, 0),
                                        ("depth", (1, 6, F, F), torch.float32, 0),
                                        ("labels", (1, 6, F, F), torch.int64, 255),
                                        ("range", (1, 6, F, F), torch.float32, 0),
                                        ("instances", (1, 6, F, F), torch.int32, 0)):
            buf = out.get(key)
            if buf is None:
                buffers[key] = torch.full(shape, fill, dtype=dtype)
                continue
            if tuple(buf.shape) != shape or buf.dtype != dtype or not buf.is_contiguous() \
                    or buf.device.type != "cpu":
                raise ValueError(f"out[{key!r}]: expected a contiguous CPU {dtype} tensor of "
                                 f"shape {shape}, got {buf.dtype} {tuple(buf.shape)}")
            buffers[key] = buf.fill_(fill)
        rgb = buffers["rgb"].view(1, 6, 3, F * F)
        dep, rng, lab = (buffers[k].view(1, 6, F * F) for k in ("depth", "range", "labels"))
        tasks = []
        for f in torch.nonzero(sel).flatten().tolist():
            if texels is None:
                tasks += [(f, slice(s, min(s + chunk, F * F))) for s in range(0, F * F, chunk)]
            else:
                idx = np.flatnonzero(texels[f].reshape(-1).numpy())
                tasks += [(f, idx[s:s + chunk]) for s in range(0, idx.size, chunk)]
        scene = self.scene(t)
        rays_np, origin_np = rays.numpy(), origin.numpy()
        rgb_np, dep_np, rng_np, lab_np = (x.numpy() for x in (rgb, dep, rng, lab))
        inst_np = buffers["instances"].view(6, F * F).numpy()
        axes_np = axes.numpy()
        ops = _ops()

        def job(task) -> None:
            f, q = task
            d = rays_np[f, q]
            hits = self._trace(scene, origin_np, d)
            inst_np[f, q] = self._tri_instance[hits[1]]
            res = {k: v.numpy() for k, v in self._shade(origin_np, d, *hits, w, scene).items()}
            a = axes_np[f]
            if ops is None:
                depth = np.where(res["hit"], res["range"] * (d[:, 0] * a[0] + d[:, 1] * a[1]
                                                             + d[:, 2] * a[2]), self.far)
                rgb_np[0, f][:, q] = res["rgb"].T   # (3, n): not rgb_np[0, f, :, q], (n, 3)
                dep_np[0, f, q], rng_np[0, f, q], lab_np[0, f, q] = \
                    depth, res["range"], res["labels"]
                return
            index, start = (None, q.start) if isinstance(q, slice) else (_t(q), 0)
            ops.town_store(_t(np.ascontiguousarray(d)), index, start,
                           *(_t(res[k]) for k in ("rgb", "range", "labels", "hit")),
                           _t(np.ascontiguousarray(a)), self.far, rgb[0, f], dep[0, f],
                           rng[0, f], lab[0, f])

        self._run(tasks, job)
        if antialias > 1:
            self._antialias(antialias, sel, texels, buffers, origin_np, rot, scene, w, chunk)
        return buffers

    def _antialias(self, k: int, sel: Tensor, texels: Tensor | None,
                   buffers: dict[str, Tensor], origin: np.ndarray, rot: Tensor | None,
                   scene: _mesh.MeshScene, w: Weather, chunk: int) -> None:
        """:meth:`render_cubemap`'s ``antialias=k``, on the cube of centre rays in
        ``buffers``: the RGB of every texel on an edge becomes the mean of ``k x k`` sub-texel
        rays (for odd ``k`` the middle one is the centre ray, already traced).

        The texels on an edge: :func:`edge_texels` of each face, among its rendered texels
        (``texels``). A texel whose neighbours all look like it keeps its centre ray's colour:
        the sky, the insides of surfaces and of texture cells."""
        F = buffers["rgb"].shape[-1]
        faces = torch.nonzero(sel).flatten().tolist()
        edges: dict[int, np.ndarray] = {}

        def detect(f: int) -> None:
            done = None if texels is None else texels[f]
            edges[f] = np.flatnonzero(edge_texels(
                buffers["labels"][0, f], buffers["range"][0, f], buffers["rgb"][0, f],
                done).reshape(-1).numpy())

        self._run(faces, detect)
        # the sub-texel offsets (du, dv) from a texel's centre, in texels (the centre left out)
        off = (torch.arange(k, dtype=torch.float32) + 0.5) / k - 0.5
        dv, du = (x.reshape(-1) for x in torch.meshgrid(off, off, indexing="ij"))
        keep = (du != 0) | (dv != 0)
        du, dv = du[keep], dv[keep]
        m = du.numel()
        per_task = max(1, chunk // m)
        tasks = [(f, edges[f][s:s + per_task]) for f in faces
                 for s in range(0, edges[f].size, per_task)]
        rgb_np = buffers["rgb"].view(1, 6, 3, F * F).numpy()

        def job(task) -> None:
            f, q = task
            # the sub-texels' unit rays (cubemap.faces), rotated into the world as element-wise
            # sums: the same bits whatever the batch (the town's textures tell a ray's last bit
            # apart: the ground's noise cells split at y = 0, where a hit point's rounding falls)
            i, j = torch.from_numpy(q // F).float(), torch.from_numpy(q % F).float()
            uv = torch.stack([j[:, None] + du, i[:, None] + dv], -1)   # (n, m, 2)
            d = face_pixel_to_ray(f, uv, F, normalize=True).reshape(-1, 3)
            if rot is not None:
                d = d[:, :1] * rot[:, 0] + d[:, 1:2] * rot[:, 1] + d[:, 2:] * rot[:, 2]
            d = np.ascontiguousarray(d.numpy())
            sub = self._shade(origin, d, *self._trace(scene, origin, d), w, scene)["rgb"]
            sub = sub.numpy().reshape(q.size, m, 3)
            total = sub[:, 0].copy()
            for n in range(1, m):   # summed in order: the same whatever the batch
                total += sub[:, n]
            if m < k * k:   # odd k: the centre ray is one of the k x k
                total += rgb_np[0, f][:, q].T
            rgb_np[0, f][:, q] = (total / np.float32(k * k)).T

        self._run(tasks, job)
