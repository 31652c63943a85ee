"""A small procedural town, ray-cast in torch from analytic primitives.

World frame (metres): x east, y down (gravity is +y, like the OpenCV camera's y), z north. The
ground is the plane ``y = 0``; things above the ground have ``y < 0``. The road runs along z,
centred on ``x = 0``: two driving lanes (``|x| < 3.5``, centre line dashed, lane edges solid),
a parking strip on each side (``3.5 < |x| < 5.25``), sidewalks (``5.25 < |x| < 8.5``), and
beyond them buildings, walls, fences and open lots (ground labelled ``Other``). The town spans
``|z| < length / 2``; the ground and the road go on beyond it. A camera with identity rotation at
``(0, -1.2, 0)`` stands on the centre line at eye height and looks north, along the road.

Primitives (no meshes): the ground plane, textured by world coordinates (road, lane markings,
crossings, sidewalk, lots); axis-aligned boxes (buildings, walls, fences, vehicles, sign plates,
bins); vertical cylinders with a top cap (poles, tree trunks, pedestrians' bodies); spheres (tree
crowns, pedestrians' heads). Primitives are seen from outside: a ray starting inside one does not
see it. Moving vehicles and pedestrians go straight along z at constant speed and wrap around
the town's length (:meth:`Town.moving_objects`).

Outputs (:meth:`Town.render_rays`, :meth:`Town.render_cubemap`): RGB in ``[0, 1]``, the range
(Euclidean distance along the ray; for the sky: ``town.far``, default 1000 m) or the cubemap's
planar depth (along each face's axis; for the sky: ``town.far``, the far plane of a simulator's
depth camera), and CARLA's 13 class ids (sky is ``Unlabeled``). Colour is
``albedo(class, world point) * (ambient + sun * lambert) + emission``, then distance fog; the
weather preset (:data:`WEATHERS`) changes light, colour and fog, never geometry or labels.

Exactness: the cubemap path culls primitives per tile of texels but computes every ray with the
same element-wise operations as :meth:`Town.render_rays`, and uses no transcendental functions
(only ``+ - * /``, ``sqrt``, comparisons, integer hashing), so ``render_rays`` of the cube's own
texel rays (:meth:`Town.cubemap_rays`) equals ``render_cubemap`` bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..cubemap.faces import face_axes, face_intrinsics, face_rays

__all__ = ["Town", "Weather", "WEATHERS", "CLASS_IDS"]

CLASS_IDS = {name: i for i, name in enumerate(
    ("Unlabeled", "Building", "Fence", "Other", "Pedestrian", "Pole", "RoadLine", "Road",
     "Sidewalk", "Vegetation", "Vehicle", "Wall", "TrafficSign"))}
_C = CLASS_IDS

EPS = 1e-4  # minimum hit distance (m)
_INF = float("inf")

# Road cross-section (|x|, metres).
LANE_EDGE = 3.5
ROAD_HALF = 5.25
SIDEWALK_HALF = 8.5
LINE_HALF = 0.08


@dataclass(frozen=True)
class Weather:
    """Light, sky and fog of a weather / time-of-day preset. Colours are linear RGB in [0, 1]
    (emission and sun may exceed 1; the result is clamped).

    ``sun_elevation`` and ``sun_azimuth`` are in degrees (azimuth from north, z, towards east,
    x). ``fog_density`` is per metre: the fog weight is ``1 - exp(-fog_density * range)``.
    ``lamps``: street-lamp intensity (0: off). ``windows``: emission of lit windows."""

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

    def sun_direction(self) -> tuple[float, float, float]:
        """Unit vector towards the sun in the world frame (y down, so up is -y)."""
        e, a = math.radians(self.sun_elevation), math.radians(self.sun_azimuth)
        return (math.sin(a) * math.cos(e), -math.sin(e), math.cos(a) * math.cos(e))


WEATHERS: dict[str, Weather] = {
    "clear_noon": Weather(65.0, 150.0, (1.0, 0.96, 0.88), (0.30, 0.34, 0.42),
                          (0.22, 0.42, 0.85), (0.68, 0.80, 0.95), (0.72, 0.80, 0.92), 0.0015),
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
    except KeyError:
        raise ValueError(f"unknown weather {weather!r}; presets: {sorted(WEATHERS)}") from None


# --------------------------------------------------------------------------------------------
# Element-wise intersection kernels. Ray tensors are (..., R, 1), primitive tensors (..., 1, K)
# or (..., K); all broadcast to (..., R, K). Only + - * / sqrt min max and comparisons.

def _box_t(o, inv, lo, hi):
    ox, oy, oz = o
    ix, iy, iz = inv
    tx1, tx2 = (lo[0] - ox) * ix, (hi[0] - ox) * ix
    ty1, ty2 = (lo[1] - oy) * iy, (hi[1] - oy) * iy
    tz1, tz2 = (lo[2] - oz) * iz, (hi[2] - oz) * iz
    tnear = torch.maximum(torch.maximum(torch.minimum(tx1, tx2), torch.minimum(ty1, ty2)),
                          torch.minimum(tz1, tz2))
    tfar = torch.minimum(torch.minimum(torch.maximum(tx1, tx2), torch.maximum(ty1, ty2)),
                         torch.maximum(tz1, tz2))
    hit = (tfar >= tnear) & (tnear > EPS)
    return torch.where(hit, tnear, _INF)


def _cyl_t(o, d, iy, a_xz, cx, cz, r, ytop, ybot):
    """Vertical cylinder |(x, z) - (cx, cz)| = r, ytop <= y <= ybot, with a top cap at ytop.
    Returns (t, cap): cap is True where the cap is hit first."""
    ox, oy, oz = o
    dx, dy, dz = d
    ocx, ocz = ox - cx, oz - cz
    r2 = r * r
    b = dx * ocx + dz * ocz
    c = ocx * ocx + ocz * ocz - r2
    disc = b * b - a_xz * c
    ts = (-b - torch.sqrt(torch.clamp(disc, min=0.0))) / a_xz
    ys = oy + ts * dy
    side = (disc >= 0) & (ts > EPS) & (ys >= ytop) & (ys <= ybot)
    ts = torch.where(side, ts, _INF)
    tc = (ytop - oy) * iy
    px, pz = ocx + tc * dx, ocz + tc * dz
    cap = (tc > EPS) & (px * px + pz * pz <= r2)
    tc = torch.where(cap, tc, _INF)
    return torch.minimum(ts, tc), tc < ts


def _sph_t(o, d, cen, r):
    ocx, ocy, ocz = o[0] - cen[0], o[1] - cen[1], o[2] - cen[2]
    b = d[0] * ocx + d[1] * ocy + d[2] * ocz
    c = ocx * ocx + ocy * ocy + ocz * ocz - r * r
    disc = b * b - c
    t = -b - torch.sqrt(torch.clamp(disc, min=0.0))
    return torch.where((disc >= 0) & (t > EPS), t, _INF)


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


class Town:
    """A procedural town, deterministic by ``seed`` (a ``torch.Generator``; no global RNG).

    Args:
        seed: the random layout (buildings, gaps, parked cars, trees, colours, movers).
        length: extent of the town along z (metres), centred on ``z = 0``.
        far: range (and planar depth) reported for the sky, metres.
        tile: texels per side of the tiles that :meth:`render_cubemap` culls primitives over.
        groups: :meth:`render_cubemap` traces its tiles in this many groups of similar
            candidate counts (speed only; the result does not depend on it).

    Attributes hold the primitives as float32 tensors: ``boxes_lo/boxes_hi (Nb, 3)``,
    ``cyl (Nc, 5)`` = (cx, cz, r, ytop, ybot), ``sph (Ns, 4)`` = (cx, cy, cz, r), each with
    ``*_label`` (int64 class ids), ``*_colour (N, 3)`` albedo and ``*_mover`` (index into the
    movers, -1 for static). ``movers`` is ``(M, 3)`` = (z0, speed m/s, kind 0 vehicle / 1
    pedestrian).
    """

    def __init__(self, seed: int = 0, *, length: float = 160.0, far: float = 1000.0,
                 tile: int = 16, groups: int = 8):
        self.seed = int(seed)
        self.length = float(length)
        self.far = float(far)
        self.tile = int(tile)
        self.groups = int(groups)
        g = torch.Generator().manual_seed(self.seed)
        self._build(g)

    # ---------------------------------------------------------------- layout
    def _build(self, g: torch.Generator) -> None:
        def U(a: float, b: float) -> float:
            return a + (b - a) * float(torch.rand((), generator=g, dtype=torch.float64))

        L2 = self.length / 2
        boxes, cyls, sphs, movers, lamps = [], [], [], [], []

        def box(lo, hi, label, colour, mover=-1):
            boxes.append((lo, hi, label, colour, mover))

        def vehicle(xc, zc, colour, mover=-1, flip=1.0):
            box((xc - 0.85, -1.05, zc - 2.15), (xc + 0.85, -0.32, zc + 2.15), _C["Vehicle"],
                colour, mover)
            z0, z1 = sorted((zc - 1.2 * flip, zc + 0.9 * flip))
            box((xc - 0.75, -1.5, z0), (xc + 0.75, -1.05, z1), _C["Vehicle"],
                (0.10, 0.12, 0.15), mover)

        for s in (-1.0, 1.0):
            # buildings along the block, gaps filled with walls, fences or left open
            z = -L2
            near_done = False
            while z < L2 - 6:
                ln = min(U(8, 20), L2 - z)
                x0, depth, h = 9.0 + U(0, 1.5), U(8, 16), U(6, 28)
                grey = U(0.35, 0.75)
                col = (grey * U(0.9, 1.1), grey * U(0.85, 1.0), grey * U(0.75, 0.95))
                xa, xb = sorted((s * x0, s * (x0 + depth)))
                box((xa, -h, z), (xb, 0.0, z + ln), _C["Building"], col)
                z += ln
                gap = U(2, 7)
                kind = U(0, 1)
                if not near_done and z > -4.0:
                    # the first gap ahead of the origin: a wall (east) or a fence (west), so
                    # that every class shows from the default pose
                    near_done, gap, kind = True, max(gap, 4.0), (0.0 if s > 0 else 0.5)
                if z + gap < L2:
                    if kind < 0.4:
                        xa, xb = sorted((s * 9.0, s * 9.35))
                        box((xa, -U(1.8, 3.0), z), (xb, 0.0, z + gap), _C["Wall"],
                            (U(0.45, 0.6), U(0.25, 0.35), U(0.2, 0.28)))
                    elif kind < 0.8:
                        xa, xb = sorted((s * 8.9, s * 8.96))
                        box((xa, -1.5, z), (xb, 0.0, z + gap), _C["Fence"],
                            (U(0.5, 0.7), U(0.45, 0.6), U(0.35, 0.45)))
                z += gap
            # street lamps (poles), staggered
            zl = -L2 + 5 + (5 if s > 0 else 0)
            while zl < L2:
                cyls.append((s * 7.9, zl, 0.11, -6.5, 0.0, _C["Pole"], (0.45, 0.46, 0.48), -1))
                lamps.append((s * 7.9, -6.6, zl))
                zl += 20
            # trees on the sidewalk
            zt = -L2 + 3
            while zt < L2 - 2:
                if U(0, 1) < 0.7:
                    r = U(1.1, 1.9)
                    cyls.append((s * 6.4, zt, 0.18, -2.8, 0.0, _C["Vegetation"],
                                 (0.30, 0.20, 0.12), -1))
                    sphs.append((s * 6.4, -(2.8 + 0.7 * r), zt, r, _C["Vegetation"],
                                 (0.16 * U(0.8, 1.2), 0.36 * U(0.8, 1.2), 0.10), -1))
                zt += 12
            # bins (Other) on the sidewalk
            for _ in range(4):
                zb = U(-L2 + 4, L2 - 4)
                xa, xb = sorted((s * 7.3, s * 7.9))
                box((xa, -1.0, zb), (xb, 0.0, zb + 0.6), _C["Other"],
                    (0.15, U(0.25, 0.4), 0.18))
            # parked vehicles on the parking strip
            zp = -L2 + 3
            while zp < L2 - 3:
                if U(0, 1) < 0.45:
                    vehicle(s * 4.4, zp, (U(0.1, 0.9), U(0.1, 0.9), U(0.1, 0.9)))
                zp += 6.0
        # traffic signs: pole + plate facing the traffic; the first is near the origin
        for i, (s, zs) in enumerate([(1.0, 14.0), (-1.0, -22.0), (1.0, U(30, 70)),
                                     (-1.0, U(-70, -30))]):
            x = s * 5.6
            cyls.append((x, zs, 0.05, -2.9, 0.0, _C["Pole"], (0.55, 0.55, 0.57), -1))
            col = [(0.1, 0.25, 0.7), (0.75, 0.1, 0.1), (0.9, 0.75, 0.1)][i % 3]
            zf = zs - 0.06 if s > 0 else zs + 0.02
            box((x - 0.35, -2.95, zf), (x + 0.35, -2.25, zf + 0.04), _C["TrafficSign"], col)
        # moving vehicles: northbound in the east lane, southbound in the west lane
        for i in range(6):
            s = 1.0 if i % 2 == 0 else -1.0
            z0 = (-30.0 if i == 0 else U(-L2, L2))
            speed = s * U(6, 12)
            movers.append((z0, speed, 0.0))
            vehicle(s * 1.75, z0, (U(0.1, 0.9), U(0.1, 0.9), U(0.1, 0.9)), len(movers) - 1, s)
        # pedestrians on the sidewalks; the first is near the origin
        for i in range(8):
            s = 1.0 if i % 2 == 0 else -1.0
            z0 = 7.0 if i == 0 else U(-L2, L2)
            speed = U(-1.6, 1.6)
            movers.append((z0, speed, 1.0))
            x = s * U(6.9, 7.5)
            cyls.append((x, z0, 0.22, -1.45, 0.0, _C["Pedestrian"],
                         (U(0.1, 0.8), U(0.1, 0.8), U(0.1, 0.8)), len(movers) - 1))
            sphs.append((x, -1.6, z0, 0.14, _C["Pedestrian"], (0.8, 0.6, 0.48), len(movers) - 1))

        f32 = torch.float32
        self.boxes_lo = torch.tensor([b[0] for b in boxes], dtype=f32)
        self.boxes_hi = torch.tensor([b[1] for b in boxes], dtype=f32)
        self.boxes_label = torch.tensor([b[2] for b in boxes], dtype=torch.int64)
        self.boxes_colour = torch.tensor([b[3] for b in boxes], dtype=f32)
        self.boxes_mover = torch.tensor([b[4] for b in boxes], dtype=torch.int64)
        self.cyl = torch.tensor([c[:5] for c in cyls], dtype=f32)
        self.cyl_label = torch.tensor([c[5] for c in cyls], dtype=torch.int64)
        self.cyl_colour = torch.tensor([c[6] for c in cyls], dtype=f32)
        self.cyl_mover = torch.tensor([c[7] for c in cyls], dtype=torch.int64)
        self.sph = torch.tensor([c[:4] for c in sphs], dtype=f32)
        self.sph_label = torch.tensor([c[4] for c in sphs], dtype=torch.int64)
        self.sph_colour = torch.tensor([c[5] for c in sphs], dtype=f32)
        self.sph_mover = torch.tensor([c[6] for c in sphs], dtype=torch.int64)
        self.movers = torch.tensor(movers, dtype=torch.float64)
        self.lamps = torch.tensor(lamps, dtype=f32)

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

    def geometry(self, t: float = 0.0) -> dict[str, Tensor]:
        """Primitive parameters at time ``t``: the movers shifted along z."""
        dz = (self.moving_objects(t)["z"] - self.movers[:, 0]).to(torch.float32)
        dz = torch.cat([dz, torch.zeros(1)])  # index -1 -> static

        def shift(m):
            return dz[m]
        lo, hi = self.boxes_lo.clone(), self.boxes_hi.clone()
        lo[:, 2] += shift(self.boxes_mover)
        hi[:, 2] += shift(self.boxes_mover)
        cyl = self.cyl.clone()
        cyl[:, 1] += shift(self.cyl_mover)
        sph = self.sph.clone()
        sph[:, 2] += shift(self.sph_mover)
        return {"lo": lo, "hi": hi, "cyl": cyl, "sph": sph}

    # ---------------------------------------------------------------- tracing
    @staticmethod
    def _ray_parts(o: Tensor, d: Tensor):
        """Per-ray components and inverse directions (no zero divisors)."""
        dd = torch.where(d == 0, torch.full_like(d, 1e-20), d)
        inv = 1.0 / dd
        a_xz = d[..., 0] * d[..., 0] + d[..., 2] * d[..., 2]
        a_xz = torch.where(a_xz < 1e-20, torch.full_like(a_xz, 1e-20), a_xz)
        return o.unbind(-1), d.unbind(-1), inv.unbind(-1), a_xz

    def _closest(self, o, d, geo, cand=None):
        """Closest hit. ``o``, ``d`` (..., R, 3); ``cand``: None (all primitives) or per-type
        ``(index (..., K), valid (..., K))`` candidate lists broadcast over R.
        Returns t (..., R) (inf: no hit), kind (0 ground, 1 box, 2 cylinder, 3 sphere), global
        primitive index, cap flag."""
        (ox, oy, oz), (dx, dy, dz), (ix, iy, iz), a_xz = self._ray_parts(o, d)
        e = lambda x: x.unsqueeze(-1)  # noqa: E731  (..., R) -> (..., R, 1)
        O, D, I = (e(ox), e(oy), e(oz)), (e(dx), e(dy), e(dz)), (e(ix), e(iy), e(iz))
        tg = torch.where((dy > 0) & (oy < 0), (0.0 - oy) * iy, _INF)
        tg = torch.where(tg > EPS, tg, _INF)

        def params(x: Tensor, k: int):
            # x (P, C) -> list of C tensors (..., 1, K) [candidates] or (P,)
            if cand is None:
                return [x[:, j] for j in range(x.shape[1])], None
            idx, valid = cand[k]
            g = x[idx]  # (..., K, C)
            return [g[..., j].unsqueeze(-2) for j in range(x.shape[1])], valid.unsqueeze(-2)

        def reduce(t, valid, k):
            if valid is not None:
                t = torch.where(valid, t, _INF)
            if t.shape[-1] == 0:
                z = torch.zeros(t.shape[:-1], dtype=torch.int64, device=t.device)
                return torch.full(t.shape[:-1], _INF), z
            tm, am = t.min(-1)
            if cand is not None:
                idx = cand[k][0].unsqueeze(-2).expand(*am.shape, -1)
                am = torch.gather(idx, -1, am.unsqueeze(-1)).squeeze(-1)
            return tm, am

        p, valid = params(torch.cat([geo["lo"], geo["hi"]], 1), 0)
        tb, ib = reduce(_box_t(O, I, p[:3], p[3:]), valid, 0)
        p, valid = params(geo["cyl"], 1)
        tc_all, cap_all = _cyl_t(O, D, I[1], e(a_xz), *p)
        tc, ic = reduce(tc_all, valid, 1)
        if cap_all.shape[-1]:
            kk = tc_all.min(-1)[1] if valid is None else torch.where(valid, tc_all, _INF).min(-1)[1]
            cap = torch.gather(cap_all, -1, kk.unsqueeze(-1)).squeeze(-1)
        else:
            cap = torch.zeros_like(tc, dtype=torch.bool)
        p, valid = params(geo["sph"], 2)
        ts, is_ = reduce(_sph_t(O, D, p[:3], p[3]), valid, 2)
        t = torch.stack([tg, tb, tc, ts], -1)
        tmin, kind = t.min(-1)
        idx = torch.stack([torch.zeros_like(ib), ib, ic, is_], -1)
        idx = torch.gather(idx, -1, kind.unsqueeze(-1)).squeeze(-1)
        tmin = torch.where(tmin < self.far, tmin, _INF)
        return tmin, kind, idx, cap & (kind == 2)

    # ---------------------------------------------------------------- shading
    def _shade(self, o, d, t, kind, idx, cap, geo, w: Weather):
        """Per-ray labels, range and colour from the closest hit. All inputs flat (N, ...)."""
        hit = torch.isfinite(t)
        tt = torch.where(hit, t, torch.zeros_like(t))
        p = o + tt.unsqueeze(-1) * d  # (N, 3)
        px, py, pz = p.unbind(-1)
        n = torch.zeros_like(p)
        n[:, 1] = -1.0  # ground / caps: up
        col = torch.zeros_like(p)
        label = torch.zeros_like(idx)
        ax = px.abs()

        # ground
        g = hit & (kind == 0)
        road = ax < ROAD_HALF
        centre = (ax < LINE_HALF) & (_frac(pz / 6.0) < 0.5)
        edge = (ax - LANE_EDGE).abs() < LINE_HALF
        cross = (_frac((pz - 20.0) / 60.0) < 4.0 / 60.0) & (ax < LANE_EDGE) & \
            (_frac(px / 1.0) < 0.5)
        line = road & (centre | edge | cross)
        glabel = torch.where(road, torch.where(line, _C["RoadLine"], _C["Road"]),
                             torch.where(ax < SIDEWALK_HALF, _C["Sidewalk"], _C["Other"]))
        label = torch.where(g, glabel, label)
        tiles = (_frac(px / 0.6) < 0.06) | (_frac(pz / 0.6) < 0.06)
        gcol = torch.where(
            (glabel == _C["Road"]).unsqueeze(-1), torch.tensor([0.26, 0.26, 0.27]),
            torch.where((glabel == _C["RoadLine"]).unsqueeze(-1), torch.tensor([0.85, 0.85, 0.8]),
                        torch.where((glabel == _C["Sidewalk"]).unsqueeze(-1),
                                    torch.tensor([0.62, 0.60, 0.56]),
                                    torch.tensor([0.42, 0.38, 0.28]))))
        gcol = gcol * torch.where((tiles & (glabel == _C["Sidewalk"])), 0.75, 1.0).unsqueeze(-1)
        col = torch.where(g.unsqueeze(-1), gcol, col)

        # boxes
        b = hit & (kind == 1)
        bi = torch.where(b, idx, 0)
        lo, hi = geo["lo"][bi], geo["hi"][bi]
        # normal: the face the point lies on (smallest distance to a slab plane)
        dist = torch.stack([(p - lo).abs(), (hi - p).abs()], -2)  # (N, 2, 3)
        dmin, which = dist.min(-2)  # (N, 3)
        axis = dmin.min(-1)[1]
        sign = torch.where(torch.gather(which, -1, axis.unsqueeze(-1)).squeeze(-1) == 0, -1.0, 1.0)
        nb = torch.zeros_like(p).scatter_(-1, axis.unsqueeze(-1), sign.unsqueeze(-1))
        n = torch.where(b.unsqueeze(-1), nb, n)
        blabel = self.boxes_label[bi]
        label = torch.where(b, blabel, label)
        col = torch.where(b.unsqueeze(-1), self.boxes_colour[bi], col)

        # cylinders
        c = hit & (kind == 2)
        ci = torch.where(c, idx, 0)
        cp = geo["cyl"][ci]
        nc = torch.stack([(px - cp[:, 0]) / cp[:, 2], torch.zeros_like(px),
                          (pz - cp[:, 1]) / cp[:, 2]], -1)
        nc = torch.where(cap.unsqueeze(-1), n, nc)
        n = torch.where(c.unsqueeze(-1), nc, n)
        label = torch.where(c, self.cyl_label[ci], label)
        col = torch.where(c.unsqueeze(-1), self.cyl_colour[ci], col)

        # spheres
        s = hit & (kind == 3)
        si = torch.where(s, idx, 0)
        sp = geo["sph"][si]
        ns = (p - sp[:, :3]) / sp[:, 3:4]
        n = torch.where(s.unsqueeze(-1), ns, n)
        label = torch.where(s, self.sph_label[si], label)
        col = torch.where(s.unsqueeze(-1), self.sph_colour[si], col)

        # textures: noise everywhere, patterns per class
        fine = _hash(_cell(px, 6.0), _cell(py, 6.0), _cell(pz, 6.0), salt=1)
        coarse = _hash(_cell(px, 0.7), _cell(py, 0.7), _cell(pz, 0.7), salt=2)
        col = col * (0.8 + 0.25 * fine + 0.15 * coarse).unsqueeze(-1)
        facade_u = torch.where(nb[:, 0].abs() > 0.5, pz, px)
        side = (b & (nb[:, 1] == 0))
        win = side & (label == _C["Building"]) & (_frac(facade_u / 2.5) > 0.25) & \
            (_frac(facade_u / 2.5) < 0.75) & (_frac(py / 3.0) > 0.3) & (_frac(py / 3.0) < 0.8) & \
            (py < -1.0)
        col = torch.where(win.unsqueeze(-1), torch.tensor([0.12, 0.16, 0.22]) * (
            0.7 + 0.6 * fine).unsqueeze(-1), col)
        roof = b & (nb[:, 1] < 0) & (label == _C["Building"])
        col = torch.where(roof.unsqueeze(-1), col * 0.45, col)
        row = torch.floor(py / 0.25)
        brick_u = facade_u / 0.5 + 0.5 * (row - 2 * torch.floor(row / 2))
        mortar = (_frac(py / 0.25) < 0.12) | (_frac(brick_u) < 0.06)
        col = torch.where((side & (label == _C["Wall"]) & mortar).unsqueeze(-1),
                          torch.tensor([0.7, 0.68, 0.62]), col)
        slat = side & (label == _C["Fence"]) & (_frac(facade_u / 0.15) > 0.75)
        col = torch.where(slat.unsqueeze(-1), col * 0.5, col)
        sign = b & (label == _C["TrafficSign"])
        cx_, cy_ = (lo[:, 0] + hi[:, 0]) / 2, (lo[:, 1] + hi[:, 1]) / 2
        border = torch.maximum((px - cx_).abs(), (py - cy_).abs()) > 0.27
        col = torch.where((sign & (border | (nb[:, 2] > 0))).unsqueeze(-1),
                          torch.tensor([0.85, 0.85, 0.85]), col)

        # light
        sun = torch.tensor(w.sun_direction())
        lam = torch.clamp(n[:, 0] * sun[0] + n[:, 1] * sun[1] + n[:, 2] * sun[2], min=0.0)
        light = torch.tensor(w.ambient) * (0.75 - 0.25 * n[:, 1]).unsqueeze(-1) + \
            torch.tensor(w.sun_colour) * lam.unsqueeze(-1)
        if w.lamps > 0:
            acc = torch.zeros_like(px)
            for lx, ly, lz in self.lamps.tolist():
                vx, vy, vz = lx - px, ly - py, lz - pz
                d2 = vx * vx + vy * vy + vz * vz + 0.25
                ndv = torch.clamp(n[:, 0] * vx + n[:, 1] * vy + n[:, 2] * vz, min=0.0)
                acc = acc + ndv / (d2 * torch.sqrt(d2))
            light = light + (w.lamps * 30.0) * acc.unsqueeze(-1) * torch.tensor([1.0, 0.8, 0.5])
        rgb = col * light
        if w.windows > 0:
            lit = win & (_hash(_cell(facade_u, 0.4), _cell(py, 1 / 3.0), bi, salt=3) > 0.55)
            rgb = torch.where(lit.unsqueeze(-1), torch.tensor([1.0, 0.82, 0.5]) * w.windows, rgb)

        # fog: exp(-x) as (1 + x / 256)^-256 (no transcendental, exact across code paths)
        x = w.fog_density * tt
        q = 1.0 / (1.0 + x / 256.0)
        for _ in range(8):
            q = q * q
        fog = torch.tensor(w.fog_colour)
        rgb = rgb * q.unsqueeze(-1) + fog * (1.0 - q).unsqueeze(-1)

        # sky
        up = torch.clamp(-d[:, 1], min=0.0)
        h = 1.0 - up
        h = 1.0 - h * h * h
        sky = torch.tensor(w.sky_horizon) + (torch.tensor(w.sky_zenith) -
                                             torch.tensor(w.sky_horizon)) * h.unsqueeze(-1)
        cs = torch.clamp(d[:, 0] * sun[0] + d[:, 1] * sun[1] + d[:, 2] * sun[2], min=0.0)
        g8 = cs
        for _ in range(3):
            g8 = g8 * g8
        g256 = g8
        for _ in range(5):
            g256 = g256 * g256
        sky = sky + torch.tensor(w.sun_colour) * (0.15 * g8 + 0.8 * g256).unsqueeze(-1)
        sky = torch.where((cs > 0.99995).unsqueeze(-1), torch.tensor(w.sun_colour) * 4.0, sky)
        # the sky takes the fog colour near the horizon, more so in thicker fog
        hf = torch.clamp(1.0 - up * 8.0, min=0.0) * min(1.0, w.fog_density * 40.0)
        sky = sky + (fog - sky) * hf.unsqueeze(-1)
        rgb = torch.where(hit.unsqueeze(-1), rgb, sky)
        rgb = torch.clamp(rgb, 0.0, 1.0)
        rng = torch.where(hit, t, torch.full_like(t, self.far))
        label = torch.where(hit, label, _C["Unlabeled"])
        n = torch.where(hit.unsqueeze(-1), n, -d)
        return {"rgb": rgb, "range": rng, "labels": label, "normal": n, "hit": hit}

    # ---------------------------------------------------------------- public API
    def render_rays(self, origins: Tensor, directions: Tensor, *, t: float = 0.0,
                    weather: str | Weather = "clear_noon", chunk: int = 8192) -> dict[str, Tensor]:
        """Ray-cast arbitrary rays: the exact ground truth.

        Args:
            origins: ``(..., 3)`` or ``(3,)`` ray origins, world frame, metres.
            directions: ``(..., 3)`` unit directions, world frame (not renormalised).
            t: time (s) for the moving objects.
            weather: a :data:`WEATHERS` name or a :class:`Weather`.
            chunk: rays per batch (memory bound; results do not depend on it).

        Returns:
            dict with ``rgb (..., 3)`` float32 in [0, 1], ``range (...)`` metres along the ray
            (``self.far`` for the sky), ``labels (...)`` int64 in 0..12, ``normal (..., 3)``
            (world frame, facing the ray; ``-direction`` for the sky), ``hit (...)`` bool.
        """
        w = _get_weather(weather)
        d = directions.to(torch.float32)
        shape = d.shape[:-1]
        d = d.reshape(-1, 3)
        o = origins.to(torch.float32)
        o = o.expand(*shape, 3).reshape(-1, 3) if o.dim() > 1 else o.expand(d.shape[0], 3)
        geo = self.geometry(t)
        outs = []
        for s in range(0, d.shape[0], chunk):
            oc, dc = o[s:s + chunk], d[s:s + chunk]
            hit = self._closest(oc, dc, geo)
            outs.append(self._shade(oc, dc, *hit, geo, w))
        out = {k: torch.cat([x[k] for x in outs]) for k in outs[0]}
        return {k: v.reshape(tuple(shape) + tuple(v.shape[1:])) for k, v in out.items()}

    @staticmethod
    def cubemap_rays(face_size: int, rotation: Tensor | None = None) -> Tensor:
        """``(6, F, F, 3)`` unit world-frame rays of the cube's texels, the rays that
        :meth:`render_cubemap` traces (``rotation`` maps cube frame to world)."""
        r = face_rays(face_size, normalize=True, dtype=torch.float32)
        if rotation is not None:
            r = r @ rotation.to(torch.float32).T
        return r

    def _tile_candidates(self, geo, origin, rot, F: int, ts: int, T: int):
        """Per (face, tile) candidate lists for each primitive type, conservative: the
        primitive's world AABB, taken to the cube frame (its AABB there), clipped to each face's
        half-space ``a . x >= 1e-5`` (closer points are within ``EPS`` of the origin, never
        hit), projected onto the face, grown by a margin, and tested against every tile."""
        f, c = face_intrinsics(F)
        axes = face_axes(torch.float32)  # cube frame
        lo, hi = geo["lo"], geo["hi"]
        cyl, sph = geo["cyl"], geo["sph"]
        aabbs = [
            (lo, hi),
            (torch.stack([cyl[:, 0] - cyl[:, 2], cyl[:, 3], cyl[:, 1] - cyl[:, 2]], -1),
             torch.stack([cyl[:, 0] + cyl[:, 2], cyl[:, 4], cyl[:, 1] + cyl[:, 2]], -1)),
            (sph[:, :3] - sph[:, 3:], sph[:, :3] + sph[:, 3:]),
        ]
        sel = torch.tensor([[0, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1, 1], [1, 0, 0], [1, 0, 1],
                            [1, 1, 0], [1, 1, 1]], dtype=torch.bool)
        start = torch.arange(T, dtype=torch.float32) * ts
        delta = 1e-5
        out = []
        for a_lo, a_hi in aabbs:
            P = a_lo.shape[0]
            corners = torch.where(sel, a_hi.unsqueeze(1), a_lo.unsqueeze(1)) - origin  # (P,8,3)
            if rot is not None:  # world -> cube frame, then the AABB there
                corners = corners @ rot
                cmin, cmax = corners.amin(1), corners.amax(1)
                corners = torch.where(sel, cmax.unsqueeze(1), cmin.unsqueeze(1))
            za = torch.einsum("pcj,kj->kpc", corners, axes[:, 0])  # (6, P, 8)
            yb = torch.einsum("pcj,kj->kpc", corners, axes[:, 1])
            xr = torch.einsum("pcj,kj->kpc", corners, axes[:, 2])
            behind = (za < delta).all(-1)  # (6, P)
            zs = torch.clamp(za, min=delta)  # clip the (cube-frame axis-aligned) box
            u, v = c + f * xr / zs, c + f * yb / zs
            m = 1.5
            umin, umax = u.amin(-1) - m, u.amax(-1) + m
            vmin, vmax = v.amin(-1) - m, v.amax(-1) + m
            cu = (start[None, :, None] <= umax[:, None]) & \
                (start[None, :, None] + ts - 1 >= umin[:, None])  # (6, T, P)
            cv = (start[None, :, None] <= vmax[:, None]) & \
                (start[None, :, None] + ts - 1 >= vmin[:, None])
            mask = cv[:, :, None, :] & cu[:, None, :, :] & ~behind[:, None, None, :]
            K = max(int(mask.sum(-1).max()) if P else 0, 1)
            order = torch.where(mask, torch.arange(P), P).sort(-1)[0][..., :K]
            valid = order < P
            out.append((torch.clamp(order, max=max(P - 1, 0)), valid))
        return out

    def render_cubemap(self, position, rotation: Tensor | None = None, face_size: int = 256, *,
                       faces: Tensor | None = None, t: float = 0.0,
                       weather: str | Weather = "clear_noon") -> dict[str, Tensor]:
        """Render a cubemap at ``position`` (world, metres).

        Args:
            position: ``(3,)`` cube centre in the world frame.
            rotation: ``(3, 3)`` cube frame -> world (default identity: the front face looks
                north along the road, down is gravity).
            face_size: ``F``.
            faces: optional ``(6,)`` bool mask of the faces to render; the others are left at
                rgb 0, depth 0 and label 255 (``IGNORE_INDEX``).
            t: time (s) for the moving objects.
            weather: a :data:`WEATHERS` name or a :class:`Weather`.

        Returns:
            dict with ``rgb (1, 6, 3, F, F)`` float32, ``depth (1, 6, F, F)`` planar depth in
            metres (along each face's axis; ``self.far`` for the sky), ``labels (1, 6, F, F)``
            int64, and ``range (1, 6, F, F)`` (``self.far`` for the sky).
        """
        w = _get_weather(weather)
        F = int(face_size)
        origin = torch.as_tensor(position, dtype=torch.float32).reshape(3)
        rot = None if rotation is None else torch.as_tensor(rotation, dtype=torch.float32)
        axes = face_axes(torch.float32)  # (6, 3 [a, b, r], 3) cube frame
        if rot is not None:
            axes = axes @ rot.T
        rays = self.cubemap_rays(F, rot)  # (6, F, F, 3)
        sel = torch.ones(6, dtype=torch.bool) if faces is None else torch.as_tensor(faces).bool()
        fidx = torch.nonzero(sel).flatten()
        nf = len(fidx)
        ts = min(self.tile, F)
        T = -(-F // ts)
        geo = self.geometry(t)
        cands = self._tile_candidates(geo, origin, rot, F, ts, T)
        cands = [(i[fidx].reshape(nf * T * T, -1), v[fidx].reshape(nf * T * T, -1))
                 for i, v in cands]
        # gather rays into tiles (replicating the last row/column where F % ts != 0)
        a = torch.arange(T * ts)
        rc = torch.clamp(a, max=F - 1).view(T, ts)
        rows = rc.view(T, 1, ts, 1).expand(T, T, ts, ts)
        cols = rc.view(1, T, 1, ts).expand(T, T, ts, ts)
        flat = (rows * F + cols).reshape(T * T, ts * ts)  # (T*T, R)
        tr = rays[fidx].reshape(nf, F * F, 3)[:, flat]  # (nf, T*T, R, 3)
        tr = tr.reshape(nf * T * T, ts * ts, 3)
        # tiles sorted by their candidate count, in groups, each padded to its own maximum
        # (the per-ray arithmetic is the same, so the result does not depend on the grouping)
        G = tr.shape[0]
        cost = sum(v.sum(-1) * wgt for (_, v), wgt in zip(cands, (3, 2, 1)))
        order = torch.argsort(cost, stable=True)
        res = [torch.empty(G, ts * ts)] + [torch.empty(G, ts * ts, dtype=dt)
                                           for dt in (torch.int64, torch.int64, torch.bool)]
        ngroups = min(self.groups, G)
        for grp in torch.tensor_split(order, ngroups):
            if grp.numel() == 0:
                continue
            sub = []
            for i, v in cands:
                k = max(int(v[grp].sum(-1).max()), 1)
                sub.append((i[grp, :k], v[grp, :k]))
            rg = tr[grp]
            out = self._closest(origin.expand_as(rg), rg, geo, sub)
            for r, x in zip(res, out):
                r[grp] = x
        tmin, kind, idx, cap = res
        # back to texel order
        ii = torch.arange(F)
        back = ((ii.view(F, 1) // ts) * T + ii.view(1, F) // ts) * (ts * ts) + \
            (ii.view(F, 1) % ts) * ts + ii.view(1, F) % ts  # (F, F)
        back = (torch.arange(nf).view(nf, 1, 1) * (T * T * ts * ts) + back).reshape(-1)
        tmin, kind, idx, cap = (x.reshape(-1)[back] for x in (tmin, kind, idx, cap))
        d = rays[fidx].reshape(-1, 3)
        sh = self._shade(origin.expand_as(d), d, tmin, kind, idx, cap, geo, w)
        acomp = (d * axes[fidx, 0].repeat_interleave(F * F, 0)).sum(-1)
        depth = torch.where(sh["hit"], sh["range"] * acomp, torch.full_like(acomp, self.far))
        rgb = torch.zeros(6, F, F, 3)
        dep = torch.zeros(6, F, F)
        rng = torch.zeros(6, F, F)
        lab = torch.full((6, F, F), 255, dtype=torch.int64)
        rgb[fidx] = sh["rgb"].reshape(nf, F, F, 3)
        dep[fidx] = depth.reshape(nf, F, F)
        rng[fidx] = sh["range"].reshape(nf, F, F)
        lab[fidx] = sh["labels"].reshape(nf, F, F)
        return {"rgb": rgb.permute(0, 3, 1, 2).unsqueeze(0).contiguous(),
                "depth": dep.unsqueeze(0), "labels": lab.unsqueeze(0),
                "range": rng.unsqueeze(0)}
