"""The town's weather and time of day: light, sky, wetness and fog (`Weather`), CARLA's 14
presets with CARLA's own parameters (`CARLA_WEATHERS`, `carla_weather`) and a few of the town's
own (`WEATHERS`). A weather changes light, colour, wetness and fog, never geometry or labels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from torch import Tensor

from ..render.kernels import town as _kernels

__all__ = ["CARLA_PRESETS", "CARLA_WEATHERS", "WEATHERS", "Weather", "carla_weather"]


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
    """The town's `Weather` for CARLA's weather parameters (percent and degrees, as
    ``carla.WeatherParameters``): the sun's colour reddens towards the horizon (noon white at
    45 deg and above, orange at 15 deg) and dims under clouds (by up to 85 %) and rain; the
    ambient light and the sky grey with clouds; fog is ``0.00075 * fog_density`` per metre plus
    ``0.012`` at full rain (the rain's haze); ``wetness`` is the deposits' share, ``rain`` the
    precipitation's (`Weather.surface_factor`, `Weather.sky_factor`)."""
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

#: The weather presets: CARLA's 14 (`CARLA_WEATHERS`, in snake case: ``clear_noon``,
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



def _kernel_weather(w: Weather, far: float) -> Tensor:
    """``w`` as the shading reads it, the sky at ``far`` metres: the ``(26,)`` float32 vector of
    `omniscape_torch.render.kernels.town.weather_vector`."""
    return _kernels.weather_vector(
        sun_direction=w.sun_direction(), sun_colour=w.sun_colour, ambient=w.ambient,
        sky_zenith=w.sky_zenith, sky_horizon=w.sky_horizon, fog_colour=w.fog_colour,
        fog_density=w.fog_density, lamps=w.lamps, windows=w.windows, wetness=w.wetness,
        darken=w.surface_factor() if (w.rain > 0 or w.wetness > 0) else 1.0,
        rain_sky=w.sky_factor() if w.rain > 0 else 1.0, far=far)
