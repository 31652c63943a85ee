"""The town's streets and what lines them: the street plans (`LAYOUTS`, `layout_streets`), the
ground as cells of one class each, and the random placement of the objects (`place_objects`).

World frame (metres): x east, y down, z north; the ground is the plane ``y = 0``. Streets share
one cross-section, ``across`` metres from their centre line: two driving lanes
(``|across| < LANE_EDGE``, 3.5), a parking strip on each side (``LANE_EDGE < |across| <
ROAD_HALF``, 5.25), sidewalks (``ROAD_HALF < |across| < SIDEWALK_HALF``, 8.5), and beyond them
buildings, walls, fences and open lots (ground labelled ``Other``). The road markings are
painted by the shading (`omniscape_torch.render.kernels.town`, whose `LANE_EDGE` and
`LINE_HALF` these are).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..render.kernels.town import LANE_EDGE, LINE_HALF

__all__ = ["CLASS_IDS", "CROSSING_BAND", "LANE_EDGE", "LAYOUTS", "LINE_HALF", "ROAD_HALF",
           "SIDEWALK_HALF", "Street", "layout_streets", "place_objects"]

CLASS_IDS = {name: i for i, name in enumerate(
    ("Unlabeled", "Building", "Fence", "Other", "Pedestrian", "Pole", "RoadLine", "Road",
     "Sidewalk", "Vegetation", "Vehicle", "Wall", "TrafficSign"))}
_C = CLASS_IDS

# Street cross-section (|across|, metres).
ROAD_HALF = 5.25
SIDEWALK_HALF = 8.5
#: Half-width of the band around a crossing street kept free of a street's buildings, metres.
CROSSING_BAND = SIDEWALK_HALF + 1.0


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
    """The streets of ``layout`` (`LAYOUTS`) for a town of ``length`` metres."""
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



def place_objects(streets: tuple[Street, ...], length: float, far: float,
                  g: torch.Generator) -> dict:
    """The town's objects along ``streets``, drawn from ``g``: buildings with walls, fences or
    open lots between them, street lamps, trees, bins and parked vehicles on each side of each
    street, traffic signs on the main street (the first), and the movers (vehicles in the lanes,
    pedestrians on the sidewalks of the north-south streets); the ground's cells out to
    ``far + length`` metres.

    Returns:
        dict of the `omniscape_torch.scenes.Town` attributes ``boxes_lo``, ``boxes_hi``,
        ``boxes_label``, ``boxes_colour``, ``boxes_mover``, ``boxes_instance``, ``cyl`` and
        ``cyl_*``, ``sph`` and ``sph_*``, ``movers``, ``instance_label``, ``lamps`` (``(L, 3)``
        float32) and ``ground`` (``_ground_cells``).
    """
    out: dict = {}
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

    for si, st in enumerate(streets):
        bands = _bands(st, streets)
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
    main = streets[0]
    bands = _bands(main, streets)
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
    L2 = length / 2
    for st in streets:
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
    out["boxes_lo"] = torch.tensor([b[0] for b in boxes], dtype=f32)
    out["boxes_hi"] = torch.tensor([b[1] for b in boxes], dtype=f32)
    out["boxes_label"] = torch.tensor([b[2] for b in boxes], dtype=torch.int64)
    out["boxes_colour"] = torch.tensor([b[3] for b in boxes], dtype=f32)
    out["boxes_mover"] = torch.tensor([b[4] for b in boxes], dtype=torch.int64)
    out["boxes_instance"] = torch.tensor([b[5] for b in boxes], dtype=torch.int64)
    out["cyl"] = torch.tensor([c[:5] for c in cyls], dtype=f32)
    out["cyl_label"] = torch.tensor([c[5] for c in cyls], dtype=torch.int64)
    out["cyl_colour"] = torch.tensor([c[6] for c in cyls], dtype=f32)
    out["cyl_mover"] = torch.tensor([c[7] for c in cyls], dtype=torch.int64)
    out["cyl_instance"] = torch.tensor([c[8] for c in cyls], dtype=torch.int64)
    out["sph"] = torch.tensor([c[:4] for c in sphs], dtype=f32)
    out["sph_label"] = torch.tensor([c[4] for c in sphs], dtype=torch.int64)
    out["sph_colour"] = torch.tensor([c[5] for c in sphs], dtype=f32)
    out["sph_mover"] = torch.tensor([c[6] for c in sphs], dtype=torch.int64)
    out["sph_instance"] = torch.tensor([c[7] for c in sphs], dtype=torch.int64)
    out["movers"] = torch.tensor(movers, dtype=torch.float64).reshape(-1, 3)
    # the class of each instance id (0: none, Unlabeled)
    out["instance_label"] = torch.zeros(instances[0] + 1, dtype=torch.int64)
    for table, label in ((out["boxes_instance"], out["boxes_label"]),
                         (out["cyl_instance"], out["cyl_label"]),
                         (out["sph_instance"], out["sph_label"])):
        out["instance_label"][table[table > 0]] = label[table > 0]
    out["lamps"] = torch.tensor(lamps, dtype=f32)
    out["ground"] = _ground_cells(streets, far + length)
    return out
