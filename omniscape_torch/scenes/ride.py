"""A motorcycle ride (or a car's drive): a route, a speed profile and a plausible attitude
(lean or body roll, pitch, yaw).

The OmniScape dataset mounts its cameras on a motorcycle and reports, per frame, the vehicle's
location, rotation, velocity, angular velocity and acceleration, with the statistics of yaw,
pitch and roll in the paper's Table I. This module makes such a ride without a simulator:

* `Route`: a smooth path of straights and circular arcs joined by clothoid transitions
  (curvature ramps linearly over ``transition`` metres, so heading, lean and yaw rate stay
  continuous), with an optional road grade per segment (also ramped).
* a speed profile along it: accelerate to ``max_speed``, slow down before curves so that the
  lateral acceleration ``v^2 kappa`` never exceeds ``max_lateral_acceleration`` (nor
  ``g tan(max_lean)``), brake to a stop at the end of the route (forward-backward passes with
  the ``acceleration`` and ``deceleration`` limits; piecewise-constant acceleration, so location,
  speed and acceleration are exact, not integrated numerically).
* `simulate`: per-frame state at ``fps``. Yaw is the path's heading. Roll (lean) tracks
  the steady-turn lean ``atan(a_lat / g)`` (``a_lat = v^2 kappa cos(grade)``, the horizontal
  centripetal acceleration; an ideal thin-tyre motorcycle) through a critically damped
  second-order lag (natural frequency ``roll_frequency`` Hz): a motorcycle cannot change lean
  instantly, and its roll rate stays continuous. Pitch is the road's grade angle plus a
  suspension pitch ``pitch_gain * a_long`` (nose down when braking, up when accelerating)
  through a second-order lag (``pitch_frequency`` Hz, damping ``pitch_damping``). Small
  band-limited noise (road roughness, rider motion; ``roll_noise``, ``pitch_noise`` degrees,
  reproducible by ``seed`` or ``generator``) is added to the lag targets, so the attitude stays
  smooth.
* a car (``simulate(..., vehicle="car")``; `CAR` holds a town car's settings): no lean, the
  body rolls out of the turn instead, ``roll_gain_deg`` degrees per m/s^2 of lateral
  acceleration (its roll gradient: 0.5 deg per m/s^2 is about 5 degrees per g, a passenger
  car's), through the same lag; the lateral acceleration is limited by
  ``max_lateral_acceleration`` alone (no lean limit). Pitch, yaw and the speed profile are
  the motorcycle's, with the car's numbers.

Frames and units
----------------
World frame (inside this module and `camera_rotation`): ``x`` east, ``y`` down, ``z``
north, metres; the rig convention of ``DESIGN.md``/``presets.py`` (x right, y down, z forward)
for a vehicle heading north. Angles are radians inside the code.

Outputs of `simulate` are in **CARLA's API** frame and units: Unreal's left-handed
``x`` forward (north here), ``y`` right (east), ``z`` up, in **metres** (the Python API's
``carla.Location``; Unreal itself uses centimetres), so ``(x, y, z)_world = (y, -z, x)_carla``
(`carla_to_world`, `world_to_carla`). Rotations are **degrees**, CARLA's
``carla.Rotation``: roll positive = right side down (leaning right), pitch positive = nose up,
yaw positive = turning right (clockwise seen from above; yaw 0 faces north, CARLA +x, yaw 90
east), yaw wrapped to ``[-180, 180)`` like ``get_transform()``. Velocity (m/s) and
acceleration (m/s^2, kinematic, gravity not included) are world vectors in CARLA axes like
``get_velocity()``/``get_acceleration()``. Angular velocity is in deg/s in CARLA axes like
``get_angular_velocity()``: the vector ``w`` with ``dp/dt = w x (p - c)`` for a point ``p`` of
the body computed with the ordinary cross-product formula in CARLA coordinates. For a right
turn ``w_z = + yaw rate``; leaning right gives ``w_x = - roll rate`` and pitching up
``w_y = - pitch rate`` (Unreal's left-handed axes). Euler-angle rates are given as well
(``rotation_rate``). A CARLA attitude converts to the rig's rotation with
``yaw_pitch_roll_to_matrix(radians(yaw), radians(pitch), radians(roll))`` (presets.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from ..cameras.presets import yaw_pitch_roll_to_matrix

__all__ = [
    "CAR",
    "GRAVITY",
    "ROTATION_ORDER",
    "VEHICLES",
    "Route",
    "Segment",
    "arc",
    "camera_rotation",
    "carla_to_world",
    "random_route",
    "records",
    "simulate",
    "straight",
    "table_one",
    "world_to_carla",
]

#: Standard gravity, m/s^2.
GRAVITY = 9.81

#: ``simulate``'s settings for a car in town (``simulate(route, fps, **CAR)``): 36 km/h at
#: most, 2 m/s^2 speeding up and 3 m/s^2 braking, at most 2.5 m/s^2 of lateral acceleration
#: (a comfortable drive), body roll 0.5 deg and suspension pitch 0.2 deg per m/s^2 (a
#: passenger car: about 5 and 2 degrees per g), road roughness 0.1 deg on each.
CAR = MappingProxyType({
    "vehicle": "car", "max_speed": 10.0, "acceleration": 2.0, "deceleration": 3.0,
    "max_lateral_acceleration": 2.5, "roll_gain_deg": 0.5, "roll_frequency": 1.5,
    "pitch_gain_deg": 0.2, "roll_noise_deg": 0.1, "pitch_noise_deg": 0.1})

#: The vehicles `simulate` knows.
VEHICLES = ("motorcycle", "car")

#: Order of the three angles in ``simulate(...)["rotation"]`` and ``["rotation_rate"]``.
ROTATION_ORDER = ("roll", "pitch", "yaw")

# (x, y, z)_world = P @ (x, y, z)_carla; det P = -1 (CARLA's frame is left-handed).
_P = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def carla_to_world(v: Tensor | np.ndarray) -> Tensor:
    """``(..., 3)`` CARLA-axis vectors (x fwd/north, y right/east, z up) to world (x east,
    y down, z north). Same units in and out."""
    v = torch.as_tensor(v)
    return torch.stack([v[..., 1], -v[..., 2], v[..., 0]], dim=-1)


def world_to_carla(v: Tensor | np.ndarray) -> Tensor:
    """Inverse of `carla_to_world`."""
    v = torch.as_tensor(v)
    return torch.stack([v[..., 2], v[..., 0], -v[..., 1]], dim=-1)


# --------------------------------------------------------------------------------------------
# Route
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Segment:
    """A piece of route: ``length`` metres along the path at constant ``curvature`` (1/m,
    positive = turning right, clockwise from above) and ``grade`` (path angle, radians,
    positive = uphill)."""

    length: float
    curvature: float = 0.0
    grade: float = 0.0

    def __post_init__(self):
        for name in ("length", "curvature", "grade"):
            value = getattr(self, name)
            if (isinstance(value, bool) or not isinstance(value, (int, float))
                    or not math.isfinite(value)):
                raise ValueError(f"{name}: expected a finite number, got {value!r}")
        if not self.length > 0:
            raise ValueError(f"length: expected > 0 metres, got {self.length}")
        if abs(self.grade) >= math.pi / 4:
            raise ValueError(f"grade: expected |grade| < 45 degrees, got "
                             f"{math.degrees(self.grade):.1f} deg")


def straight(length: float, *, grade_deg: float = 0.0) -> Segment:
    """A straight of ``length`` metres; ``grade_deg`` the road's slope angle in degrees."""
    return Segment(float(length), 0.0, math.radians(grade_deg))


def arc(radius: float, angle_deg: float, *, grade_deg: float = 0.0) -> Segment:
    """A circular arc of ``radius`` metres turning by ``angle_deg`` degrees (positive = right,
    negative = left; more than 360 loops)."""
    if not radius > 0 or not math.isfinite(radius):
        raise ValueError(f"radius: expected a positive finite number, got {radius!r}")
    if angle_deg == 0:
        raise ValueError("angle_deg: a zero-angle arc; use straight()")
    sign = 1.0 if angle_deg > 0 else -1.0
    return Segment(radius * math.radians(abs(angle_deg)), sign / radius,
                   math.radians(grade_deg))


def _ramped(bounds: np.ndarray, values: np.ndarray, half: np.ndarray, s: np.ndarray
            ) -> np.ndarray:
    """Piecewise-constant ``values`` on ``[bounds[j], bounds[j+1])`` with each inner step
    replaced by a linear ramp over ``[b - half, b + half]`` (integral preserved)."""
    out = np.full_like(s, values[0])
    for j in range(1, len(values)):
        b, h, jump = bounds[j], half[j - 1], values[j] - values[j - 1]
        if h > 0:
            out += jump * np.clip((s - (b - h)) / (2 * h), 0.0, 1.0)
        else:
            out += jump * (s >= b)
    return out


@dataclass
class Route:
    """A planar-heading route with grades, sampled every ``ds`` metres of path length.

    Args:
        segments: the `Segment` list, in order.
        transition: length in metres of the linear curvature (and grade) ramps centred on each
            joint (clothoids); clipped to the shorter neighbour segment. 0 for none.
        ds: sampling step of the path, metres.
        start: world location ``(x east, y down, z north)`` of the start, metres.
        heading_deg: heading at the start, degrees (CARLA yaw; 0 = north, 90 = east).
    """

    segments: Sequence[Segment]
    transition: float = 10.0
    ds: float = 0.05
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    heading_deg: float = 0.0
    s: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        self.segments = tuple(self.segments)
        if not self.segments or not all(isinstance(g, Segment) for g in self.segments):
            raise ValueError("segments: expected a non-empty sequence of Segment")
        if not self.transition >= 0:
            raise ValueError(f"transition: expected >= 0 metres, got {self.transition}")
        if not self.ds > 0:
            raise ValueError(f"ds: expected > 0 metres, got {self.ds}")
        lengths = np.array([g.length for g in self.segments])
        bounds = np.concatenate([[0.0], np.cumsum(lengths)])
        half = np.minimum(0.5 * self.transition,
                          0.5 * np.minimum(lengths[:-1], lengths[1:]))
        half = np.maximum(half, 1e-6)     # a step: a 2-micrometre ramp between two nodes
        self.length = float(bounds[-1])
        n = max(2, int(math.ceil(self.length / self.ds)) + 1)
        s = np.linspace(0.0, self.length, n)
        # Nodes at the ramp ends so that curvature is exactly piecewise linear between nodes.
        kinks = np.concatenate([bounds[1:-1] - half, bounds[1:-1] + half])
        s = np.unique(np.concatenate([s, kinks[(kinks > 0) & (kinks < self.length)]]))
        self.s = s
        self._bounds, self._half = bounds, half
        self._kappa_values = np.array([g.curvature for g in self.segments])
        self._grade_values = np.array([g.grade for g in self.segments])
        self.kappa = _ramped(bounds, self._kappa_values, half, s)
        self.grade = _ramped(bounds, self._grade_values, half, s)
        dsn = np.diff(s)
        psi0 = math.radians(self.heading_deg)
        self.heading = psi0 + np.concatenate(
            [[0.0], np.cumsum(0.5 * dsn * (self.kappa[:-1] + self.kappa[1:]))])
        # Position: Simpson's rule per cell (heading quadratic, grade linear in each cell).
        mid_psi = self.heading[:-1] + 0.125 * dsn * (3 * self.kappa[:-1] + self.kappa[1:])
        mid_grade = 0.5 * (self.grade[:-1] + self.grade[1:])
        t0 = self._tangent(self.heading[:-1], self.grade[:-1])
        t1 = self._tangent(self.heading[1:], self.grade[1:])
        tm = self._tangent(mid_psi, mid_grade)
        steps = (dsn / 6)[:, None] * (t0 + 4 * tm + t1)
        self.position = np.asarray(self.start, dtype=np.float64) + np.concatenate(
            [np.zeros((1, 3)), np.cumsum(steps, axis=0)])

    @staticmethod
    def _tangent(psi: np.ndarray, grade: np.ndarray) -> np.ndarray:
        """World unit tangent (x east, y down, z north) at heading ``psi``, grade angle."""
        c = np.cos(grade)
        return np.stack([c * np.sin(psi), -np.sin(grade), c * np.cos(psi)], axis=-1)

    def _cell(self, s: np.ndarray):
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, self.length)
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 2)
        return s, i, s - self.s[i], self.s[i + 1] - self.s[i]

    def curvature_at(self, s) -> np.ndarray:
        """Curvature (1/m, positive = right) at path length ``s`` (clipped to the route)."""
        s, i, u, h = self._cell(s)
        return self.kappa[i] + (self.kappa[i + 1] - self.kappa[i]) * (u / h)

    def grade_at(self, s) -> np.ndarray:
        """Path (grade) angle in radians at ``s``."""
        s, i, u, h = self._cell(s)
        return self.grade[i] + (self.grade[i + 1] - self.grade[i]) * (u / h)

    def grade_rate_at(self, s) -> np.ndarray:
        """``d grade / ds`` (rad/m) at ``s``."""
        s, i, u, h = self._cell(s)
        return (self.grade[i + 1] - self.grade[i]) / h

    def heading_at(self, s) -> np.ndarray:
        """Heading (radians, unwrapped; 0 = north, positive = clockwise from above) at ``s``."""
        s, i, u, h = self._cell(s)
        dk = (self.kappa[i + 1] - self.kappa[i]) / h
        return self.heading[i] + self.kappa[i] * u + 0.5 * dk * u * u

    def tangent_at(self, s) -> np.ndarray:
        """World unit tangent ``(..., 3)`` at ``s``."""
        return self._tangent(self.heading_at(s), self.grade_at(s))

    def position_at(self, s) -> np.ndarray:
        """World position ``(..., 3)`` (x east, y down, z north; metres) at ``s``."""
        s, i, u, h = self._cell(s)
        dk = (self.kappa[i + 1] - self.kappa[i]) / h
        dg = (self.grade[i + 1] - self.grade[i]) / h

        def tangent(v):
            psi = self.heading[i] + self.kappa[i] * v + 0.5 * dk * v * v
            return self._tangent(psi, self.grade[i] + dg * v)

        simpson = (u / 6)[..., None] * (tangent(0 * u) + 4 * tangent(0.5 * u) + tangent(u))
        return self.position[i] + simpson

    def max_abs_curvature(self) -> np.ndarray:
        """``max |kappa|`` over the two cells around each node (for the speed limit)."""
        k = np.abs(self.kappa)
        out = k.copy()
        out[1:] = np.maximum(out[1:], k[:-1])
        out[:-1] = np.maximum(out[:-1], k[1:])
        return out


def random_route(seed: int = 0, *, turns: int = 8, transition: float = 10.0,
                 max_grade_deg: float = 3.0, ds: float = 0.05) -> Route:
    """A reproducible route of ``turns`` arcs (radius 15 to 120 m, 20 to 120 degrees, either
    side) between straights of 20 to 150 m, grades within ``max_grade_deg``."""
    rng = np.random.default_rng(seed)
    segments = [straight(float(rng.uniform(40, 150)),
                         grade_deg=float(rng.uniform(-max_grade_deg, max_grade_deg)))]
    for _ in range(turns):
        side = 1.0 if rng.random() < 0.5 else -1.0
        segments.append(arc(float(rng.uniform(15, 120)), side * float(rng.uniform(20, 120)),
                            grade_deg=float(rng.uniform(-max_grade_deg, max_grade_deg))))
        segments.append(straight(float(rng.uniform(20, 150)),
                                 grade_deg=float(rng.uniform(-max_grade_deg, max_grade_deg))))
    return Route(segments, transition=transition, ds=ds)


# --------------------------------------------------------------------------------------------
# Speed profile
# --------------------------------------------------------------------------------------------

@dataclass
class _Profile:
    s: np.ndarray       # nodes (m)
    v: np.ndarray       # speed at nodes (m/s)
    a: np.ndarray       # constant acceleration in each cell (m/s^2)
    t: np.ndarray       # time at nodes (s)

    def at(self, time: np.ndarray):
        """``(s, v, a)`` at times ``time``; at rest at the end after the last node."""
        time = np.asarray(time, dtype=np.float64)
        i = np.clip(np.searchsorted(self.t, time, side="right") - 1, 0, len(self.t) - 2)
        tau = np.clip(time - self.t[i], 0.0, self.t[i + 1] - self.t[i])
        v = self.v[i] + self.a[i] * tau
        s = self.s[i] + self.v[i] * tau + 0.5 * self.a[i] * tau * tau
        a = self.a[i].copy()
        end = time >= self.t[-1]
        s = np.where(end, self.s[-1], np.minimum(s, self.s[i + 1]))
        v = np.where(end, self.v[-1], np.maximum(v, 0.0))
        a = np.where(end & (self.v[-1] == 0), 0.0, a)
        return s, v, a


def _speed_profile(route: Route, *, max_speed: float, acceleration: float,
                   deceleration: float, max_lateral: float, start_speed: float,
                   end_speed: float | None) -> _Profile:
    s = route.s
    dsn = np.diff(s)
    kmax = route.max_abs_curvature()
    with np.errstate(divide="ignore"):
        vlim = np.minimum(max_speed, np.sqrt(max_lateral / kmax))
    v = vlim.copy()
    v[0] = min(start_speed, vlim[0])
    for i in range(len(s) - 1):                                   # accelerate
        v[i + 1] = min(v[i + 1], math.sqrt(v[i] ** 2 + 2 * acceleration * dsn[i]))
    if end_speed is not None:
        v[-1] = min(v[-1], end_speed)
    for i in range(len(s) - 2, -1, -1):                           # brake ahead of limits
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * deceleration * dsn[i]))
    if v[0] == 0 and v[1] == 0:
        raise ValueError("the speed profile never leaves the start: check the limits")
    a = (v[1:] ** 2 - v[:-1] ** 2) / (2 * dsn)
    dt = 2 * dsn / (v[:-1] + v[1:])
    t = np.concatenate([[0.0], np.cumsum(dt)])
    return _Profile(s, v, a, t)


# --------------------------------------------------------------------------------------------
# Simulation
# --------------------------------------------------------------------------------------------

def _second_order(target: np.ndarray, h: float, omega: float, zeta: float,
                  x0: float) -> tuple[np.ndarray, np.ndarray]:
    """``x'' = omega^2 (u - x) - 2 zeta omega x'`` on a grid of step ``h``, ``u`` linear
    between samples (RK4 with the input interpolated); returns ``(x, x')`` at the samples."""
    n = len(target)
    x = np.empty(n)
    xd = np.empty(n)
    x[0], xd[0] = x0, 0.0
    w2, c = omega * omega, 2 * zeta * omega
    xi, vi = x0, 0.0
    for k in range(n - 1):
        u0, u1 = target[k], target[k + 1]
        um = 0.5 * (u0 + u1)
        a1x, a1v = vi, w2 * (u0 - xi) - c * vi
        a2x, a2v = vi + 0.5 * h * a1v, w2 * (um - xi - 0.5 * h * a1x) - c * (vi + 0.5 * h * a1v)
        a3x, a3v = vi + 0.5 * h * a2v, w2 * (um - xi - 0.5 * h * a2x) - c * (vi + 0.5 * h * a2v)
        a4x, a4v = vi + h * a3v, w2 * (u1 - xi - h * a3x) - c * (vi + h * a3v)
        xi += h / 6 * (a1x + 2 * a2x + 2 * a3x + a4x)
        vi += h / 6 * (a1v + 2 * a2v + 2 * a3v + a4v)
        x[k + 1], xd[k + 1] = xi, vi
    return x, xd


#: White noise is drawn in blocks of this many substeps (two channels: roll, pitch), one
#: ``torch.randn`` call per block, so sample ``i`` is the same however many are drawn: a
#: ride's frame ``k`` does not depend on its number of frames (``torch.randn`` of a larger
#: size is not an extension of a smaller one).
NOISE_BLOCK = 4096


def _white_noise(n: int, generator: torch.Generator) -> np.ndarray:
    """``(n, 2)`` standard normal samples (roll, pitch), a prefix of the same stream for
    every ``n`` (see `NOISE_BLOCK`)."""
    blocks = [torch.randn(NOISE_BLOCK, 2, generator=generator, dtype=torch.float64)
              for _ in range(-(-n // NOISE_BLOCK))]
    return torch.cat(blocks)[:n].numpy()


def _noise(white: np.ndarray, h: float, std_rad: float, correlation: float) -> np.ndarray:
    """Stationary Ornstein-Uhlenbeck noise of standard deviation ``std_rad`` driven by
    ``white (n,)``."""
    n = len(white)
    if std_rad == 0:
        return np.zeros(n)
    rho = math.exp(-h / correlation)
    scale = math.sqrt(1 - rho * rho)
    out = np.empty(n)
    acc = white[0]
    out[0] = acc
    for k in range(1, n):
        acc = rho * acc + scale * white[k]
        out[k] = acc
    return std_rad * out


def _check_positive(**values):
    for name, value in values.items():
        if (isinstance(value, bool) or not isinstance(value, (int, float))
                or not math.isfinite(value) or not value > 0):
            raise ValueError(f"{name}: expected a positive finite number, got {value!r}")


def simulate(route: Route, fps: float = 10.0, duration: float | None = None, *,
             frames: int | None = None, seed: int | None = 0,
             generator: torch.Generator | None = None,
             max_speed: float = 15.0, acceleration: float = 2.5, deceleration: float = 4.0,
             max_lateral_acceleration: float = 4.0, max_lean_deg: float = 45.0,
             start_speed: float = 0.0, end_speed: float | None = 0.0,
             roll_frequency: float = 1.0, pitch_frequency: float = 1.5,
             pitch_damping: float = 0.7, pitch_gain_deg: float = 0.4,
             roll_noise_deg: float = 0.3, pitch_noise_deg: float = 0.15,
             noise_correlation: float = 0.5, substeps: int | None = None,
             vehicle: str = "motorcycle", roll_gain_deg: float = 0.5,
             dtype: torch.dtype = torch.float64) -> dict[str, Tensor]:
    """Ride ``route`` (or drive it: ``vehicle="car"``) and return the per-frame state, in
    CARLA's API frame and units.

    Args:
        route: the `Route`.
        fps: frames per second.
        duration: seconds to simulate (``frames = floor(duration * fps) + 1``, frame 0 at
            t = 0); or give ``frames``. Default: until the motorcycle stops at the route's end.
        seed: the noise's random source; same seed, same ride, and frame ``k`` is the same
            whatever ``frames`` or ``duration`` (a longer ride extends a shorter one).
        generator: the noise's random source instead of ``seed`` (it wins over ``seed``).
        max_speed: cruising speed, m/s.
        acceleration: longitudinal limit when speeding up, m/s^2 (a positive number).
        deceleration: longitudinal limit when slowing down, m/s^2 (a positive number).
        max_lateral_acceleration: limit on ``v^2 |kappa|``, m/s^2; a motorcycle's also capped
            at ``g tan(max_lean_deg)``.
        start_speed: speed at the start, m/s (0: from rest).
        end_speed: speed at the route's end (0: stop there; None: no constraint; past the end
            it stays there).
        roll_frequency: natural frequency (Hz) of the critically damped lean (or body roll)
            lag.
        pitch_frequency: the suspension pitch lag's natural frequency, Hz.
        pitch_damping: the suspension pitch lag's damping ratio.
        pitch_gain_deg: suspension pitch per m/s^2 of longitudinal acceleration, degrees
            (positive: nose down when braking).
        roll_noise_deg: standard deviation of the noise on the lean target, degrees.
        pitch_noise_deg: standard deviation of the noise on the pitch target, degrees.
        noise_correlation: the noise's correlation time, s.
        substeps: integration steps per frame for the lags (default: steps of at most 1 ms).
        vehicle: ``"motorcycle"`` (leans into the turns) or ``"car"`` (its body rolls out of
            them, ``roll_gain_deg``; module docstring). `CAR` holds a car's settings.
        roll_gain_deg: a car's body roll per m/s^2 of lateral acceleration, degrees (positive:
            outwards, the left side down in a right turn); not used for a motorcycle.
        dtype: floating dtype of the returned tensors.

    Returns:
        A dict of tensors, ``N`` frames:

        * ``frame`` (N,) int64, ``time`` (N,) seconds;
        * ``location`` (N, 3) m, ``velocity`` (N, 3) m/s, ``acceleration`` (N, 3) m/s^2:
            CARLA axes (x north, y east, z up);
        * ``rotation`` (N, 3) degrees, ``(roll, pitch, yaw)`` (`ROTATION_ORDER`), yaw in
            ``[-180, 180)``; ``rotation_rate`` (N, 3) deg/s, their time derivatives;
        * ``angular_velocity`` (N, 3) deg/s, CARLA axes (module docstring);
        * ``distance`` (N,) m along the route, ``speed`` (N,) m/s, ``curvature`` (N,) 1/m,
            ``longitudinal_acceleration`` (N,) and ``lateral_acceleration`` (N,) m/s^2
            (horizontal, positive to the right).
    """
    if not isinstance(route, Route):
        raise TypeError(f"route: expected a Route, got {type(route).__name__}")
    _check_positive(fps=fps, max_speed=max_speed, acceleration=acceleration,
                    deceleration=deceleration, max_lateral_acceleration=max_lateral_acceleration,
                    roll_frequency=roll_frequency, pitch_frequency=pitch_frequency,
                    pitch_damping=pitch_damping, noise_correlation=noise_correlation)
    if vehicle not in VEHICLES:
        raise ValueError(f"vehicle: expected one of {VEHICLES}, got {vehicle!r}")
    if (isinstance(roll_gain_deg, bool) or not isinstance(roll_gain_deg, (int, float))
            or not math.isfinite(roll_gain_deg) or roll_gain_deg < 0):
        raise ValueError(f"roll_gain_deg: expected a finite number >= 0, got {roll_gain_deg!r}")
    if not 0 < max_lean_deg < 90:
        raise ValueError(f"max_lean_deg: expected in (0, 90), got {max_lean_deg}")
    if roll_noise_deg < 0 or pitch_noise_deg < 0:
        raise ValueError("roll_noise_deg, pitch_noise_deg: expected >= 0")
    if start_speed < 0 or (end_speed is not None and end_speed < 0):
        raise ValueError("start_speed, end_speed: expected >= 0")
    max_lateral = (max_lateral_acceleration if vehicle == "car" else
                   min(max_lateral_acceleration, GRAVITY * math.tan(math.radians(max_lean_deg))))
    profile = _speed_profile(route, max_speed=max_speed, acceleration=acceleration,
                             deceleration=deceleration, max_lateral=max_lateral,
                             start_speed=start_speed, end_speed=end_speed)
    if duration is not None and frames is not None:
        raise ValueError("give duration or frames, not both")
    if frames is None:
        if duration is None:      # until the end of the route: the last frame at or past it
            duration = math.ceil(float(profile.t[-1]) * fps - 1e-9) / fps
        if not duration >= 0 or not math.isfinite(duration):
            raise ValueError(f"duration: expected a finite number >= 0, got {duration!r}")
        frames = int(math.floor(duration * fps + 1e-9)) + 1
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ValueError(f"frames: expected a positive int, got {frames!r}")
    if substeps is None:
        substeps = max(1, int(math.ceil(1000.0 / fps)))
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise ValueError(f"substeps: expected a positive int, got {substeps!r}")
    if generator is None:
        generator = torch.Generator().manual_seed(0 if seed is None else int(seed))

    h = 1.0 / (fps * substeps)
    n = (frames - 1) * substeps + 1
    t = np.arange(n) * h
    s, v, a_long = profile.at(t)
    kappa = route.curvature_at(s)
    grade = route.grade_at(s)
    a_lat = v * v * kappa * np.cos(grade)
    if vehicle == "car":      # the body rolls out of the turn (CARLA: roll > 0 right side down)
        lean_target = -math.radians(roll_gain_deg) * a_lat
    else:                     # the steady-turn lean of a thin-tyre motorcycle
        lean_target = np.arctan(a_lat / GRAVITY)
    white = _white_noise(n, generator)
    lean_target = lean_target + _noise(white[:, 0], h, math.radians(roll_noise_deg),
                                       noise_correlation)
    pitch_target = math.radians(pitch_gain_deg) * a_long
    pitch_target = pitch_target + _noise(white[:, 1], h, math.radians(pitch_noise_deg),
                                         noise_correlation)
    roll, roll_rate = _second_order(lean_target, h, 2 * math.pi * roll_frequency, 1.0,
                                    lean_target[0])
    suspension, suspension_rate = _second_order(pitch_target, h, 2 * math.pi * pitch_frequency,
                                                pitch_damping, pitch_target[0])

    keep = slice(0, n, substeps)
    t, s, v, a_long, kappa, grade, a_lat = (x[keep] for x in (t, s, v, a_long, kappa, grade,
                                                              a_lat))
    roll, roll_rate = roll[keep], roll_rate[keep]
    pitch = grade + suspension[keep]
    pitch_rate = route.grade_rate_at(s) * v + suspension_rate[keep]
    yaw = route.heading_at(s)
    yaw_rate = kappa * v

    position = route.position_at(s)
    tangent = route._tangent(yaw, grade)
    velocity = v[:, None] * tangent
    cg, sg = np.cos(grade), np.sin(grade)
    cy, sy = np.cos(yaw), np.sin(yaw)
    d_tangent = ((kappa * cg)[:, None] * np.stack([cy, 0 * cy, -sy], -1)
                 + route.grade_rate_at(s)[:, None] * np.stack([-sg * sy, -cg, -sg * cy], -1))
    accel = a_long[:, None] * tangent + (v * v)[:, None] * d_tangent

    # Angular velocity in the world frame (right-handed, formal): w = yaw' e_y
    # + pitch' R_yaw e_x + roll' R_yaw R_pitch e_z; then to CARLA axes, w_c = -P^T w (det -1).
    cp, sp = np.cos(pitch), np.sin(pitch)
    e_x_yawed = np.stack([cy, 0 * cy, -sy], -1)
    forward = np.stack([sy * cp, -sp, cy * cp], -1)
    omega_world = (yaw_rate[:, None] * np.array([0.0, 1.0, 0.0])
                   + pitch_rate[:, None] * e_x_yawed + roll_rate[:, None] * forward)
    omega_carla = -omega_world @ _P

    def out(x):
        return torch.as_tensor(np.ascontiguousarray(x), dtype=dtype)

    deg = 180.0 / math.pi
    yaw_wrapped = (yaw * deg + 180.0) % 360.0 - 180.0
    return {
        "frame": torch.arange(frames, dtype=torch.int64),
        "time": out(t),
        "location": world_to_carla(out(position)),
        "rotation": out(np.stack([roll * deg, pitch * deg, yaw_wrapped], -1)),
        "rotation_rate": out(np.stack([roll_rate, pitch_rate, yaw_rate], -1) * deg),
        "velocity": world_to_carla(out(velocity)),
        "angular_velocity": out(omega_carla * deg),
        "acceleration": world_to_carla(out(accel)),
        "distance": out(s),
        "speed": out(v),
        "curvature": out(kappa),
        "longitudinal_acceleration": out(a_long),
        "lateral_acceleration": out(a_lat),
    }


# --------------------------------------------------------------------------------------------
# Attitude and statistics
# --------------------------------------------------------------------------------------------

def _rotation_degrees(frames) -> Tensor:
    rotation = frames["rotation"] if isinstance(frames, dict) else frames
    if not isinstance(rotation, Tensor):
        rotation = torch.as_tensor(rotation, dtype=torch.float64)
    if not rotation.is_floating_point() or rotation.dim() < 1 or rotation.shape[-1] != 3:
        raise ValueError(f"rotation: expected floating (..., 3) (roll, pitch, yaw) degrees, got "
                         f"{rotation.dtype} {tuple(rotation.shape)}")
    return rotation


def camera_rotation(frame) -> Tensor:
    """Rig-to-world rotation of a frame (or of all of them): ``(..., 3, 3)``.

    Args:
        frame: ``simulate(...)`` (all frames), a dict with ``"rotation"``, or a ``(..., 3)``
            tensor of CARLA ``(roll, pitch, yaw)`` degrees.

    Returns:
        ``yaw_pitch_roll_to_matrix(radians(yaw), radians(pitch), radians(roll))``: maps a
        vehicle (rig) frame vector (x right, y down, z forward) to the world frame (x east,
        y down, z north).
    """
    r = torch.deg2rad(_rotation_degrees(frame))
    return yaw_pitch_roll_to_matrix(r[..., 2], r[..., 1], r[..., 0])


def table_one(frames) -> dict[str, dict[str, float]]:
    """The paper's Table I: mean, std (population, ddof = 0, like numpy's default), min,
    median (midpoint of the two middle values for an even count, like numpy) and max of yaw,
    pitch and roll, in degrees.

    Args:
        frames: ``simulate(...)`` or a ``(N, 3)`` tensor of ``(roll, pitch, yaw)`` degrees.
    """
    rotation = _rotation_degrees(frames).to(torch.float64).reshape(-1, 3)
    if rotation.shape[0] == 0:
        raise ValueError("frames: no frames")
    table = {}
    for name in ("yaw", "pitch", "roll"):
        x = rotation[:, ROTATION_ORDER.index(name)]
        table[name] = {
            "mean": float(x.mean()),
            "std": float(x.std(correction=0)),
            "min": float(x.min()),
            "median": float(torch.quantile(x, 0.5)),
            "max": float(x.max()),
        }
    return table


def records(frames: dict[str, Tensor]) -> list[dict]:
    """Per-frame JSON-ready records with CARLA's names: ``frame``, ``timestamp`` (s),
    ``location`` / ``velocity`` / ``acceleration`` / ``angular_velocity`` as ``{x, y, z}``,
    ``rotation`` as ``{pitch, yaw, roll}`` (degrees), ``speed`` (m/s)."""
    out = []
    xyz = ("x", "y", "z")
    for k in range(len(frames["frame"])):
        rec = {"frame": int(frames["frame"][k]), "timestamp": float(frames["time"][k])}
        for key in ("location", "velocity", "acceleration", "angular_velocity"):
            rec[key] = dict(zip(xyz, map(float, frames[key][k])))
        roll, pitch, yaw = map(float, frames["rotation"][k])
        rec["rotation"] = {"pitch": pitch, "yaw": yaw, "roll": roll}
        rec["speed"] = float(frames["speed"][k])
        out.append(rec)
    return out
