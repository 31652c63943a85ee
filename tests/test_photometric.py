"""Photometric calibration (``omniscape_torch.calibration.photometric``) on the built-in scene.

The target is the scene's exact ray cast through a known camera (``Town.render_rays``), not the
cube sampling that the fit renders with, so a fit can only match it by finding the camera.
Tolerances: the fit's floor on this scene is about 0.4 % of focal and 0.1 px of centre
(``benchmarks/results/photometric_convergence.md``: cube resampling at face 64 against the exact
ray cast), so 1 % and 0.5 px leave room for the other scene and image size used here.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.calibration.photometric import fit_photometric, photometric_error
from omniscape_torch.cameras.presets import yaw_pitch_roll_to_matrix
from omniscape_torch.scenes import Town

#: Numerically sensitive: CI runs this module again with OMP_NUM_THREADS=1 (.ci/run).
pytestmark = pytest.mark.numerics

SIZE, FACE = 96, 64
POSITION = torch.tensor([0.0, -1.2, 0.0])
FOCAL_TOL, CENTRE_TOL_PX, ROTATION_TOL_DEG = 0.01, 0.5, 0.5


@pytest.fixture(scope="module")
def scene():
    town = Town(1)
    return town, town.render_cubemap(POSITION, face_size=FACE)["rgb"]


def ray_cast(town: Town, camera: ot.Camera, rotation: torch.Tensor):
    """The exact target image ``(1, 3, H, W)`` (0 outside the valid area) and its mask."""
    rays, valid = camera.ray_grid()
    rgb = town.render_rays(POSITION, rays @ rotation.T)["rgb"] * valid.unsqueeze(-1)
    return rgb.permute(2, 0, 1).unsqueeze(0), valid


def perturbed(camera: ot.Camera, focal: tuple[float, float], centre: tuple[float, float]):
    p = camera.params.clone()
    p[0] *= focal[0]
    p[1] *= focal[1]
    p[2] += centre[0]
    p[3] += centre[1]
    return ot.Camera(camera.model, p, camera.image_size, fov=camera.fov,
                     blind_fov=camera.blind_fov)


def rotation_error_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    cos = (float(torch.trace(a.T @ b)) - 1) / 2
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def assert_recovered(result, truth: ot.Camera, cube, target, valid):
    fitted, true = result.camera.params, truth.params
    focal = ((fitted[:2] - true[:2]) / true[:2]).abs().max()
    centre = (fitted[2:4] - true[2:4]).abs().max()
    assert focal < FOCAL_TOL and centre < CENTRE_TOL_PX, (fitted.tolist(), true.tolist())
    torch.testing.assert_close(fitted[4:], true[4:])  # held, not fitted
    assert result.converged, result.reason
    assert result.error < result.initial_error
    # the reported error is the fitted camera's (rendered anew; its fov differs from the fit's
    # unlimited one only at the rim)
    image, _ = ot.OmniProjection(result.camera, FACE)(cube, result.rotation)
    mask = valid.reshape(1, 1, *valid.shape)
    assert float(photometric_error(image, target, mask)) == pytest.approx(result.error, abs=0.02)


@pytest.mark.slow
def test_recovers_kannala_brandt_fisheye(scene):
    town, cube = scene
    truth = ot.presets.fisheye((SIZE, SIZE), fov=math.radians(190), model="kannala_brandt",
                               distortion=(0.03, -0.01, 0.0, 0.0))
    target, valid = ray_cast(town, truth, torch.eye(3))
    guess = perturbed(truth, (1.10, 0.92), (5.0, -4.0))
    result = fit_photometric(cube, target, guess, mask=valid, progress=False)
    assert_recovered(result, truth, cube, target, valid)
    assert len(result.loss) == sum(result.level_steps) == 40 * (1 + 2 + 4)
    assert result.camera.fov == truth.fov and not result.camera.learnable


@pytest.mark.slow
def test_recovers_catadioptric_and_attitude(scene):
    town, cube = scene
    truth, rotation = ot.presets.catadioptric((SIZE, SIZE))
    target, valid = ray_cast(town, truth, rotation)
    guess = perturbed(truth, (0.91, 0.91), (-4.0, 5.0))
    tilt = yaw_pitch_roll_to_matrix(math.radians(3.0), math.radians(-2.0), math.radians(2.0))
    start = rotation @ tilt
    assert rotation_error_deg(start, rotation) > 3.0
    result = fit_photometric(cube, target, guess, rotation=start, fit_attitude=True,
                             mask=valid, loss="zncc", progress=False)
    assert_recovered(result, truth, cube, target, valid)
    assert rotation_error_deg(result.rotation, rotation) < ROTATION_TOL_DEG


@pytest.mark.slow
def test_guess_outside_the_basin_is_reported(scene):
    """The principal point 35 px off (a third of the image): the fit ends in a wrong minimum and
    says so. (Focal errors alone converge from x0.3 to x3 on this scene.)"""
    town, cube = scene
    truth = ot.presets.fisheye((SIZE, SIZE), fov=math.radians(190))
    target, valid = ray_cast(town, truth, torch.eye(3))
    result = fit_photometric(cube, target, perturbed(truth, (1.0, 1.0), (35.0, 35.0)),
                             mask=valid, progress=False)
    fitted, true = result.camera.params, truth.params
    focal = ((fitted[:2] - true[:2]) / true[:2]).abs().max()
    centre = (fitted[2:4] - true[2:4]).abs().max()
    assert focal > FOCAL_TOL or centre > CENTRE_TOL_PX  # the fit is indeed wrong ...
    assert not result.converged  # ... and not reported as converged
    assert "error" in result.reason


def test_photometric_error_against_numpy_correlation():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(1, 3, 16, 20, generator=g, dtype=torch.float64)
    target = 0.5 * image + 0.3 * torch.rand(1, 3, 16, 20, generator=g, dtype=torch.float64)
    mask = torch.rand(1, 1, 16, 20, generator=g) > 0.3
    m = mask[0, 0].numpy()
    expected = 1 - np.mean([np.corrcoef(image[0, c].numpy()[m], target[0, c].numpy()[m])[0, 1]
                            for c in range(3)])
    assert float(photometric_error(image, target, mask)) == pytest.approx(expected, abs=1e-12)
    # gain and offset do not matter; an inverted image is anti-correlated
    assert float(photometric_error(2 * image + 0.1, image, mask)) == pytest.approx(0, abs=1e-12)
    assert float(photometric_error(-image, image, mask)) == pytest.approx(2, abs=1e-12)


def _inputs():
    camera = ot.presets.fisheye((32, 32))
    return torch.zeros(1, 6, 3, 20, 20), torch.zeros(1, 3, 32, 32), camera


@pytest.mark.parametrize("change, error, match", [
    (dict(cubemap=torch.zeros(1, 5, 3, 20, 20)), ValueError, "cubemap"),
    (dict(cubemap=torch.zeros(2, 6, 3, 20, 20)), ValueError, "one cubemap"),
    (dict(cubemap=torch.zeros(1, 6, 3, 20, 20, dtype=torch.int64)), TypeError, "cubemap"),
    (dict(target=torch.zeros(1, 3, 32, 30)), ValueError, "target"),
    (dict(target=torch.zeros(1, 1, 32, 32)), ValueError, "target"),
    (dict(target=torch.zeros(1, 3, 32, 32, dtype=torch.float64)), TypeError, "target"),
    (dict(target=np.zeros((1, 3, 32, 32))), TypeError, "target"),
    (dict(camera_init="equidistant"), TypeError, "camera_init"),
    (dict(camera_init=ot.Camera("equidistant", torch.ones(2, 4) * 16, (32, 32))), ValueError,
     "one camera"),
    (dict(camera_init=ot.Camera("scaramuzza", [16.0, 16.0, 1.0, 0.0, 0.0, -10.0, 0.0, 0.01],
                                (32, 32))), ValueError, "fx, fy, cx, cy"),
    (dict(mask=torch.ones(32, 31, dtype=torch.bool)), ValueError, "mask"),
    (dict(mask=torch.ones(32, 32)), TypeError, "mask"),
    (dict(mask=torch.zeros(32, 32, dtype=torch.bool)), ValueError, "mask"),
    (dict(rotation=torch.eye(4)), ValueError, "rotation"),
    (dict(rotation=torch.eye(3, dtype=torch.int64)), TypeError, "rotation"),
    (dict(levels=4), ValueError, "levels"),
    (dict(levels=0), ValueError, "levels"),
    (dict(loss="l1"), ValueError, "loss"),
    (dict(steps=2), ValueError, "steps"),
    (dict(lr=-1.0), ValueError, "lr"),
])
def test_bad_input(change, error, match):
    cubemap, target, camera = _inputs()
    args = dict(cubemap=cubemap, target=target, camera_init=camera)
    kwargs = {k: v for k, v in change.items() if k not in args}
    args.update({k: v for k, v in change.items() if k in args})
    with pytest.raises(error, match=match):
        fit_photometric(args["cubemap"], args["target"], args["camera_init"], progress=False,
                        **kwargs)
