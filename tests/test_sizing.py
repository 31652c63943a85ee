"""Cube face size and visible faces, against analytic cases."""

from __future__ import annotations

import math

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.cubemap import FACES, face_rotations
from omniscape_torch.cameras.presets import catadioptric, fisheye, yaw_pitch_roll_to_matrix
from omniscape_torch.render.sizing import (face_size_map, needed_face_names, required_face_size,
                                    visible_faces)

#: Fourth-order differences in float64 leave a relative error below 1e-10 on the face size
#: (sizing.face_size_map); 1e-8 leaves room.
SIZE_RTOL = 1e-8


def face_camera(size: int, focal: float | None = None) -> ot.Camera:
    """A pinhole identical to a cube face of ``size`` texels (or wider, with a smaller focal)."""
    f = size / 2 if focal is None else focal
    params = torch.tensor([f, f, (size - 1) / 2, (size - 1) / 2], dtype=torch.float64)
    return ot.Camera("pinhole", params, (size, size))


def names(mask: torch.Tensor) -> set[str]:
    return set(needed_face_names(mask))


# --------------------------------------------------------------------------------------------
# required_face_size
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("size", [8, 32, 33])
def test_camera_identical_to_a_face_needs_exactly_that_face(size):
    cam = face_camera(size)
    sizes = face_size_map(cam)
    # G = I / f at every pixel: the face size is F everywhere, not only at the centre.
    torch.testing.assert_close(sizes, torch.full_like(sizes, size), rtol=SIZE_RTOL, atol=0)
    assert required_face_size(cam) == size
    assert required_face_size(cam, supersample=2) == 2 * size


@pytest.mark.parametrize("size", [32, 33])
def test_isotropic_bound_asks_f_over_cos_phi_at_the_corner(size):
    cam = face_camera(size)
    # Corner pixel centre: x = y = -(F - 1) / F on the normalised plane.
    t = (size - 1) / size
    cos_phi = 1 / math.sqrt(1 + 2 * t * t)
    assert required_face_size(cam, criterion="isotropic") == math.ceil(size / cos_phi)
    iso = face_size_map(cam, criterion="isotropic")
    assert bool((iso >= face_size_map(cam) * (1 - SIZE_RTOL)).all())


def test_isotropic_bound_is_camera_density_times_two_cos_phi():
    cam = catadioptric((48, 64))[0].double()
    rotation = yaw_pitch_roll_to_matrix(torch.tensor(0.3, dtype=torch.float64), 0.2, -0.1)
    iso = face_size_map(cam, rotation, criterion="isotropic")
    finest, _ = cam.pixels_per_radian()
    rays, valid = cam.ray_grid()
    d = rays @ rotation.T
    cos_phi = d.abs().amax(-1)  # the face hit is the dominant axis
    ok = valid & (iso > 0) & (finest > 0)
    assert int(ok.sum()) > 1000
    # pixels_per_radian uses second-order differences with a 1e-3 px step: ~1e-7 relative.
    torch.testing.assert_close(iso[ok], (2 * cos_phi * finest)[ok], rtol=1e-6, atol=0)
    aniso = face_size_map(cam, rotation)
    assert bool((iso[ok] >= aniso[ok] * (1 - SIZE_RTOL)).all())
    assert bool((iso[ok] <= math.sqrt(3) * aniso[ok] * (1 + SIZE_RTOL)).all())


def test_equidistant_fisheye_analytic_face_sizes():
    # 257 x 257, 190 degrees: f = 128 / radians(95); the pixel column u = 128 and the row
    # v = 128 lie in the planes of the side faces' axes.
    cam = fisheye((257, 257), fov=math.radians(190), dtype=torch.float64)
    f = float(cam.params[0])
    assert f == pytest.approx(128 / math.radians(95), rel=1e-12)
    sizes = face_size_map(cam)
    rays, valid = cam.ray_grid()
    theta = torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2])
    on_front = valid & (rays[..., 2] > rays[..., :2].abs().amax(-1))
    # Front face (any azimuth; the face is a pinhole around the same axis): the camera's
    # tangential density f theta / sin theta against the face's f_F / cos theta.
    expected = torch.where(theta > 0, 2 * f * theta / torch.tan(theta),
                           torch.full_like(theta, 2 * f))
    torch.testing.assert_close(sizes[on_front], expected[on_front], rtol=SIZE_RTOL, atol=0)
    assert sizes[128, 128].item() == pytest.approx(2 * f, rel=SIZE_RTOL)
    # Side faces, in their axis planes: tangential f theta / sin theta against f_F / sin theta,
    # so F = 2 f theta = twice the pixel's distance to the centre.
    r = torch.arange(129, dtype=torch.float64)
    for line in (sizes[128, :], sizes[:, 128], sizes[128, :].flip(0), sizes[:, 128].flip(0)):
        side = ~on_front[128, :129] & valid[128, :129]
        assert int(side.sum()) > 30
        torch.testing.assert_close(line[:129][side], 2 * (128 - r)[side], rtol=SIZE_RTOL, atol=0)
    # The rim pixels on those lines need the most: 2 * 128.
    assert required_face_size(cam) == 256


def test_narrow_equidistant_needs_twice_the_focal():
    # Within the front face, F = 2 f theta / tan(theta) peaks at the axis: exactly 2 f.
    cam = ot.Camera("equidistant", torch.tensor([100.25, 100.25, 100.0, 100.0],
                                                dtype=torch.float64), (201, 201),
                    fov=math.radians(60))
    assert required_face_size(cam) == 201  # ceil(200.5)
    assert required_face_size(cam, supersample=1.5) == math.ceil(1.5 * 200.5)


def test_halving_the_image_halves_the_face_size():
    big = required_face_size(fisheye((256, 256)))
    small = required_face_size(fisheye((128, 128)))
    assert big == 253  # 2 * (127.5 - 1) at the rim pixels next to the axis planes
    assert small == pytest.approx(big / 2, abs=1.5)


def test_rotations_and_batches():
    cam = fisheye((64, 64), dtype=torch.float64)
    rigs = face_rotations(torch.float64)
    # A rig rotation maps the cube onto itself: same face size.
    sizes = [required_face_size(cam, rigs[k]) for k in range(6)]
    assert len(set(sizes)) == 1
    # A batch of rotations: the maximum over the batch.
    tilted = yaw_pitch_roll_to_matrix(torch.tensor([0.0, math.pi / 4, 0.3], dtype=torch.float64),
                                      torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64), 0.2)
    each = [required_face_size(cam, tilted[i]) for i in range(3)]
    assert required_face_size(cam, tilted) == max(each)
    assert face_size_map(cam, tilted).shape == (3, 64, 64)
    # A batch of cameras pairs with a batch of rotations.
    params = cam.params.expand(3, 4).clone()
    params[1, :2] *= 1.2
    batch = ot.Camera("equidistant", params, (64, 64), fov=cam.fov)
    assert face_size_map(batch, tilted).shape == (3, 64, 64)
    with pytest.raises(ValueError, match="rotation"):
        face_size_map(batch, tilted[:2])


@pytest.mark.slow
def test_any_rotation_is_twice_the_finest_density_and_bounds_every_attitude():
    """``rotation="any"``: each pixel's ray at a face's centre, where a face is coarsest, so
    ``F = 2 x`` the camera's finest pixels per radian. For an equidistant lens that is the
    tangential density ``f theta / sin theta`` of the valid pixel farthest from the axis,
    computed here from the pixel grid (``theta = r / f``)."""
    cam = fisheye((257, 257), fov=math.radians(190), dtype=torch.float64)
    f, c = float(cam.params[0]), float(cam.params[2])
    v, u = torch.meshgrid(torch.arange(257.0, dtype=torch.float64),
                          torch.arange(257.0, dtype=torch.float64), indexing="ij")
    theta = torch.hypot(u - c, v - c) / f
    theta = theta[(theta <= math.radians(95)) & (theta > 0)]
    expected = float((2 * f * theta / torch.sin(theta)).max())
    sizes = face_size_map(cam, "any")
    assert float(sizes.max()) == pytest.approx(expected, rel=1e-6)
    bound = required_face_size(cam, "any")
    assert bound == math.ceil(expected * (1 - 1e-8))
    # no attitude needs more, and the bound is reached within a texel or two by some
    g = torch.Generator().manual_seed(0)
    angles = (torch.rand(3, 64, generator=g, dtype=torch.float64) - 0.5) * 2 * math.pi
    rotations = yaw_pitch_roll_to_matrix(angles[0], angles[1] / 2, angles[2])
    sizes = [required_face_size(cam, rotations[i]) for i in range(64)]
    assert max(sizes) <= bound and max(sizes) >= bound - 3
    assert required_face_size(cam) <= bound


def test_required_face_size_entry_checks():
    cam = fisheye((16, 16))
    with pytest.raises(TypeError, match="camera"):
        required_face_size("fisheye")
    with pytest.raises(ValueError, match="rotation"):
        required_face_size(cam, torch.eye(4))
    with pytest.raises(ValueError, match="rotation"):
        required_face_size(cam, 2 * torch.eye(3))
    with pytest.raises(ValueError, match="rotation"):
        required_face_size(cam, torch.diag(torch.tensor([1.0, 1.0, -1.0])))
    with pytest.raises(TypeError, match="rotation"):
        required_face_size(cam, torch.eye(3, dtype=torch.int64))
    with pytest.raises(ValueError, match="supersample"):
        required_face_size(cam, supersample=0)
    with pytest.raises(ValueError, match="criterion"):
        required_face_size(cam, criterion="best")


# --------------------------------------------------------------------------------------------
# visible_faces
# --------------------------------------------------------------------------------------------

SIDES = {"left", "right", "up", "down"}


def test_forward_fisheye_never_needs_the_back_face():
    cam = fisheye((96, 96), fov=math.radians(190))
    needed = visible_faces(cam)
    assert needed.shape == (6,) and needed.dtype == torch.bool
    assert names(needed) == {"front"} | SIDES
    # Same answer on a finer cube and with a bicubic reach: the rim is 95 deg from the axis,
    # the back face starts 135 deg from it.
    assert names(visible_faces(cam, pad=2, face_size=200)) == {"front"} | SIDES


def test_camera_identical_to_a_face():
    cam = face_camera(32)
    # Bilinear: the outermost centres land at uv = 0 and F - 1 and read only the face's own
    # texels; the corners lie on the seams and enter no other face.
    assert names(visible_faces(cam)) == {"front"}
    assert names(visible_faces(cam, pad=1, face_size=32)) == {"front"}
    assert names(visible_faces(cam, pad=0, face_size=32)) == {"front"}
    # A finer cube: the centres land at uv = 0.5, still inside.
    assert names(visible_faces(cam, face_size=64)) == {"front"}
    # Bicubic reach (pad 2) at uv = 0 reads texel -1: the border, resampled from the neighbours.
    assert names(visible_faces(cam, pad=2, face_size=32)) == {"front"} | SIDES
    # A coarser cube: the centres land at uv = -0.25 and read the border.
    assert names(visible_faces(cam, face_size=16)) == {"front"} | SIDES


def test_footprint_between_centres_counts():
    # A slightly wider pinhole: centres at x = -15.5 / 15.9 inside the face, corners at
    # -16 / 15.9 beyond its edge (0.1 texel into the neighbour).
    cam = face_camera(32, focal=15.9)
    assert names(visible_faces(cam, pad=0, face_size=32)) == {"front"} | SIDES
    # Without the corners' contribution nothing else would be read with pad 0: check that the
    # centres alone stay on the front face.
    rays, valid = cam.ray_grid()
    face, _ = ot.cubemap.ray_to_face(rays[valid], 32)
    assert set(face.tolist()) == {FACES.index("front")}


@pytest.mark.parametrize("looking, missing", [("down", "up"), ("up", "down")])
def test_catadioptric_needs_five_faces(looking, missing):
    cam, rotation = catadioptric((96, 96), looking=looking)
    needed = visible_faces(cam, rotation)
    assert names(needed) == set(FACES) - {missing}


def test_rotations_move_the_needed_faces():
    cam = fisheye((64, 64), fov=math.radians(190))
    yaw_right = yaw_pitch_roll_to_matrix(math.pi / 2, 0.0, 0.0)
    assert names(visible_faces(cam, yaw_right)) == set(FACES) - {"left"}
    look_up = yaw_pitch_roll_to_matrix(0.0, math.pi / 2, 0.0)
    assert names(visible_faces(cam, look_up)) == set(FACES) - {"down"}
    # A batch: (B, 6), row by row the single answers; each rig rotation drops the face opposite.
    rigs = face_rotations()
    batch = visible_faces(cam, rigs, face_size=64)
    assert batch.shape == (6, 6)
    opposite = {"front": "back", "back": "front", "left": "right", "right": "left",
                "up": "down", "down": "up"}
    for k, face in enumerate(FACES):
        assert names(batch[k]) == set(FACES) - {opposite[face]}
        assert torch.equal(batch[k], visible_faces(cam, rigs[k], face_size=64))


def test_narrow_fisheye_needs_only_its_face():
    cam = fisheye((64, 64), fov=math.radians(60))
    assert names(visible_faces(cam)) == {"front"}
    tilted = yaw_pitch_roll_to_matrix(0.0, 0.0, 0.7)  # roll about the axis: still the front
    assert names(visible_faces(cam, tilted)) == {"front"}
    # Turned 40 degrees right, the 30-degree half-angle crosses the seam at 45 degrees.
    turned = yaw_pitch_roll_to_matrix(math.radians(40), 0.0, 0.0)
    assert names(visible_faces(cam, turned)) == {"front", "right"}


def test_visible_faces_entry_checks():
    cam = fisheye((16, 16))
    with pytest.raises(TypeError, match="camera"):
        visible_faces(None)
    with pytest.raises(ValueError, match="pad"):
        visible_faces(cam, pad=-1)
    with pytest.raises(TypeError, match="face_size"):
        visible_faces(cam, face_size=16.0)
    with pytest.raises(ValueError, match="eps"):
        visible_faces(cam, eps=0.0)


def test_an_image_too_large_for_memory_is_a_memory_error_naming_its_size():
    """2^24 x 2^24 pixels: more than any address space holds, so the refusal is certain on
    every machine; before issue 46, torch's raw `can't allocate ... bytes`."""
    camera = fisheye((2 ** 24, 2 ** 24))
    for call in (camera.pixel_grid, camera.ray_grid, camera.field_of_view,
                 lambda: ot.OmniProjection(camera, face_size=8)(torch.rand(1, 6, 3, 8, 8))):
        with pytest.raises(MemoryError, match=r"image_size \(16777216, 16777216\): the ray grid "
                                              r"of 281,474,976,710,656 pixels needs at least "):
            call()
    for call in (required_face_size, visible_faces, face_size_map):
        with pytest.raises(MemoryError, match=r"image_size \(16777216, 16777216\): planning "
                                              r"its cube faces needs about [\d,.]+ GB"):
            call(camera)


@pytest.mark.parametrize("face_size, pad", [(1, 1), (2, 2), (5, 1), (16, 2), (64, 1)])
def test_the_border_faces_are_the_border_plans(face_size, pad):
    """`visible_faces` reads the faces of each border texel from the plan's own system solved
    per face (fast); they must be the faces the border plan itself weighs above eps."""
    from omniscape_torch.cubemap.padding import border_plan
    from omniscape_torch.render.sizing import _border_faces

    plan = border_plan(face_size, pad)
    per_face = torch.zeros(len(plan.dst_index), 6, dtype=torch.float64).scatter_add_(
        1, plan.src_index // face_size ** 2, plan.weight)
    for eps in (1e-6, 1e-3, 0.2):
        dst, faces = _border_faces(face_size, pad, eps)
        assert torch.equal(dst, plan.dst_index)
        assert torch.equal(faces, per_face > eps), eps
