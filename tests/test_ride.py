"""Motorcycle ride: steady-turn lean, pitch signs, kinematic consistency, CARLA frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omniscape_torch.cameras.presets import yaw_pitch_roll_to_matrix
from omniscape_torch.scenes.ride import (GRAVITY, Route, arc, camera_rotation, carla_to_world,
                                  random_route, records, simulate, straight, table_one,
                                  world_to_carla)

QUIET = dict(roll_noise_deg=0.0, pitch_noise_deg=0.0)


def _circle(radius, angle_deg, v, **kw):
    route = Route([straight(30.0), arc(radius, angle_deg)], transition=10.0)
    return route, simulate(route, fps=20, duration=25.0, start_speed=v, max_speed=v,
                           end_speed=None, max_lateral_acceleration=20.0, **QUIET, **kw)


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_steady_turn_lean_is_atan_v2_over_gr(side):
    v, radius = 12.0, 40.0
    route, f = _circle(radius, side * 720.0, v)
    t = f["time"].numpy()
    steady = t > 10.0
    assert np.allclose(f["speed"].numpy()[steady], v)
    expected = math.degrees(math.atan(v * v / (GRAVITY * radius)))
    roll = f["rotation"][:, 0].numpy()[steady]
    assert np.allclose(roll, side * expected, atol=1e-6)    # right turn: lean right, roll > 0
    assert np.allclose(f["rotation"][:, 1].numpy()[steady], 0.0, atol=1e-9)
    # yaw rate v / R, the sign of the turn; CARLA's angular velocity z equals it
    yaw_rate = math.degrees(v / radius)
    assert np.allclose(f["rotation_rate"][:, 2].numpy()[steady], side * yaw_rate)
    w = f["angular_velocity"].numpy()[steady]
    assert np.allclose(w[:, 2], side * yaw_rate) and np.allclose(w[:, :2], 0.0, atol=1e-9)
    # the path is a circle of radius R: centripetal acceleration v^2 / R
    acc = f["acceleration"].numpy()[steady]
    assert np.allclose(np.linalg.norm(acc, axis=-1), v * v / radius, rtol=1e-6)
    assert np.allclose(np.abs(f["lateral_acceleration"].numpy()[steady]), v * v / radius)


def test_lean_lags_and_is_continuous():
    route, f = _circle(40.0, 90.0, 12.0)
    roll = f["rotation"][:, 0].numpy()
    rate = f["rotation_rate"][:, 0].numpy()
    assert np.all(np.abs(np.diff(roll)) < 2.0)          # no jumps at 20 fps
    assert np.all(np.abs(np.diff(rate)) < 10.0)         # continuous roll rate
    assert roll[0] == 0.0
    # leaning in while still heading north (yaw 0): CARLA w_x = -roll rate (left-handed axes)
    entry = (np.abs(f["rotation"][:, 2].numpy()) < 1.0) & (np.abs(rate) > 0.1)
    assert entry.sum() >= 3
    assert np.allclose(f["angular_velocity"][:, 0].numpy()[entry], -rate[entry], rtol=1e-3)


def test_straight_constant_speed_level():
    route = Route([straight(400.0)])
    f = simulate(route, fps=10, duration=20.0, start_speed=10.0, max_speed=10.0,
                 end_speed=None, **QUIET)
    assert np.allclose(f["rotation"].numpy(), 0.0, atol=1e-12)
    assert np.allclose(f["speed"].numpy(), 10.0)
    loc = f["location"].numpy()
    assert np.allclose(loc[:, 0], 10.0 * f["time"].numpy())   # CARLA x = north = forward
    assert np.allclose(loc[:, 1:], 0.0)
    assert np.allclose(f["angular_velocity"].numpy(), 0.0)


def test_braking_pitches_nose_down_and_accelerating_up():
    route = Route([straight(200.0)])
    f = simulate(route, fps=20, **QUIET)            # from rest to a stop at the end
    a = f["longitudinal_acceleration"].numpy()
    pitch = f["rotation"][:, 1].numpy()
    speed = f["speed"].numpy()
    assert a.min() == pytest.approx(-4.0) and a.max() == pytest.approx(2.5)
    braking = np.nonzero(a < 0)[0]
    accel = np.nonzero(a > 0)[0]
    # after the suspension settles (1 s into each phase): nose down / up by gain * a
    mid_brake = braking[len(braking) // 2]
    mid_acc = accel[len(accel) // 2]
    assert pitch[mid_brake] == pytest.approx(0.4 * -4.0, abs=1e-3)
    assert pitch[mid_acc] == pytest.approx(0.4 * 2.5, abs=1e-3)
    assert speed[-1] == 0.0
    assert np.all(speed >= 0)


def test_road_grade_pitch_and_height():
    route = Route([straight(100.0, grade_deg=5.0)], transition=0.0)
    f = simulate(route, fps=10, duration=8.0, start_speed=10.0, max_speed=10.0,
                 end_speed=None, **QUIET)
    assert np.allclose(f["rotation"][:, 1].numpy(), 5.0)     # uphill: nose up
    loc = f["location"].numpy()
    d = f["distance"].numpy()
    assert np.allclose(loc[:, 2], d * math.sin(math.radians(5.0)))   # CARLA z up
    assert np.allclose(loc[:, 0], d * math.cos(math.radians(5.0)))


def _ride(seed=3, fps=30.0, noise=True):
    return simulate(random_route(seed, turns=5), fps=fps, duration=60.0, seed=seed,
                    **({} if noise else QUIET))


def test_velocity_is_derivative_of_location():
    fps = 30.0
    f = _ride(fps=fps)
    loc, vel = f["location"].numpy(), f["velocity"].numpy()
    fd = (loc[2:] - loc[:-2]) * fps / 2
    # central differences: O(dt) only where the acceleration steps (up to 6.5 m/s^2 from
    # accelerating to braking: error <= 6.5 dt / 8)
    assert np.abs(fd - vel[1:-1]).max() < 6.5 / fps / 8 + 1e-3
    assert np.median(np.abs(fd - vel[1:-1])) < 1e-4
    assert np.allclose(np.linalg.norm(vel, axis=-1), f["speed"].numpy())


def test_acceleration_is_derivative_of_velocity():
    fps = 30.0
    f = _ride(fps=fps)
    vel, acc = f["velocity"].numpy(), f["acceleration"].numpy()
    fd = (vel[2:] - vel[:-2]) * fps / 2
    err = np.linalg.norm(fd - acc[1:-1], axis=-1)
    assert np.median(err) < 1e-3
    assert np.mean(err < 0.05) > 0.95           # the rest: steps of a_long, grade, curvature


@pytest.mark.parametrize("noise, tol", [(False, 1e-3), (True, 0.05)])
def test_rotation_rate_is_derivative_of_angles(noise, tol):
    fps = 30.0
    f = _ride(fps=fps, noise=noise)
    rot = f["rotation"].numpy().copy()
    rot[:, 2] = np.degrees(np.unwrap(np.radians(rot[:, 2])))
    fd = (rot[2:] - rot[:-2]) * fps / 2
    rate = f["rotation_rate"].numpy()[1:-1]
    err = np.abs(fd - rate)
    assert np.median(err) < tol           # the noise is continuous, not smooth: looser
    assert err[:, 0].max() < 0.5          # roll rate continuous (lagged lean)
    assert np.mean(err < 0.1) > 0.97


@pytest.mark.parametrize("noise, tol", [(False, 2e-3), (True, 0.05)])
def test_angular_velocity_from_rotation_matrices(noise, tol):
    """w in CARLA axes: skew(w) = dM/dt M^T, M the attitude in CARLA's own coordinates."""
    fps = 30.0
    f = _ride(fps=fps, noise=noise)
    R = camera_rotation(f).numpy()                      # rig -> world
    P = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # world <- carla
    M = P.T @ R @ P                                       # CARLA coordinates
    W = (M[2:] - M[:-2]) * fps / 2 @ np.transpose(M[1:-1], (0, 2, 1))
    w = np.degrees(np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], -1))
    err = np.linalg.norm(w - f["angular_velocity"].numpy()[1:-1], axis=-1)
    assert np.median(err) < tol
    assert np.mean(err < 0.2) > 0.97


def test_carla_sign_conventions():
    route = Route([straight(20.0), arc(30.0, 90.0)], transition=0.0)
    f = simulate(route, fps=10, start_speed=8.0, max_speed=8.0, **QUIET)
    last = f["location"][-1].numpy()
    # a right turn from north ends heading east, at (x north, y east) = (20 + R, R)
    assert last == pytest.approx([50.0, 30.0, 0.0], abs=1e-6)
    assert f["rotation"][-1, 2].item() == pytest.approx(90.0)
    v = f["velocity"].numpy()
    turning = np.abs(f["curvature"].numpy()) > 0
    assert np.all(f["angular_velocity"].numpy()[turning & (f["speed"].numpy() > 0), 2] > 0)
    # a vehicle heading east (yaw 90) moves along CARLA +y
    moving = f["speed"].numpy() > 1
    assert v[-2, 1] > 0 or not moving[-2]


def test_camera_rotation_matches_presets():
    f = _ride()
    R = camera_rotation(f)
    r = torch.deg2rad(f["rotation"])
    assert torch.allclose(R, yaw_pitch_roll_to_matrix(r[:, 2], r[:, 1], r[:, 0]))
    # the rig's forward axis (+z) is the direction of travel (pitch = grade + suspension)
    fwd = R[:, :, 2]
    vel = carla_to_world(f["velocity"])
    moving = f["speed"] > 1
    cos = (fwd[moving] * vel[moving]).sum(-1) / vel[moving].norm(dim=-1)
    assert cos.min() > math.cos(math.radians(3.0))
    assert camera_rotation(f["rotation"][5]).shape == (3, 3)


def test_frame_conversions_round_trip():
    v = torch.randn(4, 3, dtype=torch.float64)
    assert torch.equal(carla_to_world(world_to_carla(v)), v)
    assert carla_to_world(torch.tensor([1.0, 2.0, 3.0])).tolist() == [2.0, -3.0, 1.0]


def test_determinism_by_seed():
    route = random_route(5, turns=3)
    a = simulate(route, fps=10, duration=20.0, seed=7)
    b = simulate(route, fps=10, duration=20.0, seed=7)
    c = simulate(route, fps=10, duration=20.0, seed=8)
    g = simulate(route, fps=10, duration=20.0, generator=torch.Generator().manual_seed(7))
    for key in a:
        assert torch.equal(a[key], b[key]) and torch.equal(a[key], g[key])
    assert not torch.equal(a["rotation"], c["rotation"])
    assert torch.equal(a["location"], c["location"])      # noise only in the attitude


def test_a_longer_ride_extends_a_shorter_one():
    """Frame k depends on the seed and k only: the first frames of a longer ride (more frames,
    or a longer duration) are those of the shorter one, noise included, bit for bit (a dataset
    of 12 frames extends one of 8)."""
    route = random_route(2, turns=3)
    short = simulate(route, fps=2, frames=8, seed=3)
    for longer in (simulate(route, fps=2, frames=12, seed=3),
                   simulate(route, fps=2, duration=30.0, seed=3)):
        for key in short:
            assert torch.equal(short[key], longer[key][:8]), key
    assert not torch.equal(short["rotation"], simulate(route, fps=2, frames=8,
                                                        seed=4)["rotation"])


def test_lateral_acceleration_within_limit():
    for seed in range(3):
        f = simulate(random_route(seed, turns=6), fps=10, max_lateral_acceleration=3.0,
                     seed=seed)
        assert f["lateral_acceleration"].abs().max() <= 3.0 + 1e-9
        assert f["speed"].max() <= 15.0 + 1e-9
    # the lean cap also limits it: g tan(10 deg)
    f = simulate(random_route(0, turns=6), fps=10, max_lean_deg=10.0, **QUIET)
    assert f["lateral_acceleration"].abs().max() <= GRAVITY * math.tan(math.radians(10)) + 1e-9
    assert f["rotation"][:, 0].abs().max() <= 10.0 + 0.5


def test_longitudinal_limits():
    f = simulate(random_route(2, turns=4), fps=10, seed=2)
    a = f["longitudinal_acceleration"].numpy()
    assert a.max() <= 2.5 + 1e-9 and a.min() >= -4.0 - 1e-9


def test_table_one_matches_numpy():
    f = _ride()
    t = table_one(f)
    rot = f["rotation"].numpy()
    for name, col in (("roll", 0), ("pitch", 1), ("yaw", 2)):
        x = rot[:, col]
        assert t[name]["mean"] == pytest.approx(np.mean(x), rel=1e-12, abs=1e-12)
        assert t[name]["std"] == pytest.approx(np.std(x), rel=1e-12)
        assert t[name]["min"] == np.min(x) and t[name]["max"] == np.max(x)
        assert t[name]["median"] == pytest.approx(np.median(x), rel=1e-12, abs=1e-12)
    even = torch.tensor([[1.0, 2.0, 3.0], [3.0, 4.0, 5.0]])
    assert table_one(even)["roll"]["median"] == 2.0


def test_frames_and_duration():
    route = Route([straight(100.0)])
    f = simulate(route, fps=10, duration=2.0, start_speed=5.0, max_speed=5.0, end_speed=None)
    assert len(f["frame"]) == 21 and f["time"][-1].item() == pytest.approx(2.0)
    f = simulate(route, fps=10, frames=5)
    assert f["frame"].tolist() == [0, 1, 2, 3, 4]
    # past the end of the route the motorcycle stands still
    f = simulate(Route([straight(20.0)]), fps=5, duration=60.0, **QUIET)
    assert f["speed"][-20:].eq(0).all() and f["location"][-1, 0].item() == pytest.approx(20.0)
    assert f["acceleration"][-20:].abs().max() == 0


def test_records_json_ready():
    import json
    f = simulate(Route([straight(50.0)]), fps=5, frames=3)
    rec = records(f)
    assert len(rec) == 3 and set(rec[0]["rotation"]) == {"pitch", "yaw", "roll"}
    json.dumps(rec)


def test_errors():
    with pytest.raises(ValueError, match="length"):
        straight(0.0)
    with pytest.raises(ValueError, match="radius"):
        arc(-1.0, 90.0)
    with pytest.raises(ValueError, match="segments"):
        Route([])
    route = Route([straight(10.0)])
    with pytest.raises(ValueError, match="fps"):
        simulate(route, fps=0)
    with pytest.raises(ValueError, match="not both"):
        simulate(route, duration=1.0, frames=3)
    with pytest.raises(TypeError, match="Route"):
        simulate([straight(1.0)])
    with pytest.raises(ValueError, match="rotation"):
        table_one(torch.zeros(4, 2))
