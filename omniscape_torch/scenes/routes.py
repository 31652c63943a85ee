"""Rides through the town's layouts (`town.LAYOUTS`): a `ride.Route` that stays
in the right-hand lanes of the layout's streets, for ``omniscape-torch generate --town N``.

* 1, main street: from the south end in the right-hand lane, heading north, weaving between
  the lanes (S-bends of two opposite arcs, radius 60 to 120 m), about 140 m; the road is
  straight, so the leans stay moderate (a few degrees at 10 m/s).
* 2, crossroads: north in the main street's right-hand lane, a right turn (radius 6 to 8 m) at
  the crossing into the cross street's eastbound lane, then east.
* 3, blocks: round the block between the streets, four right turns (radius 6 to 8 m) at the
  corners, then north again.

A turn's arcs are joined to the straights by the route's clothoids, which move the path a little
off the pure arc's; the straights are sized with the turn's displacement measured on the route
itself, so the path leaves each turn on its new lane's centre line. Lanes are
``LANE = 1.75`` m off a street's centre line (world frame: x east, y down, z north).
"""

from __future__ import annotations

import math

import numpy as np

from . import ride as _ride

__all__ = ["LANE", "route"]

#: A lane's centre line, metres from its street's centre line.
LANE = 1.75


def _main_street(seed: int, half_length: float) -> _ride.Route:
    rng = np.random.default_rng([seed, 7])
    segments = [_ride.straight(10.0)]
    side = -1.0  # first to the left lane, then back
    while sum(seg.length for seg in segments) < 2 * half_length - 60.0:
        radius = float(rng.uniform(60.0, 120.0))
        # two opposite arcs of angle t shift the path sideways by 2 R (1 - cos t) = one lane
        turn = math.degrees(math.acos(1 - 2 * LANE / (2 * radius)))
        segments += [_ride.arc(radius, side * turn), _ride.arc(radius, -side * turn),
                     _ride.straight(float(rng.uniform(8.0, 20.0)))]
        side = -side
    return _ride.Route(segments, start=(LANE, 0.0, -half_length + 5.0), heading_deg=0.0)


def _turn(radius: float) -> tuple[float, float]:
    """How far a right turn of ``radius`` metres (90 degrees, between straights, with the
    route's clothoids) moves the path forward and to the right of its entry heading, beyond
    the straights' own lengths."""
    run = 30.0
    r = _ride.Route([_ride.straight(run), _ride.arc(radius, 90.0), _ride.straight(run)])
    x, _, z = r.position[-1]   # heading north (z), turning east (x)
    return float(z - run), float(x - run)


def _right_turns(start: tuple[float, float], lanes: list[float], radius: list[float],
                 last: float) -> _ride.Route:
    """From ``start = (x, z)`` heading north, right turns into the lanes ``lanes`` (each the
    coordinate of the next lane's centre line along the heading before its turn), ``last``
    metres after the last one."""
    heading = 0                          # degrees, CARLA yaw: 0 north, 90 east
    pos = np.array(start, dtype=float)   # (x, z)
    segments = []
    for lane, r in zip(lanes, radius):
        fwd = np.array([math.sin(math.radians(heading)), math.cos(math.radians(heading))])
        right = np.array([fwd[1], -fwd[0]])
        f, s = _turn(r)
        length = lane - float(pos @ fwd) - f
        if length < 10.0:
            raise ValueError(f"lanes: a straight of {length:.1f} m before a turn (10 m at least)")
        segments += [_ride.straight(length), _ride.arc(r, 90.0)]
        pos = pos + (length + f) * fwd + s * right
        heading = (heading + 90) % 360
    segments.append(_ride.straight(last))
    return _ride.Route(segments, start=(start[0], 0.0, start[1]), heading_deg=0.0)


def route(layout: int, seed: int, half_length: float = 80.0) -> _ride.Route:
    """The ride through ``layout`` (1 main street, 2 crossroads, 3 blocks) of a town of
    ``2 * half_length`` metres, varied by ``seed`` (S-bends, turn radii)."""
    if layout == 1:
        return _main_street(seed, half_length)
    rng = np.random.default_rng([seed, 7, layout])
    if layout == 2:
        # north in the east lane (x = 1.75), right into the cross street's eastbound lane
        return _right_turns((LANE, -half_length + 5.0), [-LANE],
                            [float(rng.uniform(6.0, 8.0))], half_length - 10.0)
    if layout == 3:
        # round the block x in [0, 70], z in [-40, 40], clockwise seen from above
        radii = [float(rng.uniform(6.0, 8.0)) for _ in range(4)]
        lanes = [40.0 - LANE, 70.0 - LANE, 40.0 - LANE, -LANE]
        # along the headings: north to z = 38.25, east to x = 68.25, south to z = -38.25
        # (the coordinate along "south" is -z), west to x = 1.75 (along "west": -x)
        return _right_turns((LANE, -25.0), lanes, radii, 50.0)
    raise ValueError(f"layout: expected 1, 2 or 3, got {layout!r}")
