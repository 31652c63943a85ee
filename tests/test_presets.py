"""Presets (fisheye, catadioptric) and the rig's yaw/pitch/roll rotations."""

from __future__ import annotations

import math

import pytest
import torch

import omniscape_torch as ot

from omniscape_torch.cubemap import FACES, face_axes, face_rotations
from omniscape_torch.cameras.presets import (FISHEYE_DEFAULTS, catadioptric, fisheye,
                                     matrix_to_yaw_pitch_roll, yaw_pitch_roll_to_matrix)

#: Float64 trigonometry and products of three rotations: a few ulps.
EXACT = dict(rtol=0, atol=1e-12)

#: DESIGN.md's face table: the rig rotation of each face's simulator camera, (yaw, pitch) deg.
RIG = {"front": (0, 0), "back": (180, 0), "left": (-90, 0), "right": (90, 0),
       "up": (0, 90), "down": (0, -90)}


def rad(*degrees):
    return [torch.tensor(math.radians(d), dtype=torch.float64) for d in degrees]


# --------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("face", FACES)
def test_rig_rotations_match_the_face_table(face):
    yaw, pitch = RIG[face]
    R = yaw_pitch_roll_to_matrix(*rad(yaw, pitch, 0))
    a, b, r = face_axes(torch.float64)[FACES.index(face)]
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(R @ z, a, **EXACT)  # looks along a
    torch.testing.assert_close(R @ y, b, **EXACT)  # image down along b
    torch.testing.assert_close(R, face_rotations(torch.float64)[FACES.index(face)], **EXACT)


def test_signs_of_yaw_pitch_roll():
    x, y, z = torch.eye(3, dtype=torch.float64)
    # Turn right: forward goes to +x.
    torch.testing.assert_close(yaw_pitch_roll_to_matrix(*rad(90, 0, 0)) @ z, x, **EXACT)
    # Look up: forward goes to -y (y is down).
    torch.testing.assert_close(yaw_pitch_roll_to_matrix(*rad(0, 90, 0)) @ z, -y, **EXACT)
    # Lean right (clockwise seen from behind): the right axis goes down, +y; the axis stays.
    R = yaw_pitch_roll_to_matrix(*rad(0, 0, 90))
    torch.testing.assert_close(R @ x, y, **EXACT)
    torch.testing.assert_close(R @ z, z, **EXACT)
    # Roll first, then pitch, then yaw: a leaning camera that turns right still leans about
    # its own forward axis, which now points right.
    R = yaw_pitch_roll_to_matrix(*rad(90, 0, 30))
    torch.testing.assert_close(R @ z, x, **EXACT)
    expected_right = torch.tensor([0.0, math.sin(math.radians(30)), -math.cos(math.radians(30))],
                                  dtype=torch.float64)
    torch.testing.assert_close(R @ x, expected_right, **EXACT)


def carla_matrix(pitch, yaw, roll):
    """LibCarla geom/Transform.h, Transform::GetMatrix (3 x 3 part), angles in degrees, in
    Unreal's left-handed frame x forward, y right, z up."""
    cy, sy = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    cr, sr = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    cp, sp = math.cos(math.radians(pitch)), math.sin(math.radians(pitch))
    return torch.tensor([
        [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
        [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
        [sp, -cp * sr, cp * cr],
    ], dtype=torch.float64)


def test_matches_carla_rotation():
    # (x, y, z)_ours = (y, -z, x)_UE: right, down, forward.
    P = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    angles = (torch.rand(20, 3, generator=gen, dtype=torch.float64) - 0.5) * 360
    compared = 0
    for pitch, yaw, roll in angles.tolist():
        ours = yaw_pitch_roll_to_matrix(*rad(yaw, pitch, roll))
        torch.testing.assert_close(ours, P @ carla_matrix(pitch, yaw, roll) @ P.T, **EXACT)
        compared += 1
    assert compared == 20


def test_inverse_round_trip_and_gimbal_lock():
    gen = torch.Generator().manual_seed(1)
    n = 200
    yaw = (torch.rand(n, generator=gen, dtype=torch.float64) * 2 - 1) * math.pi * 0.999
    pitch = (torch.rand(n, generator=gen, dtype=torch.float64) * 2 - 1) * math.pi / 2 * 0.999
    roll = (torch.rand(n, generator=gen, dtype=torch.float64) * 2 - 1) * math.pi * 0.999
    R = yaw_pitch_roll_to_matrix(yaw, pitch, roll)
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64)
                               .expand(n, 3, 3), **EXACT)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(n, dtype=torch.float64), **EXACT)
    back = matrix_to_yaw_pitch_roll(R)
    for got, want in zip(back, (yaw, pitch, roll)):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-9)
    # At pitch = +-90 deg only yaw -+ roll is defined: roll comes back 0, the matrix is kept.
    for p in (90.0, -90.0):
        R = yaw_pitch_roll_to_matrix(*rad(30, p, 20))
        y, pt, r = matrix_to_yaw_pitch_roll(R)
        assert float(r) == 0.0 and float(pt) == pytest.approx(math.radians(p), abs=1e-7)
        torch.testing.assert_close(yaw_pitch_roll_to_matrix(y, pt, r), R, rtol=0, atol=1e-7)
    # The face rig rotations come back as the table's angles.
    for k, face in enumerate(FACES):
        y, pt, r = matrix_to_yaw_pitch_roll(face_rotations(torch.float64)[k])
        yaw_deg, pitch_deg = RIG[face]
        assert math.degrees(float(pt)) == pytest.approx(pitch_deg, abs=1e-9)
        assert math.cos(float(y) - math.radians(yaw_deg)) == pytest.approx(1.0, abs=1e-12)
        assert float(r) == pytest.approx(0.0, abs=1e-12)


def test_broadcasting_dtype_and_gradients():
    yaw = torch.zeros(4, 1, dtype=torch.float32)
    pitch = torch.zeros(3, dtype=torch.float32)
    R = yaw_pitch_roll_to_matrix(yaw, pitch, 0.1)
    assert R.shape == (4, 3, 3, 3) and R.dtype == torch.float32
    assert yaw_pitch_roll_to_matrix(0.0, 0.0, 0.0).dtype == torch.get_default_dtype()
    angles = torch.tensor([0.3, -0.4, 0.5], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: yaw_pitch_roll_to_matrix(a[0], a[1], a[2]),
                                    (angles,))
    R = yaw_pitch_roll_to_matrix(*rad(10, 20, 30)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda m: torch.stack(matrix_to_yaw_pitch_roll(m)), (R,))
    with pytest.raises(TypeError, match="pitch"):
        yaw_pitch_roll_to_matrix(0.0, "up", 0.0)
    with pytest.raises(TypeError, match="roll"):
        yaw_pitch_roll_to_matrix(0.0, 0.0, torch.tensor(1))
    with pytest.raises(ValueError, match="rotation"):
        matrix_to_yaw_pitch_roll(torch.eye(2))


# --------------------------------------------------------------------------------------------
# Fisheye
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("model", sorted(FISHEYE_DEFAULTS))
def test_fisheye_image_circle_is_inscribed(model):
    fov = math.radians(180 if model == "orthographic" else 190)
    cam = fisheye((101, 121), fov=fov, model=model, dtype=torch.float64)
    assert cam.model.name == model and cam.fov == fov and cam.image_size == (101, 121)
    fx, fy, cx, cy = cam.params[:4].tolist()
    assert (fx, cx, cy) == (fy, 60.0, 50.0)
    # The rim lands on the outermost pixel centres of the shorter side: 50 px from the centre.
    theta = 0.5 * fov
    rim = torch.tensor([[math.sin(theta), 0.0, math.cos(theta)],
                        [0.0, -math.sin(theta), math.cos(theta)]], dtype=torch.float64)
    pixels, valid = cam.model.project(rim, cam.params)
    assert bool(valid.all())
    torch.testing.assert_close(pixels, torch.tensor([[110.0, 50.0], [60.0, 0.0]],
                                                    dtype=torch.float64), rtol=0, atol=1e-9)
    # Valid pixels fill the circle and stay in it; the optical axis is +z.
    rays, valid = cam.ray_grid()
    grid = cam.pixel_grid()
    centre = torch.tensor([60.0, 50.0], dtype=torch.float64)
    radius = torch.linalg.vector_norm(grid - centre, dim=-1)
    assert bool((radius[valid] <= 50 + 1e-9).all())
    assert bool(valid[radius < 49.5].all())
    torch.testing.assert_close(rays[50, 60], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                               rtol=0, atol=1e-12)


def test_fisheye_focal_of_the_closed_forms():
    half = math.radians(95)
    rim = 511.5
    assert float(fisheye((1024, 1024), dtype=torch.float64).params[0]) == pytest.approx(
        rim / half, rel=1e-12)
    kb = fisheye((1024, 1024), model="kannala_brandt", dtype=torch.float64)
    assert float(kb.params[0]) == pytest.approx(rim / half, rel=1e-12)
    eqs = fisheye((1024, 1024), model="equisolid", dtype=torch.float64)
    assert float(eqs.params[0]) == pytest.approx(rim / (2 * math.sin(half / 2)), rel=1e-12)
    st = fisheye((1024, 1024), model="stereographic", dtype=torch.float64)
    assert float(st.params[0]) == pytest.approx(rim / (2 * math.tan(half / 2)), rel=1e-12)
    assert fisheye((8, 8)).params.dtype == torch.float32


def test_fisheye_entry_checks():
    with pytest.raises(ValueError, match="fov"):
        fisheye((64, 64), model="orthographic", fov=math.radians(190))
    with pytest.raises(ValueError, match="fov"):
        fisheye((64, 64), fov=190.0)  # degrees by mistake
    with pytest.raises(ValueError, match="model"):
        fisheye((64, 64), model="scaramuzza")
    with pytest.raises(ValueError, match="distortion"):
        fisheye((64, 64), model="double_sphere", distortion=(0.1,))
    with pytest.raises(ValueError, match="image_size"):
        fisheye((1, 64))
    with pytest.raises(TypeError, match="dtype"):
        fisheye((64, 64), dtype=torch.int32)


# --------------------------------------------------------------------------------------------
# Catadioptric
# --------------------------------------------------------------------------------------------

def test_catadioptric_rim_blind_spot_and_axis():
    cam, R = catadioptric((128, 160), dtype=torch.float64)
    assert cam.model.name == "unified"
    gamma, gamma_y, cx, cy, xi = cam.params[:5].tolist()
    assert (gamma, cx, cy, xi) == (gamma_y, 79.5, 63.5, 0.9)
    assert cam.params[5:].abs().sum() == 0
    rim, blind = math.radians(110), math.radians(20)
    assert cam.fov == pytest.approx(2 * rim) and cam.blind_fov == pytest.approx(2 * blind)
    # Rim at 63.5 px: gamma sin(theta) / (cos(theta) + xi) = 63.5.
    assert gamma == pytest.approx(63.5 * (math.cos(rim) + xi) / math.sin(rim), rel=1e-12)
    # 360 degrees around: every pixel between the blind disc and the rim is valid.
    _, valid = cam.ray_grid()
    centre = torch.tensor([cx, cy], dtype=torch.float64)
    radius = torch.linalg.vector_norm(cam.pixel_grid() - centre, dim=-1)
    r_blind = gamma * math.sin(blind) / (math.cos(blind) + xi)
    assert r_blind / 63.5 == pytest.approx(0.110, abs=1e-3)
    assert bool(valid[(radius > r_blind + 0.01) & (radius < 63.5 - 0.01)].all())
    assert not bool(valid[radius < r_blind - 0.01].any())
    assert not bool(valid[radius > 63.5 + 1e-9].any())
    # Looking down: the axis is cube +y, the top of the image shows the front (+z).
    torch.testing.assert_close(R @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                               torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), **EXACT)
    rays, _ = cam.ray_grid()
    top = R @ rays[2, 80]
    assert top[2] > 0.9
    torch.testing.assert_close(R, yaw_pitch_roll_to_matrix(*rad(0, -90, 0)), **EXACT)
    _, up = catadioptric((128, 160), looking="up", dtype=torch.float64)
    torch.testing.assert_close(up @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                               torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64), **EXACT)


def test_catadioptric_from_a_mirror():
    d, p = 0.3, 0.05
    cam, _ = catadioptric((64, 64), mirror=dict(kind="hyperbolic", d=d, p=p),
                          dtype=torch.float64)
    assert float(cam.params[4]) == pytest.approx(d / math.sqrt(d * d + 4 * p * p), rel=1e-12)
    parabolic, _ = catadioptric((64, 64), mirror=dict(kind="parabolic", p=0.02))
    assert float(parabolic.params[4]) == 1.0
    no_blind, _ = catadioptric((64, 64), blind_fov=None)
    assert no_blind.blind_fov is None
    with pytest.raises(ValueError, match="xi"):
        catadioptric((64, 64), xi=0.8, mirror=dict(kind="parabolic", p=0.02))
    with pytest.raises(TypeError, match="mirror"):
        catadioptric((64, 64), mirror="hyperbolic")
    with pytest.raises(ValueError, match="mirror"):
        catadioptric((64, 64), mirror=dict(kind="conical"))
    with pytest.raises(ValueError, match="mirror"):
        catadioptric((64, 64), mirror=dict(kind="hyperbolic", d=1.0, p=0.1, focal=3.0))
    # xi = 0.5 ends at acos(-0.5) = 120 deg from the axis.
    with pytest.raises(ValueError, match="fov"):
        catadioptric((64, 64), xi=0.5, fov=math.radians(250))
    with pytest.raises(ValueError, match="looking"):
        catadioptric((64, 64), looking="sideways")
    with pytest.raises(ValueError, match="blind_fov"):
        catadioptric((64, 64), blind_fov=math.radians(230))


def _catadioptric_pair_calls():
    import omniscape_torch.calibration as calibration
    from omniscape_torch.cameras.export import write_camera
    from omniscape_torch.data.ocamcalib import fit_polynomial

    image = torch.rand(1, 3, 16, 16)
    fisheye = ot.presets.fisheye((16, 16))
    return {
        "OmniProjection": lambda pair: ot.OmniProjection(pair, face_size=8),
        "reproject (dst)": lambda pair: ot.reproject(image, fisheye, pair),
        "reproject (src)": lambda pair: ot.reproject(image, pair, fisheye),
        "visible_faces": lambda pair: ot.visible_faces(pair),
        "required_face_size": lambda pair: ot.required_face_size(pair),
        "convert": lambda pair: calibration.convert(pair, "eucm"),
        "select_model": lambda pair: calibration.select_model(pair, 1.0),
        "fit_photometric": lambda pair: calibration.fit_photometric(
            torch.rand(1, 6, 3, 8, 8), image, pair),
        "write_camera": lambda pair: write_camera(pair, "unused.json", "json"),
        "fit_polynomial": lambda pair: fit_polynomial(pair),
        "RandomReproject": lambda pair: ot.augment.RandomReproject((16, 16), source_camera=pair),
    }


@pytest.mark.parametrize("call", sorted(_catadioptric_pair_calls()))
def test_a_catadioptric_pair_where_a_camera_is_expected_says_what_to_pass(call):
    """`ot.presets.catadioptric` returns `(camera, rotation)`, unlike `fisheye`: passing the
    pair by analogy is refused with a hint, wherever a camera is checked (issue 46)."""
    pair = ot.presets.catadioptric((16, 16))
    with pytest.raises(TypeError, match=r"expected an ot\.Camera.*got tuple; "
                                        r"ot\.presets\.catadioptric returns \(camera, rotation\): "
                                        r"pass the camera"):
        _catadioptric_pair_calls()[call](pair)
    with pytest.raises(TypeError, match=r"got list$"):   # no hint for what it does not fit
        ot.OmniProjection([1, 2], face_size=8)
