"""Reprojection between cameras, and panoramas to cubemaps, against analytic oracles.

Oracles written here, independently of the code under test: panoramas of known functions of the
direction (low-order spherical harmonics; the direction itself), the face table of DESIGN.md,
finite differences for gradients, per-camera loops for batches, and the real fisheye image.
(Palette, labels and image I/O: ``test_labels.py``.)
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.io import IGNORE_INDEX, read_image, to_float

from conftest import DESIGN_TABLE, OCAMCALIB_FILE

F64 = torch.float64



def texture(d):
    """A smooth function on the sphere (degree <= 2 spherical harmonics), written out here.

    Second derivatives along longitude and latitude (worked out by hand from x = cos(lat)
    sin(lon), y = sin(lat), z = cos(lat) cos(lon)) are at most 0.7, 0.85 and 1.3 per channel.
    """
    x, y, z = d.unbind(-1)
    return torch.stack((0.5 + 0.3 * x + 0.2 * y * z, 0.4 - 0.25 * z + 0.3 * x * y,
                        0.3 + 0.2 * (3 * z * z - 1) + 0.1 * x), dim=0)


def direction(lon, lat):
    return torch.stack((torch.cos(lat) * torch.sin(lon), torch.sin(lat),
                        torch.cos(lat) * torch.cos(lon)), -1)


def pano_of(fn, width, height):
    """(1, C, H, W) panorama of ``fn`` at pixel-centre directions (lon right, lat down)."""
    v, u = torch.meshgrid(torch.arange(height, dtype=F64), torch.arange(width, dtype=F64),
                          indexing="ij")
    lon = (u - (width - 1) / 2) * 2 * math.pi / width
    lat = (v - (height - 1) / 2) * math.pi / height
    return fn(direction(lon, lat)).unsqueeze(0)


def rot_y(angle):
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=F64)


def rot_z(angle):
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=F64)


# --------------------------------------------------------------------------------------------
# identity and analytic panoramas
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("interpolation", ["nearest", "bilinear", "bicubic"])
def test_pinhole_to_same_pinhole_is_identity(interpolation):
    cam = ot.Camera("pinhole", torch.tensor([40.0, 42.0, 31.5, 23.5], dtype=F64), (48, 64))
    image = torch.rand(2, 3, 48, 64, dtype=F64, generator=torch.Generator().manual_seed(0))
    out, valid = ot.reproject(image, cam, cam, interpolation=interpolation)
    assert bool(valid.all())
    # unproject-then-project returns every pixel centre to ~1e-13 px
    torch.testing.assert_close(out, image, atol=1e-10, rtol=0)


def test_equirect_to_cubemap_matches_the_function_including_the_seam():
    """Bilinear error bound: (h_lon^2 max|f_lon lon| + h_lat^2 max|f_lat lat|) / 8 with
    h = 2 pi / W = pi / H = 0.0123 rad and max |f''| <= 1.3 (see ``texture``):
    1.3 * 2 * 0.0123^2 / 8 = 4.9e-5 (the up/down faces' texels stay 2.5 deg from the poles,
    outside the clamped half row). Measured: 3.8e-5 (front/back), 1.5e-5 .. 2.0e-5 elsewhere."""
    pano = pano_of(texture, 512, 256)
    cube = ot.equirect_to_cubemap(pano, 32)
    assert cube.shape == (1, 6, 3, 32, 32) and cube.dtype == F64
    rays = ot.cubemap.face_rays(32, dtype=F64, normalize=True)  # (6, F, F, 3)
    truth = texture(rays).permute(1, 0, 2, 3)  # (6, 3, F, F)
    err = (cube[0] - truth).abs()
    bound = 1.3 * 2 * (2 * math.pi / 512) ** 2 / 8
    assert float(err.max()) < bound
    # the back face's middle columns straddle the +-180 degree seam: clamping there instead
    # of wrapping would give 0.5 px * |df/dlon| * h ~ 2e-3, forty times the bound
    back = ot.cubemap.FACES.index("back")
    assert float(err[back, :, :, 14:18].max()) < bound
    # faces' edges (where the cubemap's seams are): same bound
    edges = torch.zeros(32, 32, dtype=torch.bool)
    edges[[0, -1], :] = edges[:, [0, -1]] = True
    assert float(err[..., edges].max()) < bound


@pytest.mark.parametrize("interpolation, bound", [("bilinear", 4.9e-5), ("bicubic", 1e-3)])
def test_sampling_is_continuous_across_the_seam(interpolation, bound):
    """Dense rays around lon = +-180 deg: a panorama of 509 columns, turned half a revolution,
    samples the 512-column source at every fractional offset, on both sides of the seam and
    within half a pixel of it (where clamping would err by ~2e-3) and within 2 px (where bicubic
    reads the far side). Bounds: bilinear as above; bicubic as measured below (4.8e-4)."""
    pano = pano_of(texture, 512, 256)
    src = ot.equirectangular_camera(512, 256, dtype=F64)
    dst = ot.equirectangular_camera(509, 254, dtype=F64)
    rotation = rot_y(math.pi + 1e-3)
    # point samples: the bounds are the interpolations' own (509 of 512 columns minify by
    # 0.6%, which the prefilter would average)
    out, valid = ot.reproject(pano, src, dst, rotation=rotation, interpolation=interpolation,
                              antialias=False)
    assert bool(valid.all())
    rays, _ = dst.ray_grid()
    rays = rays @ rotation.T  # in the source frame
    truth = texture(rays)
    lon = torch.atan2(rays[..., 0], rays[..., 2])
    lat = torch.asin(rays[..., 1].clamp(-1, 1))
    seam = (math.pi - lon.abs()) * 512 / (2 * math.pi) < 2.5  # within 2.5 source pixels
    rows = lat.abs() < math.pi / 2 - 2 * math.pi / 256  # away from the clamped pole rows
    assert int((seam & rows).sum()) > 1000
    err = (out[0] - truth).abs()
    assert float(err[:, seam & rows].max()) < bound
    assert float(err[:, seam & rows].max()) <= 1.05 * float(err[:, ~seam & rows].max())


@pytest.mark.parametrize("interpolation", ["nearest", "bilinear", "bicubic"])
def test_seam_equals_the_middle_of_the_panorama_rolled_half_a_turn(interpolation):
    """Exact oracle for the wrap, on noise: rolling a panorama by W / 2 columns turns it by 180
    degrees about y, so sampling across its seam must equal sampling the rolled panorama in its
    middle, where no wrapping is involved (to float64 round-off of the pixel positions)."""
    gen = torch.Generator().manual_seed(6)
    pano = torch.rand(1, 2, 40, 80, dtype=F64, generator=gen)
    src = ot.equirectangular_camera(80, 40, dtype=F64)
    dst = ot.Camera("pinhole", torch.tensor([30.0, 30.0, 23.5, 19.5], dtype=F64), (40, 48))
    behind = rot_y(math.pi + 0.013) @ rot_z(0.2)  # looks across the seam, tilted
    out, valid = ot.reproject(pano, src, dst, rotation=behind, interpolation=interpolation)
    rolled = torch.roll(pano, 40, dims=-1)
    ref, ref_valid = ot.reproject(rolled, src, dst, rotation=rot_y(math.pi) @ behind,
                                  interpolation=interpolation)
    assert bool(valid.all()) and bool(ref_valid.all())
    torch.testing.assert_close(out, ref, atol=1e-9, rtol=0)


def test_nearest_and_bicubic_errors():
    """Nearest: half a pixel diagonal times |grad f| <= 0.5 sqrt(2) h 0.8 = 7e-3 (measured
    4.5e-3). PyTorch's bicubic (Keys, a = -0.75, as OpenCV's INTER_CUBIC) does not reproduce
    linear functions: first-order, error ~ 0.05 h |grad f| per axis; measured 4.8e-4, ten times
    bilinear's, so bilinear is the accurate choice on smooth data."""
    pano = pano_of(texture, 512, 256)
    truth = texture(ot.cubemap.face_rays(32, dtype=F64, normalize=True)).permute(1, 0, 2, 3)
    h = 2 * math.pi / 512
    nearest = (ot.equirect_to_cubemap(pano, 32, interpolation="nearest")[0] - truth).abs()
    assert float(nearest.max()) < 0.5 * math.sqrt(2) * h * 0.8
    bicubic = (ot.equirect_to_cubemap(pano, 32, interpolation="bicubic")[0] - truth).abs()
    assert float(bicubic.max()) < 1e-3
    back = ot.cubemap.FACES.index("back")  # the seam is wrapped for bicubic too
    assert float(bicubic[back].max()) <= 1.01 * float(bicubic[0].max())


def test_panorama_face_conventions():
    """lon 0 / lat 0 is the centre of 'front', lon +90 of 'right', lat -90 (y up) of 'up'; each
    face's image-right and image-down are DESIGN.md's r and b."""
    pano = pano_of(lambda d: d.permute(2, 0, 1), 720, 360)  # texels hold their direction
    cube = ot.equirect_to_cubemap(pano, 9)  # odd F: a texel at the exact face centre
    expected = {"front": [0, 0, 1], "right": [1, 0, 0], "up": [0, -1, 0], "back": [0, 0, -1],
                "left": [-1, 0, 0], "down": [0, 1, 0]}
    for name, (a, b, r) in DESIGN_TABLE.items():
        face = cube[0, ot.cubemap.FACES.index(name)]  # (3, F, F)
        assert list(a) == expected[name]
        # at the poles the panorama's first row is half a row (0.25 deg = 4.4e-3 rad) away
        torch.testing.assert_close(face[:, 4, 4], torch.tensor(a, dtype=F64), atol=5e-3, rtol=0)
        # one texel right / down moves along r / b by 1 / f = 2 / F (tangent plane at a)
        right = (face[:, 4, 5] - face[:, 4, 3]) / 2
        down = (face[:, 5, 4] - face[:, 3, 4]) / 2
        step = math.atan(2 / 9)
        torch.testing.assert_close(right, step * torch.tensor(r, dtype=F64), atol=6e-3, rtol=0)
        torch.testing.assert_close(down, step * torch.tensor(b, dtype=F64), atol=6e-3, rtol=0)


def test_cubemap_is_reproject_to_each_rotated_face_pinhole():
    """equirect_to_cubemap is reproject with dst = the face pinhole and rotation = the face's
    rig rotation (face rays into the cube/panorama frame), point samples both
    (``antialias=False``: 12 px faces of a 128 px panorama minify it)."""
    pano = pano_of(texture, 128, 64)
    cube = ot.equirect_to_cubemap(pano, 12)
    face_cam = ot.Camera("pinhole", torch.tensor([6.0, 6.0, 5.5, 5.5], dtype=F64), (12, 12))
    rotations = ot.cubemap.face_rotations(dtype=F64)
    for k in range(6):
        out, valid = ot.reproject(pano, ot.equirectangular_camera(128, 64, dtype=F64), face_cam,
                                  rotation=rotations[k], antialias=False)
        assert bool(valid.all())
        torch.testing.assert_close(cube[:, k], out, atol=1e-12, rtol=0)


def test_partial_panorama_does_not_wrap():
    """A 180-degree equirectangular image's left and right edges are different meridians:
    nothing of the right edge may leak into the left one."""
    w, h = 64, 32
    half = ot.Camera("equirectangular", torch.tensor([w / math.pi, h / math.pi, (w - 1) / 2,
                                                      (h - 1) / 2], dtype=F64), (h, w))
    image = torch.zeros(1, 1, h, w, dtype=F64)
    image[..., -1] = 1.0
    shifted = ot.Camera("equirectangular", half.params + torch.tensor([0, 0, 0.3, 0],
                                                                       dtype=F64), (h, w))
    out, valid = ot.reproject(image, half, shifted)
    assert bool(valid[..., 0].all())  # u = -0.3 is inside the image (edge at -0.5)
    assert float(out[0, 0, :, 0].abs().max()) == 0.0
    # the same image as a full panorama does wrap: 0.3 of the last column reaches column 0
    full = ot.equirectangular_camera(w, h, dtype=F64)
    shifted_full = ot.Camera("equirectangular", full.params + torch.tensor([0, 0, 0.3, 0],
                                                                           dtype=F64), (h, w))
    out, _ = ot.reproject(image, full, shifted_full)
    torch.testing.assert_close(out[0, 0, :, 0], torch.full((h,), 0.3, dtype=F64))


# --------------------------------------------------------------------------------------------
# labels
# --------------------------------------------------------------------------------------------

def test_labels_are_never_blended():
    labels = torch.randint(0, 13, (1, 64, 128), generator=torch.Generator().manual_seed(1))
    labels = torch.where(labels > 6, 3 * labels, labels)  # gaps: blending would show
    cube = ot.equirect_to_cubemap(labels, 16, interpolation="bilinear")
    assert cube.dtype == torch.int64 and cube.shape == (1, 6, 16, 16)
    assert set(cube.unique().tolist()) <= set(labels.unique().tolist())
    fisheye = ot.presets.fisheye((40, 40), fov=math.radians(200))
    out, valid = ot.reproject(labels, ot.equirectangular_camera(128, 64), fisheye,
                              interpolation="bicubic")
    assert out.shape == (1, 40, 40) and valid.shape == (1, 1, 40, 40)
    assert set(out[valid[:, 0]].unique().tolist()) <= set(labels.unique().tolist())
    assert bool((out[~valid[:, 0]] == IGNORE_INDEX).all()) and bool((~valid).any())


def test_labels_keep_channels_and_follow_the_nearest_pixel():
    """Integer (B, C, H, W) keeps its C channels; labels equal the image's nearest sampling."""
    gen = torch.Generator().manual_seed(2)
    ids = torch.randint(0, 200, (2, 3, 32, 64), generator=gen, dtype=torch.uint8)
    src = ot.equirectangular_camera(64, 32, dtype=F64)
    dst = ot.presets.fisheye((24, 24), fov=math.radians(180), dtype=F64)
    # uint8 is an image unless labels=True says it holds class ids
    out, valid = ot.reproject(ids, src, dst, rotation=rot_y(2.9), labels=True)  # across the seam
    assert out.shape == (2, 3, 24, 24) and out.dtype == torch.int64
    as_float, _ = ot.reproject(ids.to(F64), src, dst, rotation=rot_y(2.9),
                               interpolation="nearest")
    assert torch.equal(out[valid.expand_as(out)], as_float[valid.expand_as(out)].long())
    # other integer dtypes are labels by default
    wide, _ = ot.reproject(ids.to(torch.int16), src, dst, rotation=rot_y(2.9))
    assert torch.equal(wide, out)
    with pytest.raises(TypeError, match="to_float"):
        ot.reproject(ids.to(torch.int16), src, dst, labels=False)
    with pytest.raises(TypeError, match="labels=True"):
        ot.reproject(ids.to(F64), src, dst, labels=True)


# --------------------------------------------------------------------------------------------
# 8-bit and half-precision images
# --------------------------------------------------------------------------------------------

def _u8_pano(seed=3, shape=(2, 3, 32, 64)):
    return torch.randint(0, 256, shape, generator=torch.Generator().manual_seed(seed),
                         dtype=torch.uint8)


@pytest.mark.parametrize("interpolation", ["nearest", "bilinear", "bicubic"])
def test_uint8_image_within_a_level_of_the_float_path(interpolation):
    """A uint8 image is an image (labels=None): sampled in float32 and rounded half up and
    saturated; the reference is the float32 image of its levels through the same call."""
    pano = _u8_pano()
    src = ot.equirectangular_camera(64, 32)
    dst = ot.presets.fisheye((24, 24), fov=math.radians(200))
    out, valid = ot.reproject(pano, src, dst, rotation=rot_y(2.9).float(),
                              interpolation=interpolation)
    ref, ref_valid = ot.reproject(pano.float(), src, dst, rotation=rot_y(2.9).float(),
                                  interpolation=interpolation)
    assert out.dtype == torch.uint8 and out.shape == (2, 3, 24, 24)
    assert torch.equal(valid, ref_valid) and bool(valid.any()) and bool((~valid).any())
    expected = torch.floor(ref.clamp(0, 255) + 0.5)   # half up, saturated (bicubic overshoots)
    assert float((out.float() - expected).abs().max()) <= 1
    assert float((out.float() - expected).abs().mean()) < 0.01   # nearly all exact
    if interpolation == "nearest":
        assert torch.equal(out.float(), ref)   # levels copied
    assert bool((out[~valid.expand_as(out)] == 0).all())
    # a floating out_dtype: scaled to [0, 1], the float path on the image / 255
    scaled, _ = ot.reproject(pano, src, dst, rotation=rot_y(2.9).float(),
                             interpolation=interpolation, out_dtype=torch.float64)
    unit, _ = ot.reproject(pano.float() / 255, src, dst, rotation=rot_y(2.9).float(),
                           interpolation=interpolation)
    assert scaled.dtype == torch.float64
    torch.testing.assert_close(scaled, unit.double(), atol=1e-6, rtol=0)


def test_uint8_equirect_to_cubemap_and_labels_true():
    pano = _u8_pano(shape=(1, 3, 32, 64))
    cube = ot.equirect_to_cubemap(pano, 16)
    ref = ot.equirect_to_cubemap(pano.float() / 255, 16)
    assert cube.dtype == torch.uint8 and cube.shape == (1, 6, 3, 16, 16)
    assert float((cube.float() - torch.floor(ref * 255 + 0.5)).abs().max()) <= 1
    as_float = ot.equirect_to_cubemap(pano, 16, out_dtype=torch.float32)
    torch.testing.assert_close(as_float, ref, atol=1e-6, rtol=0)
    # uint8 class ids with labels=True: nearest, exact, int64 (the int64 ids' result)
    ids = pano[:, 0] % 13
    cube_ids = ot.equirect_to_cubemap(ids, 16, labels=True)
    assert cube_ids.dtype == torch.int64
    assert torch.equal(cube_ids, ot.equirect_to_cubemap(ids.long(), 16))
    # (B, H, W) uint8 without labels=True is ambiguous
    with pytest.raises(ValueError, match="labels=True"):
        ot.equirect_to_cubemap(ids, 16)
    with pytest.raises(ValueError, match=r"labels=True.*\(B, C, H, W\)"):
        ot.reproject(ids, ot.equirectangular_camera(64, 32), ot.presets.fisheye((8, 8)))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_images_are_sampled_with_a_float32_grid(dtype):
    """The float32 image of the same (rounded) values through the same call, rounded once to
    the image's dtype: exactly. (A grid cast to half was off by pixels, and gave NaN.)"""
    pano = pano_of(texture, 256, 128).to(dtype)
    cube = ot.equirect_to_cubemap(pano, 64)
    assert cube.dtype == dtype and bool(torch.isfinite(cube).all())
    assert torch.equal(cube, ot.equirect_to_cubemap(pano.float(), 64).to(dtype))
    fisheye = ot.presets.fisheye((32, 32), fov=math.radians(190))
    out, valid = ot.reproject(pano, ot.equirectangular_camera(256, 128), fisheye,
                              interpolation="bicubic")
    ref, _ = ot.reproject(pano.float(), ot.equirectangular_camera(256, 128), fisheye,
                          interpolation="bicubic")
    assert out.dtype == dtype and torch.equal(out, ref.to(dtype))
    wide, _ = ot.reproject(pano, ot.equirectangular_camera(256, 128), fisheye,
                           interpolation="bicubic", out_dtype=torch.float32)
    assert torch.equal(wide, ref)


def test_uint8_gradients_and_bad_out_dtype():
    pano = _u8_pano(shape=(1, 3, 32, 64))
    src = ot.equirectangular_camera(64, 32)
    dst = ot.Camera("equidistant", [12.0, 12.0, 15.5, 15.5], (32, 32), learnable=True)
    params = dst.params
    with pytest.raises(TypeError, match="out_dtype"):   # uint8 out would drop the gradient
        ot.reproject(pano, src, dst)
    out, _ = ot.reproject(pano, src, dst, out_dtype=torch.float32)   # the grid's gradient
    out.sum().backward()
    assert params.grad is not None and bool(torch.isfinite(params.grad).all())
    assert float(params.grad.abs().sum()) > 0
    with torch.no_grad():
        assert ot.reproject(pano, src, dst)[0].dtype == torch.uint8
    cam = ot.Camera("pinhole", [4.0, 4.0, 3.5, 3.5], (8, 8))
    with pytest.raises(TypeError, match="out_dtype"):
        ot.reproject(torch.rand(1, 3, 8, 8), cam, cam, out_dtype=torch.uint8)
    with pytest.raises(TypeError, match="out_dtype"):
        ot.reproject(_u8_pano(shape=(1, 3, 8, 8)), cam, cam, out_dtype=torch.int32)
    with pytest.raises(ValueError, match="out_dtype"):
        ot.reproject(torch.zeros(1, 8, 8, dtype=torch.int64), cam, cam, out_dtype=torch.float32)


# --------------------------------------------------------------------------------------------
# batches and gradients
# --------------------------------------------------------------------------------------------

def test_batches_match_per_camera_loops():
    gen = torch.Generator().manual_seed(3)
    image = torch.rand(2, 3, 32, 32, dtype=F64, generator=gen)
    params = torch.tensor([[10.0, 10.0, 15.5, 15.5], [12.0, 11.0, 15.0, 16.0]], dtype=F64)
    src_b = ot.Camera("equidistant", params, (32, 32))
    dst = ot.Camera("pinhole", torch.tensor([8.0, 8.0, 7.5, 7.5], dtype=F64), (16, 16))
    dst_b = ot.Camera("pinhole", torch.tensor([[8.0, 8.0, 7.5, 7.5], [9.0, 7.0, 7.0, 8.0]],
                                              dtype=F64), (16, 16))
    rotations = torch.stack((rot_z(0.1) @ rot_y(0.2), rot_z(-0.2)))
    src = ot.Camera("equidistant", params[0], (32, 32))
    cases = {  # name: (batched call, per-sample call)
        "src": (lambda: ot.reproject(image, src_b, dst),
                lambda b: ot.reproject(image[b:b + 1], ot.Camera("equidistant", params[b],
                                                                 (32, 32)), dst)),
        "dst": (lambda: ot.reproject(image, src, dst_b),
                lambda b: ot.reproject(image[b:b + 1], src,
                                       ot.Camera("pinhole", dst_b.params[b], (16, 16)))),
        "rotation": (lambda: ot.reproject(image, src, dst, rotation=rotations),
                     lambda b: ot.reproject(image[b:b + 1], src, dst, rotation=rotations[b])),
        "one image, batched geometry": (
            lambda: ot.reproject(image[:1], src_b, dst_b, rotation=rotations),
            lambda b: ot.reproject(image[:1], ot.Camera("equidistant", params[b], (32, 32)),
                                   ot.Camera("pinhole", dst_b.params[b], (16, 16)),
                                   rotation=rotations[b])),
    }
    for name, (batched, single) in cases.items():
        out, valid = batched()
        assert out.shape == (2, 3, 16, 16) and valid.shape == (2, 1, 16, 16), name
        assert bool(valid.any()), name
        for b in range(2):
            ob, vb = single(b)
            assert torch.equal(valid[b:b + 1], vb), name
            torch.testing.assert_close(out[b:b + 1], ob, atol=1e-12, rtol=0, msg=name)
    with pytest.raises(ValueError, match="batch sizes disagree"):
        ot.reproject(torch.rand(3, 3, 32, 32, dtype=F64), src_b, dst)
    with pytest.raises(ValueError, match="batch sizes disagree"):
        ot.reproject(image, src, dst_b, rotation=torch.stack([rot_z(0.1)] * 3))


@pytest.mark.slow
def test_gradcheck_image_and_rotation():
    src = ot.Camera("pinhole", torch.tensor([6.0, 6.0, 5.5, 5.5], dtype=F64), (12, 12))
    dst = ot.Camera("pinhole", torch.tensor([4.0, 4.0, 3.5, 3.5], dtype=F64), (8, 8))
    gen = torch.Generator().manual_seed(4)
    image = torch.rand(1, 2, 12, 12, dtype=F64, generator=gen, requires_grad=True)
    rotation = (rot_z(0.05) @ rot_y(0.03)).requires_grad_(True)
    for mode in ("bilinear", "bicubic"):
        # point samples (the 8 px pinhole minifies the 12 px one: the prefilter's footprint
        # moves with the rotation without a gradient)
        assert torch.autograd.gradcheck(
            lambda img, rot: ot.reproject(img, src, dst, rotation=rot, interpolation=mode,
                                          antialias=False)[0], (image, rotation))
    # the prefilter is linear in the image: its gradient is exact
    assert torch.autograd.gradcheck(
        lambda img: ot.reproject(img, src, dst, rotation=rotation.detach())[0], (image,))
    # across the seam of a panorama too
    pano = torch.rand(1, 1, 16, 32, dtype=F64, generator=gen, requires_grad=True)
    behind = (rot_y(math.pi - 0.02) @ rot_z(0.1)).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda img, rot: ot.reproject(img, ot.equirectangular_camera(32, 16, dtype=F64), dst,
                                      rotation=rot, antialias=False)[0], (pano, behind))


@pytest.mark.parametrize("which", ["src", "dst"])
def test_gradients_flow_to_camera_params(which):
    """Autograd against central differences (step 1e-6 px: no texel boundary is crossed), of
    point samples (the 16 px pinhole minifies the 32 px source: ``antialias=False``)."""
    gen = torch.Generator().manual_seed(5)
    image = torch.rand(1, 1, 32, 32, dtype=F64, generator=gen)
    weights = torch.rand(1, 1, 16, 16, dtype=F64, generator=gen)
    p_src = torch.tensor([10.0, 10.5, 15.5, 15.2], dtype=F64)
    p_dst = torch.tensor([8.0, 8.0, 7.5, 7.5], dtype=F64)

    def loss(p, learnable=False):
        ps, pd = (p, p_dst) if which == "src" else (p_src, p)
        src = ot.Camera("equidistant", ps, (32, 32), learnable=learnable and which == "src")
        dst = ot.Camera("pinhole", pd, (16, 16), learnable=learnable and which == "dst")
        # point samples: the antialiasing taps spread with the footprint, which has no gradient
        out, _ = ot.reproject(image, src, dst, antialias=False)
        return (out * weights).sum(), (src if which == "src" else dst)

    p0 = p_src if which == "src" else p_dst
    value, cam = loss(p0, learnable=True)
    value.backward()
    eye = torch.eye(4, dtype=F64) * 1e-6
    fd = torch.stack([(loss(p0 + eye[i])[0] - loss(p0 - eye[i])[0]) / 2e-6 for i in range(4)])
    assert bool(torch.isfinite(cam.params.grad).all()) and float(cam.params.grad.abs().min()) > 0
    torch.testing.assert_close(cam.params.grad, fd, atol=1e-6, rtol=1e-6)


def test_gradients_flow_through_a_panorama_into_a_fisheye():
    pano = pano_of(texture, 64, 32).requires_grad_(True)
    fisheye = ot.presets.fisheye((20, 20), fov=math.radians(190), dtype=F64)
    fisheye = ot.Camera(fisheye.model, fisheye.params, (20, 20), fov=fisheye.fov,
                        learnable=True)
    out, valid = ot.reproject(pano, ot.equirectangular_camera(64, 32, dtype=F64), fisheye,
                              rotation=rot_y(math.pi))  # looking backwards: the seam
    out.sum().backward()
    assert bool(valid.any()) and bool((~valid).any())
    assert float(pano.grad.abs().sum()) > 0 and bool(torch.isfinite(pano.grad).all())
    assert float(fisheye.params.grad.abs().sum()) > 0
    assert bool(torch.isfinite(fisheye.params.grad).all())


# --------------------------------------------------------------------------------------------
# the real fisheye
# --------------------------------------------------------------------------------------------

def test_real_fisheye_to_pinhole_keeps_straight_lines_straight():
    """The corridor of the real OCamCalib image: the pinhole view has more long straight
    segments (doors, tiles) than the fisheye image over the same field, where they curve."""
    cv2 = pytest.importorskip("cv2")
    fisheye = ot.Camera.from_ocamcalib(OCAMCALIB_FILE, dtype=torch.float32)
    image = to_float(read_image(OCAMCALIB_FILE.parent / "img0.jpg")).unsqueeze(0)
    pinhole = ot.Camera("pinhole", [300.0, 300.0, 399.5, 299.5], (600, 800))
    view, valid = ot.reproject(image, fisheye, pinhole)
    assert view.shape == (1, 3, 600, 800) and float(valid.float().mean()) > 0.99
    assert float(view.std()) > 0.1  # not degenerate: a textured picture, not a flat one

    def long_segments(picture):
        grey = (picture.mean(0).numpy() * 255).astype(np.uint8)
        edges = cv2.Canny(grey, 50, 150)
        lines = cv2.HoughLinesP(edges, 1, np.pi / 360, 60, minLineLength=80, maxLineGap=3)
        return 0 if lines is None else len(lines.reshape(-1, 4))

    # the same field of view in the fisheye: the central 800 x 600 px around the centre
    cx, cy = (int(round(float(v))) for v in fisheye.params[:2])
    crop = image[0, :, cy - 300:cy + 300, cx - 400:cx + 400]
    straight, curved = long_segments(view[0]), long_segments(crop)
    # lines through the fisheye's centre stay straight there too, so the margin is modest
    assert straight >= 5, straight
    assert straight > curved, (straight, curved)


def test_bad_input():
    cam = ot.Camera("pinhole", [4.0, 4.0, 3.5, 3.5], (8, 8))
    with pytest.raises(ValueError, match="does not match the camera's image_size"):
        ot.reproject(torch.rand(1, 3, 9, 8), cam, cam)
    with pytest.raises(ValueError, match="interpolation"):
        ot.reproject(torch.rand(1, 3, 8, 8), cam, cam, interpolation="cubic")
    with pytest.raises(ValueError, match="rotation"):
        ot.reproject(torch.rand(1, 3, 8, 8), cam, cam, rotation=torch.eye(4))
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        ot.reproject(torch.rand(3, 8, 8), cam, cam)
    with pytest.raises(ValueError, match="face_size"):
        ot.equirect_to_cubemap(torch.rand(1, 3, 8, 16), 0)
