"""Tests of omniscape_torch.render.kernels.cone.read_texels: the texels a layer reads.

The oracle is the layer itself: a cube whose texels outside the set hold noise gives the same
images, bit for bit, as the cube itself (RGB bilinear, depth and labels nearest, the border
resampled across the seams), on the C++ route and on torch's. The taps' C++ op against its NumPy
twin: the same texels on rays made to fall on seams and texel boundaries.
"""

from __future__ import annotations

import math
import re

import pytest
import torch

from omniscape_torch.cameras import presets
from omniscape_torch.cubemap.cone import camera_cone, cone_texels
from omniscape_torch.render.kernels import available
from omniscape_torch.render.kernels.cone import cone_taps, read_texels
from omniscape_torch.render.layer import OmniProjection


def _rotation(yaw: float, pitch: float, roll: float) -> torch.Tensor:
    cy, sy, cp, sp, cr, sr = (f(a) for a in (yaw, pitch, roll) for f in (math.cos, math.sin))
    rz = torch.tensor([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]])
    rx = torch.tensor([[1.0, 0, 0], [0, cp, -sp], [0, sp, cp]])
    ry = torch.tensor([[cy, 0, sy], [0, 1.0, 0], [-sy, 0, cy]])
    return (ry @ rx @ rz).float()


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("supersample", [1, 2])
@pytest.mark.parametrize("camera", ["fisheye", "catadioptric"])
def test_noise_outside_the_read_texels_changes_no_pixel(camera, supersample, backend):
    size, F = (40, 40), 48   # a cube finer than the image: many texels no tap reads
    cam = presets.fisheye(size) if camera == "fisheye" else presets.catadioptric(size)[0]
    layer = OmniProjection(cam, F, supersample=supersample, fused_grid=False, backend=backend)
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(1, 6, 3, F, F, generator=g)
    depth = torch.rand(1, 6, F, F, generator=g) * 50 + 1
    labels = torch.randint(0, 13, (1, 6, F, F), generator=g)
    rays_s, valid_s, rays_c, valid_c = layer.camera_rays()
    for rotation in (None, _rotation(0.3, -0.2, 0.1), _rotation(math.pi / 4, 0.0, 0.0)):
        read = read_texels(rays_s, valid_s, rotation, F, layer.pad, backend=backend)
        read |= read_texels(rays_c, valid_c, rotation, F, layer.pad, backend=backend)
        # fewer than every texel in the camera's cone, and none outside it
        axis = torch.tensor([0.0, 0.0, 1.0]) if rotation is None else rotation[:, 2]
        cone = cone_texels(F, axis, camera_cone(cam, F))
        assert not (read & ~cone).any()
        assert read.sum() < cone.sum()
        keep = read.view(1, 6, 1, F, F)
        noisy = dict(rgb=torch.where(keep, rgb, torch.rand(rgb.shape, generator=g)),
                     depth=torch.where(keep[:, :, 0], depth,
                                       torch.rand(depth.shape, generator=g) * 900),
                     labels=torch.where(keep[:, :, 0], labels, torch.randint(
                         0, 13, labels.shape, generator=g)))
        with torch.no_grad():
            a = layer.render(rgb=rgb, depth=depth, labels=labels, rotation=rotation)
            b = layer.render(rotation=rotation, **noisy)
        for key in ("rgb", "depth", "labels", "valid"):
            assert torch.equal(a[key], b[key]), (key, rotation)


def test_rays_on_a_seam_read_both_faces():
    """A ray on the edge between two faces reads texels of both (the layer may pick either)."""
    F = 8
    rays = torch.tensor([[1.0, 0.0, 1.0]])   # between +x and +z
    read = read_texels(rays, torch.ones(1, dtype=torch.bool), None, F, 1)
    assert int(read.flatten(1).any(1).sum()) == 2


def _awkward_rays(n: int, seed: int) -> torch.Tensor:
    """Rays of every kind `cone_taps` must agree on: random directions, rays on seams and
    cube corners, rays whose face coordinate lies on a texel boundary (to within a
    rounding), the zero ray and rays with a NaN or an infinity."""
    g = torch.Generator().manual_seed(seed)
    rays = [torch.randn(n, 3, generator=g, dtype=torch.float64)]
    edge = torch.randn(n, 3, generator=g, dtype=torch.float64)
    edge[:, 1] = edge[:, 0].abs() * torch.where(torch.rand(n, generator=g) < 0.5, 1.0, -1.0)
    rays.append(edge)                                          # |x| == |y|: on a seam
    grid = torch.randint(-8, 9, (n, 2), generator=g).double() / 8   # texel boundaries at F = 16
    rays.append(torch.cat([grid, torch.ones(n, 1, dtype=torch.float64)], 1))
    rays.append(torch.tensor([[0.0, 0.0, 0.0], [float("nan"), 0.0, 1.0],
                              [0.0, float("inf"), 1.0], [1.0, 1.0, 1.0], [-1.0, 1.0, -1.0]],
                             dtype=torch.float64))
    return torch.cat(rays)


@pytest.mark.skipif(not available(), reason="the C++ kernels are not built here")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("pad", [0, 1, 2])
def test_cone_taps_cpp_and_numpy_agree(dtype, pad):
    rays = _awkward_rays(400, seed=pad).to(dtype)
    valid = torch.rand(rays.shape[0], generator=torch.Generator().manual_seed(3)) < 0.9
    for rotation in (None, _rotation(0.3, -0.2, 0.1).double(), _rotation(math.pi / 4, 0, 0)):
        for mask in (None, valid):
            a = cone_taps(rays, mask, rotation, 16, pad, 1e-3, 1e-5, backend="cpp")
            b = cone_taps(rays, mask, rotation, 16, pad, 1e-3, 1e-5, backend="torch")
            assert a.shape == b.shape == (6, 16 + 2 * pad + 2, 16 + 2 * pad + 2)
            assert a.any() and (a == b).all(), (rotation, mask is None)


def test_cone_taps_ignore_rays_that_are_not_finite():
    bad = torch.tensor([[float("nan"), 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, -float("inf"), 1.0]])
    for backend in ("auto", "torch"):
        assert not cone_taps(bad, None, None, 8, 1, 1e-3, 1e-5, backend=backend).any()


@pytest.mark.slow   # about 3 s in a fresh process: opcheck's schema test warms up on the first op
@pytest.mark.skipif(not available(), reason="the C++ kernels are not built here")
def test_opcheck_cone_taps():
    m = 8 + 2 * 1 + 2
    args = (_awkward_rays(20, 0).float(), torch.ones(65, dtype=torch.bool),
            torch.eye(3, dtype=torch.float64), torch.tensor([[3, 2, 1], [-3, 2, -1], [-1, 2, 3],
                                                             [1, 2, -3], [-2, 3, 1], [2, -3, 1]]),
            8, 1, 1e-3, 1.0 - 1e-5, torch.zeros(6, m, m, dtype=torch.bool))
    torch.library.opcheck(torch.ops.omniscape_torch.cone_taps, args)


@pytest.mark.parametrize("kwargs, message", [
    (dict(rays=torch.zeros(4, 2)), "rays: expected a (..., 3) float32 or float64"),
    (dict(rays=torch.zeros(4, 3, dtype=torch.int64)), "rays: expected"),
    (dict(valid=torch.ones(3, dtype=torch.bool)), "valid: expected a bool tensor of shape (4,)"),
    (dict(valid=torch.ones(4)), "valid: expected a bool tensor"),
    (dict(rotation=torch.eye(4)), "rotation: expected a (3, 3) floating tensor or None"),
    (dict(rotation=torch.eye(3, dtype=torch.int64)), "rotation: expected a (3, 3) floating"),
    (dict(face_size=0), "face_size: expected an integer >= 1"),
    (dict(pad=-1), "pad: expected an integer >= 0"),
    (dict(tap_margin=0.7), "tap_margin: expected a value in [0, 0.5)"),
])
def test_cone_taps_name_the_bad_argument(kwargs, message):
    args = dict(rays=torch.ones(4, 3), valid=None, rotation=None, face_size=8, pad=1,
                tap_margin=1e-3, seam_margin=1e-5)
    args.update(kwargs)
    with pytest.raises(ValueError, match=re.escape(message)):
        cone_taps(**args)
