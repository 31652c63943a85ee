"""Reprojection, panoramas to cubemaps, and labels on the real CARLA frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.io import (CLASSES, IGNORE_INDEX, PALETTE, colorize, palette_to_labels,
                                read_image, to_float, write_image)

from conftest import OCAMCALIB_FILE, SHARED_DATA

F64 = torch.float64
PANO = SHARED_DATA / "omniscape_equirect"


def texture(d):
    """A smooth function on the sphere (degree <= 2 spherical harmonics), written out here."""
    x, y, z = d.unbind(-1)
    return torch.stack((0.5 + 0.3 * x + 0.2 * y * z, 0.4 - 0.25 * z + 0.3 * x * y,
                        0.3 + 0.2 * (3 * z * z - 1) + 0.1 * x), dim=0)


def pano_of(fn, width, height):
    """(1, 3, H, W) panorama of ``fn`` at pixel-centre directions (lon right, lat down)."""
    v, u = torch.meshgrid(torch.arange(height, dtype=F64), torch.arange(width, dtype=F64),
                          indexing="ij")
    lon = (u - (width - 1) / 2) * 2 * math.pi / width
    lat = (v - (height - 1) / 2) * math.pi / height
    d = torch.stack((torch.cos(lat) * torch.sin(lon), torch.sin(lat),
                     torch.cos(lat) * torch.cos(lon)), -1)
    return fn(d).unsqueeze(0)


def test_pinhole_to_same_pinhole_is_identity():
    cam = ot.Camera("pinhole", torch.tensor([40.0, 42.0, 31.5, 23.5], dtype=F64), (48, 64))
    image = torch.rand(2, 3, 48, 64, dtype=F64, generator=torch.Generator().manual_seed(0))
    out, valid = ot.reproject(image, cam, cam)
    assert bool(valid.all())
    torch.testing.assert_close(out, image, atol=1e-10, rtol=0)


def test_equirect_to_cubemap_matches_the_function_including_the_seam():
    """Bilinear error bound: h^2/8 |f''| with h the panorama's pixel angle (2 pi / W rad) and
    |f''| <= 1.5 for these harmonics: 1.5 * (2 pi / 512)^2 / 8 = 2.8e-5 (x2 for the two axes)."""
    pano = pano_of(texture, 512, 256)
    cube = ot.equirect_to_cubemap(pano, 32)
    rays = ot.cubemap.face_rays(32, dtype=F64, normalize=True)  # (6, F, F, 3)
    truth = texture(rays).permute(1, 0, 2, 3)  # (6, 3, F, F)
    err = (cube[0] - truth).abs()
    assert float(err.max()) < 6e-5
    # the back face straddles the +-180 degree seam of the panorama: no wrap would break it
    back = ot.cubemap.FACES.index("back")
    assert float(err[back].max()) < 6e-5


def test_panorama_face_conventions():
    """lon 0 / lat 0 is the centre of 'front', lon +90 of 'right', lat -90 (y up) of 'up'."""
    pano = pano_of(lambda d: d.permute(2, 0, 1), 720, 360)  # texels hold their direction
    cube = ot.equirect_to_cubemap(pano, 9)  # odd F: a texel at the exact face centre
    centre = cube[0, :, :, 4, 4]  # (6, 3)
    expected = {"front": [0, 0, 1], "right": [1, 0, 0], "up": [0, -1, 0], "back": [0, 0, -1],
                "left": [-1, 0, 0], "down": [0, 1, 0]}
    # at the poles the panorama's first row is half a row (0.25 deg = 4.4e-3 rad) away
    for name, direction in expected.items():
        torch.testing.assert_close(centre[ot.cubemap.FACES.index(name)],
                                   torch.tensor(direction, dtype=F64), atol=5e-3, rtol=0)


def test_labels_are_never_blended():
    labels = torch.randint(0, 13, (1, 64, 128), generator=torch.Generator().manual_seed(1))
    cube = ot.equirect_to_cubemap(labels, 16)
    assert cube.dtype == torch.int64 and cube.shape == (1, 6, 16, 16)
    assert set(cube.unique().tolist()) <= set(labels.unique().tolist())
    fisheye = ot.presets.fisheye((40, 40), fov=math.radians(200))
    out, valid = ot.reproject(labels, ot.equirectangular_camera(128, 64), fisheye)
    assert set(out[valid[:, 0]].unique().tolist()) <= set(labels.unique().tolist())
    assert bool((out[~valid[:, 0]] == IGNORE_INDEX).all()) and bool((~valid).any())


def test_gradients_flow_to_image_and_camera():
    src = ot.Camera("equidistant", torch.tensor([10.0, 10.0, 15.5, 15.5], dtype=F64), (32, 32))
    dst = ot.Camera("pinhole", torch.tensor([8.0, 8.0, 7.5, 7.5], dtype=F64), (16, 16),
                    learnable=True)
    image = torch.rand(1, 1, 32, 32, dtype=F64, requires_grad=True)
    out, valid = ot.reproject(image, src, dst)
    out.sum().backward()
    assert float(image.grad.abs().sum()) > 0 and float(dst.params.grad.abs().sum()) > 0
    assert bool(torch.isfinite(dst.params.grad).all())


def test_real_fisheye_to_pinhole_keeps_straight_lines_straight():
    """The corridor of the real OCamCalib image: the pinhole view has more long straight
    segments (doors, tiles) than the fisheye image over the same field, where they curve."""
    cv2 = pytest.importorskip("cv2")
    fisheye = ot.Camera.from_ocamcalib(OCAMCALIB_FILE, dtype=torch.float32)
    image = to_float(read_image(OCAMCALIB_FILE.parent / "img0.jpg")).unsqueeze(0)
    pinhole = ot.Camera("pinhole", [300.0, 300.0, 399.5, 299.5], (600, 800))
    view, valid = ot.reproject(image, fisheye, pinhole)
    assert float(valid.float().mean()) > 0.99

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


def test_palette_and_real_semantic_frame():
    assert len(CLASSES) == 13 and PALETTE.shape == (13, 3)
    assert tuple(PALETTE[CLASSES.index("Road")]) == (128, 64, 128)  # CARLA's road colour
    rgb = read_image(PANO / "carla_left_semantic_palette_quantized.png")
    labels = palette_to_labels(rgb)
    # GIF quantization moves colours a little: most pixels sit near a palette colour
    near = palette_to_labels(rgb, max_distance=30.0)
    assert float((near != IGNORE_INDEX).float().mean()) > 0.8
    # road is the most frequent class of the lower half of a street-level panorama
    lower = labels[labels.shape[0] // 2:]
    assert int(torch.bincount(lower.flatten(), minlength=13).argmax()) == CLASSES.index("Road")
    # colorize inverts the mapping on palette colours exactly
    ids = torch.arange(13).view(1, 13)
    assert torch.equal(palette_to_labels(colorize(ids)), ids)
    assert tuple(colorize(torch.tensor([[IGNORE_INDEX]]))[0, 0]) == (255, 255, 255)


def test_image_io_round_trip(tmp_path):
    image = (np.arange(4 * 5 * 3) % 256).astype(np.uint8).reshape(4, 5, 3)
    path = write_image(tmp_path / "a.png", image)
    assert np.array_equal(read_image(path).numpy(), image)
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]  # no temporary left behind
    with pytest.raises(TypeError, match="uint8"):
        write_image(tmp_path / "b.png", image.astype(np.float32))
    with pytest.raises(FileNotFoundError):
        read_image(tmp_path / "missing.png")


def test_bad_input():
    cam = ot.Camera("pinhole", [4.0, 4.0, 3.5, 3.5], (8, 8))
    with pytest.raises(ValueError, match="does not match the camera's image_size"):
        ot.reproject(torch.rand(1, 3, 9, 8), cam, cam)
    with pytest.raises(ValueError, match="interpolation"):
        ot.reproject(torch.rand(1, 3, 8, 8), cam, cam, interpolation="cubic")
    with pytest.raises(ValueError, match="rotation"):
        ot.reproject(torch.rand(1, 3, 8, 8), cam, cam, rotation=torch.eye(4))
    with pytest.raises(ValueError, match="face_size"):
        ot.equirect_to_cubemap(torch.rand(1, 3, 8, 16), 0)
