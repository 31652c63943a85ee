"""Tests of ``ot.OmniProjection``: the cubemap -> omnidirectional layer.

Every oracle is written here, independently of the code under test: the face table literally from
DESIGN.md, texel rays from the pinhole formula of a face, our own ray -> (face, uv) by the largest
signed face axis, our own equidistant unprojection (r = f theta), and analytic scenes whose value
along any ray is known exactly (a spherical-harmonic texture, a box of planar walls, a 3D
checkerboard). The library is only called through the layer and the camera it renders with.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F_nn
from torch.func import functional_call

import omniscape_torch as ot

from conftest import DESIGN_TABLE, FACE_ORDER

f64, f32 = torch.float64, torch.float32


# Rig rotations of six simulator cameras, as the columns (r, b, a) of R: the face camera's
# OpenCV axes (right, down, forward) in the cube frame, written literally.
RIG = {
    "front": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),  # none
    "back": ((-1, 0, 0), (0, 1, 0), (0, 0, -1)),  # yaw 180 deg
    "left": ((0, 0, 1), (0, 1, 0), (-1, 0, 0)),  # yaw -90 deg (turn left)
    "right": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),  # yaw +90 deg (turn right)
    "up": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),  # pitch +90 deg (look up)
    "down": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),  # pitch -90 deg (look down)
}
#: Yaw +90 degrees (turn right): columns are the "right" face's r = -z, b = +y, a = +x.
YAW_RIGHT = ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0))


def table(dtype=f64) -> torch.Tensor:
    """(6, 3, 3): per face (a, b, r), DESIGN order."""
    return torch.tensor([DESIGN_TABLE[name] for name in FACE_ORDER], dtype=dtype)


def texel_rays(size: int, dtype=f64) -> torch.Tensor:
    """(6, F, F, 3) rays of texel centres, a-component 1: r (u - c) / f + b (v - c) / f + a."""
    f, c = size / 2, (size - 1) / 2
    t = (torch.arange(size, dtype=dtype) - c) / f
    y, x = torch.meshgrid(t, t, indexing="ij")
    a, b, r = table(dtype).unbind(1)  # [6, 3] each
    return (r[:, None, None] * x[..., None] + b[:, None, None] * y[..., None]
            + a[:, None, None])


def ref_face_uv(d: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Face whose axis a has the largest dot product with the ray, and the pinhole uv on it."""
    axes = table(d.dtype)  # [6, (a, b, r), 3]
    face = (d @ axes[:, 0].T).argmax(-1)
    a, b, r = axes[face].unbind(-2)
    depth = (a * d).sum(-1)
    f, c = size / 2, (size - 1) / 2
    uv = torch.stack((c + f * (r * d).sum(-1) / depth, c + f * (b * d).sum(-1) / depth), -1)
    return face, uv


def edge_distance(uv: torch.Tensor, size: int) -> torch.Tensor:
    """Distance in texels from uv to the nearest edge of its face (edges at -0.5 and F - 0.5)."""
    return torch.stack((uv[..., 0] + 0.5, size - 0.5 - uv[..., 0], uv[..., 1] + 0.5,
                        size - 0.5 - uv[..., 1]), -1).amin(-1)


def equidistant_rays(f: float, c: float, h: int, w: int, sub: int = 1) -> torch.Tensor:
    """(h sub, w sub, 3) unit rays of r = f theta at sub-pixel centres (pixel centres for sub=1)."""
    off = (torch.arange(sub, dtype=f64) + 0.5) / sub - 0.5
    us = (torch.arange(w, dtype=f64)[:, None] + off).reshape(-1)
    vs = (torch.arange(h, dtype=f64)[:, None] + off).reshape(-1)
    v, u = torch.meshgrid(vs, us, indexing="ij")
    mx, my = (u - c) / f, (v - c) / f
    theta = torch.sqrt(mx**2 + my**2)
    s = torch.where(theta > 0, torch.sin(theta) / theta.clamp(min=1e-300), torch.ones_like(theta))
    return torch.stack((mx * s, my * s, torch.cos(theta)), -1)


def fisheye(size: int, fov_deg: float = 190.0, *, learnable=False, dtype=f64) -> tuple:
    """A square equidistant fisheye whose fov circle touches the image edge; (camera, f, c)."""
    c = (size - 1) / 2
    f = (size / 2) / math.radians(fov_deg / 2)
    cam = ot.Camera("equidistant", torch.tensor([f, f, c, c], dtype=dtype), (size, size),
                    fov=math.radians(fov_deg), learnable=learnable)
    return cam, f, c


def theta_of(d: torch.Tensor) -> torch.Tensor:
    return torch.atan2(d[..., :2].norm(dim=-1), d[..., 2])


def smooth(d: torch.Tensor) -> torch.Tensor:
    """0.5 + 0.15 x (real spherical harmonics of degree <= 2, arbitrary coefficients): in [0, 1]."""
    x, y, z = (d / d.norm(dim=-1, keepdim=True)).unbind(-1)
    sh = (0.3 + 0.5 * x - 0.4 * y + 0.7 * z + 0.6 * x * y - 0.5 * y * z
          + 0.4 * (3 * z * z - 1) + 0.8 * x * z + 0.5 * (x * x - y * y))
    return 0.5 + 0.15 * sh


def smooth_cube(size: int, dtype=f32, channels: int = 1) -> torch.Tensor:
    """(1, 6, C, F, F) texture at texel-centre rays; channel k is the texture of a permuted ray."""
    rays = texel_rays(size)
    chans = [smooth(rays[..., [(k + i) % 3 for i in range(3)]]) for k in range(channels)]
    return torch.stack(chans, 1).unsqueeze(0).to(dtype)  # [1, 6, C, F, F]


# A box around the camera, off-centre (walls at x = -3.0 and 4.0, ...), OpenCV frame.
BOX_LO = (-3.0, -2.5, -3.6)
BOX_HI = (4.0, 3.2, 4.5)


def box_hits(d: torch.Tensor) -> torch.Tensor:
    """(..., 3): parameter t of the ray d hitting the wall it points to along each axis."""
    hi = torch.tensor(BOX_HI, dtype=d.dtype)
    lo = torch.tensor(BOX_LO, dtype=d.dtype)
    wall = torch.where(d > 0, hi, lo)
    safe = torch.where(d != 0, d, torch.ones_like(d))
    return torch.where(d != 0, wall / safe, torch.full_like(d, math.inf))


def box_t(d: torch.Tensor) -> torch.Tensor:
    """t with point = t d on the box (range if d is unit, planar depth if a . d = 1)."""
    return box_hits(d).amin(-1)


NEAR_Z, NEAR_X = 1.2, (-0.5, 0.4)  # a near plane z = 1.2, for x in [-0.5, 0.4], all y


def edge_scene_t(d: torch.Tensor) -> torch.Tensor:
    """Box plus the near plane in front of the camera."""
    t_box = box_t(d)
    dz = torch.where(d[..., 2] > 0, d[..., 2], torch.ones_like(d[..., 2]))
    t_near = NEAR_Z / dz
    x = t_near * d[..., 0]
    hit = (d[..., 2] > 0) & (x >= NEAR_X[0]) & (x <= NEAR_X[1])
    return torch.where(hit, torch.minimum(t_near, t_box), t_box)


def psnr(err: torch.Tensor, peak: float = 1.0) -> float:
    return 10 * math.log10(peak**2 / float((err**2).mean()))


def not_tie(uv: torch.Tensor, margin: float = 1e-3) -> torch.Tensor:
    """True where neither coordinate is within margin of a nearest-rounding tie (x.5)."""
    frac = uv - torch.floor(uv)
    return ((frac - 0.5).abs() > margin).all(-1)


# ------------------------------------------------------------------------------------------
# Face conventions
# ------------------------------------------------------------------------------------------
def coded_cube(size: int) -> torch.Tensor:
    """(1, 6, 3, F, F) float64 cube whose texel [k, :, v, u] holds (k, u, v)."""
    t = torch.arange(size, dtype=f64)
    v, u = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([torch.stack((torch.full_like(u, k), u, v)) for k in range(6)])[None]


@pytest.mark.parametrize("dtype", [f64, torch.uint8])
def test_axis_rays_land_at_face_centres(dtype):
    size = 9  # odd: the face centre is a texel centre
    # Equidistant with f = 20 / pi: the ray at 90 degrees is 10 px from the centre pixel (16, 16).
    f = 20 / math.pi
    cam = ot.Camera("equidistant", torch.tensor([f, f, 16.0, 16.0], dtype=f64), (33, 33),
                    fov=math.radians(190))
    layer = ot.OmniProjection(cam, size, interpolation="nearest")
    image, valid = layer(coded_cube(size).to(dtype))
    assert image.dtype == dtype
    centre = (size - 1) / 2
    expect = {(16, 16): "front", (26, 16): "right", (6, 16): "left", (16, 26): "down",
              (16, 6): "up"}
    for (u, v), name in expect.items():
        assert bool(valid[0, 0, v, u])
        got = image[0, :, v, u].tolist()
        assert got == [FACE_ORDER.index(name), centre, centre], (name, got)
    # Yaw +90 deg: the forward pixel looks along +x, the "right" face.
    rot = torch.tensor(YAW_RIGHT, dtype=f64)
    assert torch.equal(rot[:, 2], torch.tensor([1.0, 0, 0], dtype=f64))  # a of "right"
    image, _ = layer(coded_cube(size).to(dtype), rotation=rot)
    assert image[0, :, 16, 16].tolist() == [FACE_ORDER.index("right"), centre, centre]
    # and the pixel that looked right (+x) now looks back (-z)
    assert image[0, :, 16, 26].tolist() == [FACE_ORDER.index("back"), centre, centre]
    assert image[0, :, 16, 6].tolist() == [FACE_ORDER.index("front"), centre, centre]


@pytest.mark.parametrize("dtype", [f64, torch.uint8])
@pytest.mark.parametrize("yaw", [False, True])
def test_nearest_reads_reference_texel_everywhere(yaw, dtype):
    """Every valid pixel of a 190-degree fisheye reads the texel our own ray -> face gives."""
    size, n = 12, 48
    cam, f, c = fisheye(n)
    layer = ot.OmniProjection(cam, size, interpolation="nearest")
    rot = torch.tensor(YAW_RIGHT, dtype=f64) if yaw else None
    image, valid = layer(coded_cube(size).to(dtype), rotation=rot)
    assert image.dtype == dtype
    image = image.to(f64)
    cam_rays = equidistant_rays(f, c, n, n)
    rays = cam_rays @ rot.T if yaw else cam_rays
    face, uv = ref_face_uv(rays, size)
    ok = valid[0, 0] & not_tie(uv)
    expect = torch.stack((face.to(f64), *torch.round(uv).clamp(0, size - 1).unbind(-1)))
    assert int(ok.sum()) > 0.9 * int(valid.sum()) > 0
    assert torch.equal(image[0][:, ok], expect[:, ok])
    assert torch.equal(valid[0, 0], theta_of(cam_rays) <= math.radians(95))


@pytest.mark.parametrize("interpolation,dtype,atol", [
    ("nearest", f32, 0.0), ("bilinear", f32, 1e-5), ("bilinear", f64, 1e-12),
    ("bicubic", f64, 1e-12)])
def test_rig_of_six_pinhole_cameras_reproduces_the_faces(interpolation, dtype, atol):
    size = 10
    f, c = size / 2, (size - 1) / 2
    cam = ot.Camera("pinhole", torch.tensor([f, f, c, c], dtype=f64), (size, size))
    layer = ot.OmniProjection(cam, size, interpolation=interpolation)
    cube = torch.rand(1, 6, 2, size, size, generator=torch.Generator().manual_seed(0),
                      dtype=dtype)
    rot = torch.tensor([RIG[name] for name in FACE_ORDER], dtype=f64).transpose(1, 2)
    image, valid = layer(cube.expand(6, -1, -1, -1, -1).contiguous(), rotation=rot.to(dtype))
    assert bool(valid.all())
    torch.testing.assert_close(image, cube[0], atol=atol, rtol=0)
    if interpolation == "nearest":
        assert torch.equal(image, cube[0])
    # The rig rotations written here are DESIGN's columns (r, b, a).
    for k, name in enumerate(FACE_ORDER):
        a, b, r = DESIGN_TABLE[name]
        assert torch.equal(rot[k], torch.tensor((r, b, a), dtype=f64).T)


# ------------------------------------------------------------------------------------------
# Analytic sphere texture: accuracy and seams (the big case, run once)
# ------------------------------------------------------------------------------------------
BIG_F, BIG_N = 512, 1024


@pytest.fixture(scope="module")
def big_case():
    cam, f, c = fisheye(BIG_N)
    rays = equidistant_rays(f, c, BIG_N, BIG_N)
    truth = smooth(rays).to(f32)
    _, uv = ref_face_uv(rays, BIG_F)
    dist = edge_distance(uv, BIG_F)
    cube = smooth_cube(BIG_F)
    out = {}
    for border in ("resampled", "copied"):
        layer = ot.OmniProjection(cam, BIG_F, border=border)
        image, valid = layer(cube)
        out[border] = (image[0, 0] - truth).abs(), valid[0, 0]
    return out, dist


def seam_ratio(err, valid, dist):
    band = valid & (dist < 2)
    rest = valid & (dist >= 2)
    assert int(band.sum()) > 1000 and int(rest.sum()) > 1000
    return float(err[band].max()) / float(err[rest].max()), float(err[band].max()), \
        float(err[rest].max())


def test_bilinear_psnr_on_analytic_texture(big_case):
    err, valid = big_case[0]["resampled"]
    db = psnr(err[valid])
    print(f"\nPSNR 6x{BIG_F} cube -> {BIG_N}^2 equidistant 190 deg, bilinear: {db:.1f} dB, "
          f"max error {float(err[valid].max()):.2e}")
    assert db >= 70
    assert bool(torch.isfinite(err).all())


def test_no_seam_error_with_resampled_border(big_case):
    (err, valid), dist = big_case[0]["resampled"], big_case[1]
    ratio, band, rest = seam_ratio(err, valid, dist)
    print(f"\nseam band (< 2 texels) max error {band:.2e}, elsewhere {rest:.2e}, "
          f"ratio {ratio:.2f}")
    assert ratio <= 1.5


def test_copied_border_violates_the_seam_criterion(big_case):
    (err, valid), dist = big_case[0]["copied"], big_case[1]
    ratio, band, rest = seam_ratio(err, valid, dist)
    print(f"\ncopied border: seam band max error {band:.2e}, elsewhere {rest:.2e}, "
          f"ratio {ratio:.1f}")
    assert ratio > 1.5
    assert psnr(err[valid]) < psnr(big_case[0]["resampled"][0][valid])


#: The seam criterion on the 8-bit path: a coarser cube, whose copied border's seam error
#: (several levels) stands out of the quantisation (about a level everywhere).
SEAM8_F, SEAM8_N = 32, 256


@pytest.fixture(scope="module")
def seam_case_uint8():
    cam, f, c = fisheye(SEAM8_N)
    rays = equidistant_rays(f, c, SEAM8_N, SEAM8_N)
    truth = smooth(rays)
    _, uv = ref_face_uv(rays, SEAM8_F)
    cube = torch.floor(smooth_cube(SEAM8_F, f64) * 255 + 0.5).to(torch.uint8)
    out = {}
    for border in ("resampled", "copied"):
        layer = ot.OmniProjection(cam, SEAM8_F, border=border)
        image, valid = layer(cube)
        assert image.dtype == torch.uint8
        out[border] = (image[0, 0].double() / 255 - truth).abs(), valid[0, 0]
    return out, edge_distance(uv, SEAM8_F)


def test_no_seam_error_with_resampled_border_uint8(seam_case_uint8):
    (err, valid), dist = seam_case_uint8[0]["resampled"], seam_case_uint8[1]
    ratio, band, rest = seam_ratio(err, valid, dist)
    print(f"\nuint8: seam band (< 2 texels) max error {band * 255:.2f} levels, elsewhere "
          f"{rest * 255:.2f}, ratio {ratio:.2f}")
    assert ratio <= 1.5
    assert rest * 255 <= 1.5   # input and output rounding (half a level each) and the blend


def test_copied_border_violates_the_seam_criterion_uint8(seam_case_uint8):
    (err, valid), dist = seam_case_uint8[0]["copied"], seam_case_uint8[1]
    ratio, band, rest = seam_ratio(err, valid, dist)
    print(f"\nuint8, copied border: seam band max error {band * 255:.2f} levels, elsewhere "
          f"{rest * 255:.2f}, ratio {ratio:.1f}")
    assert ratio > 1.5


# ------------------------------------------------------------------------------------------
# Depth
# ------------------------------------------------------------------------------------------
DEPTH_F, DEPTH_N = 128, 96


def box_depth_cube(size: int, scene=box_t, dtype=f32) -> torch.Tensor:
    """(1, 6, 1, F, F) planar depth: t of the texel ray with a-component 1."""
    return scene(texel_rays(size))[None, :, None].to(dtype)


@pytest.fixture(scope="module")
def depth_case():
    cam, f, c = fisheye(DEPTH_N)
    rays = equidistant_rays(f, c, DEPTH_N, DEPTH_N)
    return cam, rays, box_depth_cube(DEPTH_F)


def test_depth_nearest_is_the_range_of_the_nearest_texel(depth_case):
    cam, rays, cube = depth_case
    layer = ot.OmniProjection(cam, DEPTH_F, depth_interpolation="nearest")
    out = layer.render(depth=cube)
    depth, valid = out["depth"][0, 0], out["valid"][0, 0]
    face, uv = ref_face_uv(rays, DEPTH_F)
    iu, iv = torch.round(uv).long().clamp(0, DEPTH_F - 1).unbind(-1)
    texel_ray = texel_rays(DEPTH_F)[face, iv, iu]
    expect = box_t(texel_ray / texel_ray.norm(dim=-1, keepdim=True))
    ok = valid & not_tie(uv)
    assert int(ok.sum()) > 0.9 * int(valid.sum())
    rel = ((depth.double() - expect) / expect).abs()[ok]
    print(f"\ndepth nearest: max relative error vs nearest texel range {float(rel.max()):.1e}")
    assert float(rel.max()) <= 1e-6
    assert bool((depth[~valid] == 0).all())


@pytest.mark.parametrize("mode", ["nearest", "bilinear", "edge_aware"])
def test_depth_range_and_z_away_from_edges(depth_case, mode):
    cam, rays, cube = depth_case
    layer = ot.OmniProjection(cam, DEPTH_F, depth_interpolation=mode)
    out = layer.render(depth=cube)
    depth, valid = out["depth"][0, 0].double(), out["valid"][0, 0]
    truth = box_t(rays)
    _, uv = ref_face_uv(rays, DEPTH_F)
    hits = box_hits(rays).sort(-1).values
    away = ((hits[..., 1] - hits[..., 0]) / hits[..., 0] > 8 / DEPTH_F)  # off the box creases
    away &= edge_distance(uv, DEPTH_F) >= 1.0  # off the face seams
    ok = valid & away
    assert int(ok.sum()) > 0.7 * int(valid.sum())
    rel = ((depth - truth) / truth).abs()[ok]
    # nearest is off by the range change over half a texel: bounded by the face's own sampling
    limit = 1e-3 if mode != "nearest" else 2 * math.sqrt(2) * 1.5 / DEPTH_F
    print(f"\ndepth {mode}: max relative range error away from edges {float(rel.max()):.2e}")
    assert float(rel.max()) <= limit
    z = layer.render(depth=cube, depth_output="z")["depth"][0, 0].double()
    torch.testing.assert_close(z[valid], (depth * rays[..., 2])[valid], rtol=1e-6, atol=1e-6)
    assert bool((z[~valid] == 0).all())
    assert bool((z[valid & (rays[..., 2] < -0.01)] < 0).all())  # beyond 90 deg: behind


@pytest.mark.parametrize("mode", ["nearest", "bilinear", "edge_aware"])
def test_depth_of_the_rig_is_the_planar_depth(mode):
    """Through six 90-degree pinhole cameras, depth 'z' is each face's planar depth itself."""
    size = 16
    f, c = size / 2, (size - 1) / 2
    cam = ot.Camera("pinhole", torch.tensor([f, f, c, c], dtype=f64), (size, size))
    layer = ot.OmniProjection(cam, size, depth_interpolation=mode)
    cube = box_depth_cube(size)
    rot = torch.tensor([RIG[name] for name in FACE_ORDER], dtype=f32).transpose(1, 2)
    batch = cube.expand(6, -1, -1, -1, -1)
    z = layer.render(depth=batch, rotation=rot, depth_output="z")["depth"]
    torch.testing.assert_close(z[:, 0], cube[0, :, 0], rtol=1e-6, atol=0)
    rng = layer.render(depth=batch, rotation=rot)["depth"]
    norm = texel_rays(size).norm(dim=-1).to(f32)
    torch.testing.assert_close(rng[:, 0], cube[0, :, 0] * norm, rtol=1e-6, atol=0)


@pytest.mark.parametrize("mode,flying", [("nearest", False), ("edge_aware", False),
                                         ("bilinear", True)])
def test_no_flying_pixels_at_a_depth_edge(mode, flying):
    size, n = 64, 96
    cam, f, c = fisheye(n, 120.0)
    rays = equidistant_rays(f, c, n, n)
    layer = ot.OmniProjection(cam, size, depth_interpolation=mode)
    out = layer.render(depth=box_depth_cube(size, edge_scene_t))
    depth, valid = out["depth"][0, 0].double(), out["valid"][0, 0]
    dz = rays[..., 2].clamp(min=1e-9)
    near, far = NEAR_Z / dz, box_t(rays)
    both = valid & (rays[..., 2] > 0) & (far > 1.5 * near)
    tol = 0.05  # nearest texel of a tilted plane: up to ~1.5% off the pixel's own ray
    between = both & (depth > near * (1 + tol)) & (depth < far * (1 - tol))
    # both sides are present
    assert int((both & ((depth - near).abs() < tol * near)).sum()) > 100
    assert int((both & ((depth - far).abs() < tol * far)).sum()) > 100
    print(f"\ndepth edge, {mode}: {int(between.sum())} pixels strictly between the two sides")
    assert bool(between.any()) == flying


# ------------------------------------------------------------------------------------------
# Labels
# ------------------------------------------------------------------------------------------
LABEL_VALUES = torch.tensor([0, 2, 5, 9, 12, 77, 300])
#: 8-bit ids: every value but the ignore index (255)
LABEL_VALUES_UINT8 = torch.tensor([0, 2, 5, 9, 12, 77, 254], dtype=torch.uint8)


@pytest.mark.parametrize("values", [LABEL_VALUES, LABEL_VALUES_UINT8], ids=["int64", "uint8"])
@pytest.mark.parametrize("yaw", [False, True])
@pytest.mark.parametrize("supersample", [1, 2])
def test_labels_equal_brute_force_nearest_texel(yaw, supersample, values):
    size, n = 16, 64
    cam, f, c = fisheye(n)
    g = torch.Generator().manual_seed(1)
    cube = values[torch.randint(0, len(values), (1, 6, size, size), generator=g)]
    layer = ot.OmniProjection(cam, size, supersample=supersample, interpolation="bicubic")
    rot = torch.tensor(YAW_RIGHT, dtype=f32) if yaw else None
    out = layer.render(labels=cube, rotation=rot)
    labels, valid = out["labels"][0], out["valid"][0, 0]
    assert labels.dtype == torch.int64
    rays = equidistant_rays(f, c, n, n)
    if yaw:
        rays = rays @ rot.double().T
    face, uv = ref_face_uv(rays, size)
    iu, iv = torch.round(uv).long().clamp(0, size - 1).unbind(-1)
    expect = cube[0, face, iv, iu]
    ok = valid & not_tie(uv, 1e-4)
    assert int(ok.sum()) > 0.95 * int(valid.sum()) > 0
    assert torch.equal(labels[ok], expect[ok].long())
    assert bool((labels[~valid] == 255).all()) and int((~valid).sum()) > 0
    assert set(labels.unique().tolist()) <= set(values.tolist()) | {255}


def test_labels_custom_ignore_index_and_uint8():
    size, n = 8, 24
    cam, _, _ = fisheye(n)
    layer = ot.OmniProjection(cam, size, ignore_index=-1)
    cube = torch.randint(0, 13, (2, 6, 1, size, size), dtype=torch.uint8)
    out = layer.render(labels=cube)
    valid = out["valid"][:, 0]
    assert bool((out["labels"][~valid] == -1).all())
    assert set(out["labels"][valid].unique().tolist()) <= set(cube.unique().tolist())


def test_large_label_ids_survive():
    """Ids above 2**24 (instance ids packed in 3 bytes) are not representable in float32:
    labels must never pass through a float grid_sample."""
    size, n = 8, 24
    cam, _, _ = fisheye(n)
    layer = ot.OmniProjection(cam, size)
    big = 2**24 + 1  # e.g. instance ids packed in 3 bytes
    cube = torch.full((1, 6, size, size), big, dtype=torch.int64)
    out = layer.render(labels=cube)
    assert set(out["labels"].unique().tolist()) <= {big, 255}


def region_labels(d: torch.Tensor) -> torch.Tensor:
    """Piecewise-constant classes 0..11 on the sphere: 6 longitude sectors x 2 latitude bands."""
    d = d / d.norm(dim=-1, keepdim=True)
    lon = torch.atan2(d[..., 0], d[..., 2])
    sector = torch.floor((lon + math.pi) / (math.pi / 3)).long().clamp(0, 5)
    return sector + 6 * (d[..., 1] > 0.3).long()


@pytest.mark.parametrize("supersample", [1, 2])
def test_soft_labels_sum_to_one_and_agree_with_hard_labels(supersample):
    size, n = 32, 48
    cam, f, c = fisheye(n)
    cube = region_labels(texel_rays(size))[None]  # [1, 6, F, F]
    layer = ot.OmniProjection(cam, size, supersample=supersample)
    out = layer.render(labels=cube, soft_labels=13)
    soft, hard, valid = out["soft_labels"][0], out["labels"][0], out["valid"][0, 0]
    assert soft.shape == (13, n, n)
    torch.testing.assert_close(soft.sum(0)[valid], torch.ones(int(valid.sum())), atol=1e-5, rtol=0)
    assert bool((soft[:, ~valid] == 0).all()) and bool((soft >= -1e-6).all())
    # away from label edges: the class is constant on a cap of 3 texel angles around the ray
    rays = equidistant_rays(f, c, n, n)
    seed = torch.tensor([0.3, 0.9, 0.1], dtype=f64)
    t1 = torch.linalg.cross(rays, seed.expand_as(rays))
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(rays, t1)
    # bilinear taps reach 1 texel (<= 2 / F rad at a face centre, x sqrt 2 diagonally) and the
    # sub-samples a quarter pixel (0.07 rad here): 2 texel angles covers both
    radius = 2 * 2 / size
    own = region_labels(rays)
    uniform = torch.ones_like(valid)
    for k in range(12):
        phi = 2 * math.pi * k / 12
        for s in (0.5, 1.0):
            d = rays + s * radius * (math.cos(phi) * t1 + math.sin(phi) * t2)
            uniform &= region_labels(d) == own
    ok = valid & uniform
    assert int(ok.sum()) > 0.5 * int(valid.sum())
    assert torch.equal(soft.argmax(0)[ok], hard[ok])
    assert torch.equal(hard[ok], own[ok])


# ------------------------------------------------------------------------------------------
# Gradients
# ------------------------------------------------------------------------------------------
def small_camera(learnable=True):
    """8 x 8 equidistant seeing at most ~0.26 rad off axis: well inside the front face, and every
    pixel valid (no fov), so small perturbations cross no seam and change no validity."""
    return ot.Camera("equidistant", torch.tensor([20.0, 21.0, 3.6, 3.4], dtype=f64), (8, 8),
                     learnable=learnable)


def skew(w: torch.Tensor) -> torch.Tensor:
    zero = torch.zeros_like(w[0])
    return torch.stack((torch.stack((zero, -w[2], w[1])), torch.stack((w[2], zero, -w[0])),
                        torch.stack((-w[1], w[0], zero))))


@pytest.mark.slow
@pytest.mark.parametrize("interpolation", ["bilinear", "bicubic"])
def test_gradcheck_intrinsics(interpolation):
    layer = ot.OmniProjection(small_camera(), 16, interpolation=interpolation)
    cube = smooth_cube(16, f64, channels=2)
    params = layer.camera.params.detach().clone().requires_grad_(True)

    def fn(p):
        image, valid = functional_call(layer, {"camera.params": p}, (cube,))
        assert bool(valid.all())
        return image

    assert torch.autograd.gradcheck(fn, (params,), eps=1e-6, atol=1e-6, rtol=1e-4)
    fn(params).sum().backward()
    assert bool((params.grad != 0).all())


@pytest.mark.slow
def test_gradcheck_depth_and_soft_labels_intrinsics():
    layer = ot.OmniProjection(small_camera(), 16, depth_interpolation="bilinear")
    depth = box_depth_cube(16, dtype=f64)
    labels = region_labels(texel_rays(16))[None]
    params = layer.camera.params.detach().clone().requires_grad_(True)

    class Render(torch.nn.Module):  # functional_call calls forward; route it to render
        def __init__(self):
            super().__init__()
            self.layer = layer

        def forward(self, **kw):
            return self.layer.render(**kw)

    def fn(p):
        out = functional_call(Render(), {"layer.camera.params": p}, (),
                              {"depth": depth, "labels": labels, "soft_labels": 12,
                               "depth_output": "z"})
        return out["depth"], out["soft_labels"]

    assert torch.autograd.gradcheck(fn, (params,), eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.slow
def test_gradcheck_rotation():
    layer = ot.OmniProjection(small_camera(learnable=False), 16)
    cube = smooth_cube(16, f64, channels=2)
    base = torch.tensor(YAW_RIGHT, dtype=f64) @ torch.linalg.matrix_exp(
        skew(torch.tensor([0.1, -0.2, 0.05], dtype=f64)))
    w = torch.tensor([0.03, -0.02, 0.04], dtype=f64, requires_grad=True)

    def fn(w):
        return layer(cube, rotation=torch.linalg.matrix_exp(skew(w)) @ base)[0]

    assert torch.autograd.gradcheck(fn, (w,), eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [f32, f64])
def test_gradients_finite_everywhere(dtype):
    """A 190-degree camera whose corners also leave the model's domain (theta >= pi)."""
    n = 16
    f = 3.0  # corners at 10.6 px > pi f: outside the equidistant domain
    cam = ot.Camera("equidistant", torch.tensor([f, f, 7.5, 7.5], dtype=dtype), (n, n),
                    fov=math.radians(190), learnable=True)
    rgb = smooth_cube(8, dtype, 3).requires_grad_(True)
    labels = region_labels(texel_rays(8))[None]
    depth = box_depth_cube(8, dtype=dtype)
    w = torch.zeros(3, dtype=dtype, requires_grad=True)
    total = 0
    for mode in ("bilinear", "edge_aware"):
        layer = ot.OmniProjection(cam, 8, supersample=2, depth_interpolation=mode)
        out = layer.render(rgb=rgb, depth=depth, labels=labels, soft_labels=12,
                           rotation=torch.linalg.matrix_exp(skew(w)), depth_output="z")
        valid = out["valid"]
        assert 0 < int(valid.sum()) < valid.numel()
        for key in ("rgb", "depth", "soft_labels"):
            assert bool(torch.isfinite(out[key]).all())
            total = total + out[key].sum()
    total.backward()
    for t in (cam.params, rgb, w):
        assert t.grad is not None and bool(torch.isfinite(t.grad).all())
        assert bool((t.grad != 0).any())


# ------------------------------------------------------------------------------------------
# Caching
# ------------------------------------------------------------------------------------------
def test_grid_cached_for_fixed_camera_and_rebuilt_with_rotation():
    cam, _, _ = fisheye(24)
    layer = ot.OmniProjection(cam, 8)
    cube = smooth_cube(8)
    first = layer.sampling_grid()
    layer(cube)
    second = layer.sampling_grid()
    assert second[0] is first[0] and second[3] is first[3]
    rot = torch.tensor(YAW_RIGHT)[None]
    with_rot = layer.sampling_grid(rotation=rot)
    again = layer.sampling_grid(rotation=rot)
    assert with_rot[0] is not first[0] and again[0] is not with_rot[0]
    torch.testing.assert_close(again[0], with_rot[0])
    assert not torch.allclose(with_rot[0], first[0])
    # a rotated render does not overwrite the cache of the unrotated one
    image_rot, _ = layer(cube, rotation=rot)
    assert layer.sampling_grid()[0] is first[0]
    assert not torch.allclose(image_rot, layer(cube)[0])
    # an in-place change of the (buffer) parameters invalidates the cache
    before, _ = layer(cube)
    with torch.no_grad():
        cam.params[0] *= 1.2
        cam.params[1] *= 1.2
    assert layer.sampling_grid()[0] is not first[0]
    after, _ = layer(cube)
    fresh, _ = ot.OmniProjection(ot.Camera("equidistant", cam.params.clone(), (24, 24),
                                           fov=cam.fov), 8)(cube)
    assert not torch.allclose(before, after)
    torch.testing.assert_close(after, fresh, atol=0, rtol=0)


@pytest.mark.slow
def test_learnable_camera_has_no_stale_cache():
    cam, _, _ = fisheye(16, 120.0, learnable=True)
    layer = ot.OmniProjection(cam, 8)
    cube = smooth_cube(8, channels=3)
    opt = torch.optim.Adam(cam.parameters(), lr=0.05)  # every parameter moves ~0.05
    with torch.no_grad():
        eval_before, _ = layer(cube)  # fills the cache (no grad: camera fixed here)
    image, _ = layer(cube)
    torch.testing.assert_close(image.detach(), eval_before)
    image.square().sum().backward()
    assert bool((cam.params.grad != 0).any())
    opt.step()
    image_after, _ = layer(cube)
    with torch.no_grad():
        eval_after, _ = layer(cube)
    moved = ot.Camera("equidistant", cam.params.detach().clone(), (16, 16), fov=cam.fov)
    # the gradient path samples with grid_sample, the no-grad path with fastsample (equal to
    # float32 rounding, tests/test_fastpath.py): each compared bit for bit with its own path
    expect_ref, _ = ot.OmniProjection(moved, 8, fast=False)(cube)
    expect, _ = ot.OmniProjection(moved, 8)(cube)
    assert not torch.allclose(image_after.detach(), image.detach())
    torch.testing.assert_close(image_after.detach(), expect_ref, atol=0, rtol=0)
    torch.testing.assert_close(eval_after, expect, atol=0, rtol=0)


# ------------------------------------------------------------------------------------------
# Half precision
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype,unit", [(torch.float16, 2.0**-11), (torch.bfloat16, 2.0**-8)])
@pytest.mark.parametrize("interpolation", ["nearest", "bilinear"])
def test_half_precision_cubemaps(dtype, unit, interpolation):
    size, n = 64, 64
    cam, _, _ = fisheye(n)
    cube = torch.rand(2, 6, 3, size, size, generator=torch.Generator().manual_seed(2))
    layer = ot.OmniProjection(cam, size, interpolation=interpolation)
    ref, valid = layer(cube)
    half, valid_h = layer(cube.to(dtype))
    assert half.dtype == dtype and torch.equal(valid, valid_h)
    # the cached grid is float32 (the half render reused the float32 one)
    grid = layer.sampling_grid(dtype=f32)
    assert grid[0].dtype == f32
    err = (half.float() - ref).abs().max()
    # input rounding (<= unit |x|) plus output rounding (<= unit |y|); a texel off would be ~0.5
    assert float(err) <= 2 * unit * float(cube.abs().max()) + 1e-7
    # depth in half precision: relative error of the same order
    depth = box_depth_cube(size)
    out32 = layer.render(depth=depth)
    r32, ok = out32["depth"], out32["valid"]
    r16 = layer.render(depth=depth.to(dtype))["depth"]
    assert r16.dtype == dtype
    rel = ((r16.float() - r32) / r32.clamp(min=1e-9)).abs()[ok]
    assert float(rel.max()) <= 4 * unit


def test_bfloat16_grid_would_be_off_by_texels():
    """Why the grid stays float32: on a 512 face, a bf16 grid is off by more than half a texel."""
    size, n = 512, 256
    _, f, c = fisheye(n)
    rays = equidistant_rays(f, c, n, n)
    rays = rays[theta_of(rays) <= math.radians(95)]
    pad = 1
    extent = torch.tensor([size + 2 * pad, 6 * (size + 2 * pad)], dtype=f64) / 2  # texel / unit
    exact = ot.cubemap.rays_to_grid(rays, size, pad)
    err32 = ((ot.cubemap.rays_to_grid(rays.float(), size, pad).double() - exact) * extent).abs()
    err16 = ((exact.bfloat16().double() - exact) * extent).abs()
    print(f"\ngrid error on a {size} face: float32 {float(err32.max()):.1e} texel, "
          f"bfloat16 {float(err16.max()):.1f} texel")
    assert float(err32.max()) < 0.01
    assert float(err16.max()) > 0.5


# ------------------------------------------------------------------------------------------
# Supersampling
# ------------------------------------------------------------------------------------------
def checker(d: torch.Tensor, k: float = 20.0) -> torch.Tensor:
    """A 3D checkerboard restricted to the sphere: about the same frequency everywhere."""
    d = d / d.norm(dim=-1, keepdim=True)
    s = torch.sin(k * d[..., 0]) * torch.sin(k * d[..., 1] + 0.3) * torch.sin(k * d[..., 2] + 0.7)
    return (s > 0).to(d.dtype)


def test_supersampling_reduces_aliasing():
    size, n, many = 128, 24, 16
    cam, f, c = fisheye(n)
    cube = checker(texel_rays(size))[None, :, None].to(f32)
    sub = equidistant_rays(f, c, n, n, many)  # [n many, n many, 3]
    inside = (theta_of(sub) <= math.radians(95)).double()
    values = checker(sub) * inside
    truth = F_nn.avg_pool2d(values[None, None], many)[0, 0]
    coverage = F_nn.avg_pool2d(inside[None, None], many)[0, 0]
    full = coverage == 1
    errors = {}
    for s in (1, 2, 4):
        image, _ = ot.OmniProjection(cam, size, supersample=s)(cube)
        errors[s] = float((image[0, 0].double() - truth)[full].square().mean().sqrt())
    print(f"\nsupersampling RMS error vs {many}x{many} ground truth: "
          + ", ".join(f"s={s}: {e:.3f}" for s, e in errors.items()))
    assert errors[2] < 0.75 * errors[1]
    assert errors[4] < errors[2]


# ------------------------------------------------------------------------------------------
# Batches
# ------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_batch_of_cameras_and_rotations_equals_per_sample_renders():
    size, n, batch = 16, 32, 3
    params = torch.tensor([[9.0, 9.5, 15.5, 15.0], [11.0, 10.0, 16.0, 15.5],
                           [8.0, 8.0, 15.5, 15.5]], dtype=f64)
    fov = math.radians(190)
    rots = torch.stack([torch.linalg.matrix_exp(skew(torch.tensor(w, dtype=f64)))
                        for w in ([0.0, 0.0, 0.0], [0.2, -0.5, 0.1], [1.0, 2.0, -0.4])])
    g = torch.Generator().manual_seed(3)
    rgb = torch.rand(batch, 6, 2, size, size, generator=g)
    labels = torch.randint(0, 13, (batch, 6, size, size), generator=g)
    depth = 1 + 5 * torch.rand(batch, 6, 1, size, size, generator=g)
    kw = dict(supersample=2, depth_interpolation="edge_aware")
    layer = ot.OmniProjection(ot.Camera("equidistant", params, (n, n), fov=fov), size, **kw)
    out = layer.render(rgb=rgb, depth=depth, labels=labels, rotation=rots.float(),
                       soft_labels=13)
    for i in range(batch):
        one = ot.OmniProjection(ot.Camera("equidistant", params[i], (n, n), fov=fov), size, **kw)
        ref = one.render(rgb=rgb[i:i + 1], depth=depth[i:i + 1], labels=labels[i:i + 1],
                         rotation=rots[i].float(), soft_labels=13)
        for key in ("rgb", "depth", "soft_labels", "valid"):
            torch.testing.assert_close(out[key][i:i + 1], ref[key], atol=1e-6, rtol=0)
        assert torch.equal(out["labels"][i:i + 1], ref["labels"])
    # one camera, a batch of rotations; and one (3, 3) rotation broadcast over the batch
    single = ot.OmniProjection(ot.Camera("equidistant", params[0], (n, n), fov=fov), size)
    image, valid = single(rgb, rotation=rots.float())
    assert valid.shape == (batch, 1, n, n)
    for i in range(batch):
        ref, ref_valid = single(rgb[i:i + 1], rotation=rots[i:i + 1].float())
        torch.testing.assert_close(image[i:i + 1], ref, atol=1e-6, rtol=0)
        assert torch.equal(valid[i:i + 1], ref_valid)
    image, _ = single(rgb, rotation=rots[1].float())
    for i in range(batch):
        torch.testing.assert_close(image[i:i + 1], single(rgb[i:i + 1], rots[1].float())[0])


# ------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_layer():
    cam, _, _ = fisheye(8)
    return ot.OmniProjection(cam, 4)


@pytest.mark.parametrize("kwargs,error,match", [
    (dict(rgb=torch.rand(1, 5, 3, 4, 4)), ValueError, "rgb"),
    (dict(rgb=torch.rand(6, 3, 4, 4)), ValueError, "rgb"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 5)), ValueError, "rgb"),
    (dict(rgb=torch.rand(1, 6, 3, 8, 8)), ValueError, "face_size"),
    (dict(rgb=torch.randint(0, 255, (1, 6, 3, 4, 4), dtype=torch.int16)), TypeError, "rgb"),
    (dict(rgb=torch.rand(1, 6, 4, 4, 3), channels_last=1), TypeError, "channels_last"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), channels_last=True), ValueError, "rgb"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), out_dtype=torch.int32), TypeError, "out_dtype"),
    (dict(labels=torch.zeros(1, 6, 4, 4, dtype=torch.long), out_dtype=torch.float32),
     ValueError, "out_dtype"),
    (dict(labels=torch.rand(1, 6, 4, 4)), TypeError, "labels"),
    (dict(labels=torch.zeros(1, 6, 4, 5, dtype=torch.long)), ValueError, "labels"),
    (dict(labels=torch.zeros(1, 6, 2, 4, 4, dtype=torch.long)), ValueError, "labels"),
    (dict(depth=torch.ones(1, 6, 4, 4, dtype=torch.long)), TypeError, "depth"),
    (dict(depth=torch.ones(1, 5, 4, 4)), ValueError, "depth"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), depth=torch.ones(2, 6, 4, 4)), ValueError, "depth"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), labels=torch.zeros(1, 6, 8, 8, dtype=torch.long)),
     ValueError, "labels"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), rotation=torch.eye(3)[None].expand(2, 3, 3)),
     ValueError, "rotation"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), rotation=torch.eye(4)), ValueError, "rotation"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), rotation=torch.eye(3)[None, None]), ValueError,
     "rotation"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), rotation=torch.eye(3, dtype=torch.long)), TypeError,
     "rotation"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), rotation=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
     TypeError, "rotation"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), depth_output="planar"), ValueError, "depth_output"),
    (dict(labels=torch.zeros(1, 6, 4, 4, dtype=torch.long), soft_labels=0), ValueError,
     "soft_labels"),
    (dict(labels=torch.full((1, 6, 4, 4), 13), soft_labels=13), ValueError, "labels"),
    (dict(rgb=torch.rand(1, 6, 3, 4, 4), soft_labels=13), ValueError, "soft_labels"),
    (dict(), ValueError, "rgb"),
])
def test_bad_render_input(small_layer, kwargs, error, match):
    with pytest.raises(error, match=match):
        small_layer.render(**kwargs)


def test_bad_forward_input(small_layer):
    with pytest.raises(ValueError, match="cubemap|rgb"):
        small_layer(torch.rand(1, 6, 3, 4))
    with pytest.raises(TypeError, match="rgb|cubemap"):
        small_layer("not a tensor")
    batched = ot.OmniProjection(ot.Camera("equidistant", torch.rand(2, 4) + 3, (8, 8)), 4)
    with pytest.raises(ValueError, match="batch"):
        batched(torch.rand(3, 6, 3, 4, 4))


@pytest.mark.slow
def test_render_through_a_given_grid():
    """``render(grid=...)`` samples through a grid computed elsewhere (per-sample random
    cameras in one kernel): the grid of the camera's rays under a rotation gives the image
    rendered with that rotation, on the fast and the reference path."""
    cam, _, _ = fisheye(16)
    cube = torch.rand(2, 6, 3, 8, 8, dtype=f64)
    labels = torch.randint(0, 13, (2, 6, 8, 8))
    rotation = ot.presets.yaw_pitch_roll_to_matrix(torch.tensor([0.3, -1.2], dtype=f64),
                                                   torch.tensor([0.1, 0.4], dtype=f64), 0.2)
    for fast in (True, False):
        layer = ot.OmniProjection(cam, 8, fast=fast)
        expected = layer.render(rgb=cube, labels=labels, rotation=rotation)
        rays, valid = cam.ray_grid()
        grid = ot.cubemap.rotated_rays_to_grid(rays, rotation, 8, layer.pad, compiled=False)
        grid = torch.where(valid[..., None], grid, torch.full_like(grid, -2.0))
        got = layer.render(rgb=cube, labels=labels, grid=(grid, valid.expand(2, -1, -1)))
        torch.testing.assert_close(got["rgb"], expected["rgb"])
        assert torch.equal(got["labels"], expected["labels"])
        assert torch.equal(got["valid"], expected["valid"])
    with pytest.raises(ValueError, match="grid: a given grid already holds the attitude"):
        layer.render(rgb=cube, rotation=rotation, grid=(grid, valid.expand(2, -1, -1)))
    with pytest.raises(ValueError, match="grid: expected a floating tensor"):
        layer.render(rgb=cube, grid=(grid[:, :4], valid.expand(2, -1, -1)))
    with pytest.raises(TypeError, match="grid: expected a tuple"):
        layer.render(rgb=cube, grid=grid)


def _bad_rotations() -> dict[str, torch.Tensor]:
    """Matrices that are not rotations, each with the words its error must use."""
    theta = 0.3
    turn = torch.tensor([[math.cos(theta), 0.0, math.sin(theta)], [0.0, 1.0, 0.0],
                         [-math.sin(theta), 0.0, math.cos(theta)]])
    return {"NaN": torch.full((3, 3), float("nan")),
            "det 0": torch.zeros(3, 3),
            "det -1": torch.diag(torch.tensor([1.0, 1.0, -1.0])),     # a reflection
            "not orthonormal": 1.01 * turn,                          # scaled
            "NaN or infinite": torch.eye(3).index_fill(1, torch.tensor([2]), float("inf"))}


@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("what", list(_bad_rotations()))
def test_invalid_rotations_are_refused_naming_the_batch_index(what, fast):
    """A NaN, zero, reflected or scaled matrix in a rotation batch is a ValueError naming its
    index, on the fast and the reference path alike (it once rendered zeros, NaN, a mirrored
    image or the silently normalised rotation, each marked valid)."""
    cam, _, _ = fisheye(16)
    layer = ot.OmniProjection(cam, 8, fast=fast)
    cube = torch.rand(3, 6, 3, 8, 8, dtype=f64)
    rotations = torch.eye(3, dtype=f64).repeat(3, 1, 1)
    rotations[2] = _bad_rotations()[what]
    with pytest.raises(ValueError, match=r"rotation\[2\]"):
        layer(cube, rotations)
    with pytest.raises(ValueError, match=what):
        layer.render(labels=torch.zeros(3, 6, 8, 8, dtype=torch.long), rotation=rotations)
    # a float32 rotation built from angles passes; so does the identity in half precision
    good = ot.presets.yaw_pitch_roll_to_matrix(torch.tensor(0.3), torch.tensor(-0.2),
                                               torch.tensor(1.1))
    layer(cube.float(), good.float())
    ot.cubemap.check_rotation(torch.eye(3, dtype=torch.float16))


def test_every_path_that_takes_an_attitude_checks_it():
    bad = torch.diag(torch.tensor([1.0, -1.0, 1.0]))      # a reflection: det -1
    cam, _, _ = fisheye(16, dtype=f32)
    with pytest.raises(ValueError, match="rotation.*det"):
        ot.required_face_size(cam, bad)
    with pytest.raises(ValueError, match="rotation.*det"):
        ot.visible_faces(cam, bad)
    with pytest.raises(ValueError, match="rotation.*det"):
        ot.reproject(torch.rand(1, 3, 16, 32), ot.equirectangular_camera(32, 16), cam,
                     rotation=bad)
    layer = ot.OmniProjection(cam, 8)
    with pytest.raises(ValueError, match=r"rotations\[1\].*det"):
        ot.StereoRig(layer, layer, rotations=torch.stack((torch.eye(3), bad)))
    aug = ot.augment.RandomOmniCamera((16, 16), 8, seed=0)
    cube = torch.rand(2, 6, 3, 8, 8)
    params = aug.forward_parameters(2)
    params["rotation"] = params["rotation"].clone()
    params["rotation"][1] = 2 * params["rotation"][1]
    with pytest.raises(ValueError, match=r'params\["rotation"\]\[1\].*orthonormal'):
        aug(cube, params=params)


@pytest.mark.parametrize("value, match", [(float("nan"), "fx .*finite"),
                                          (float("inf"), "fx .*finite"),
                                          (-50.0, "fx .*> 0"), (0.0, "fx .*> 0")])
def test_learnable_camera_outside_its_domain_raises_on_forward(value, match):
    """A learnable focal length that becomes NaN or negative stops the next forward with the
    parameter's name (it rendered black with valid all False, or a mirrored image marked
    valid); field_of_view() says so too instead of returning 0."""
    cam, _, _ = fisheye(16, learnable=True)
    layer = ot.OmniProjection(cam, 8)
    cube = torch.rand(1, 6, 3, 8, 8, dtype=f64)
    image, _ = layer(cube)
    image.sum().backward()
    with torch.no_grad():
        cam.params[0] = value
    with pytest.raises(ValueError, match=match):
        layer(cube)
    with pytest.raises(ValueError, match=match):
        cam.field_of_view()
    with torch.no_grad(), pytest.raises(ValueError, match=match):
        layer(cube)   # a frozen layer re-reads parameters changed in place
    with torch.no_grad():
        cam.params[0] = 5.0
    layer(cube)   # back in the domain: renders again


def test_model_constraints_are_checked_on_forward():
    """Beyond the focal lengths: each model's own ranges (here the double sphere's alpha in
    [0, 1]) are checked on every forward of a learnable camera."""
    cam = ot.Camera("double_sphere", torch.tensor([10.0, 10.0, 7.5, 7.5, -0.2, 0.6],
                                                  dtype=f64), (16, 16), learnable=True)
    layer = ot.OmniProjection(cam, 8)
    cube = torch.rand(1, 6, 3, 8, 8, dtype=f64)
    layer(cube)
    with torch.no_grad():
        cam.params[5] = 1.5
    with pytest.raises(ValueError, match="alpha of the double_sphere model"):
        layer(cube)


def test_mismatched_devices(small_layer):
    meta = torch.device("meta")
    cpu_cube = torch.rand(1, 6, 3, 4, 4)
    with pytest.raises(ValueError, match="camera|device|meta"):
        small_layer(torch.empty(1, 6, 3, 4, 4, device=meta))
    with pytest.raises(ValueError, match="rotation"):
        small_layer(cpu_cube, rotation=torch.eye(3, device=meta))
    with pytest.raises(ValueError, match="labels"):
        small_layer.render(rgb=cpu_cube, labels=torch.zeros(1, 6, 4, 4, dtype=torch.long,
                                                             device=meta))


@pytest.mark.parametrize("kwargs,error,match", [
    (dict(camera="equidistant"), TypeError, "camera"),
    (dict(face_size=0), ValueError, "face_size"),
    (dict(face_size=4.0), ValueError, "face_size"),
    (dict(face_size=True), ValueError, "face_size"),
    (dict(interpolation="linear"), ValueError, "interpolation"),
    (dict(depth_interpolation="bicubic"), ValueError, "depth_interpolation"),
    (dict(supersample=0), ValueError, "supersample"),
    (dict(supersample=1.5), ValueError, "supersample"),
    (dict(border="mirror"), ValueError, "border"),
    (dict(depth_edge_threshold=0.0), ValueError, "depth_edge_threshold"),
])
def test_bad_constructor_args(kwargs, error, match):
    args = dict(camera=ot.Camera("equidistant", [3.0, 3.0, 3.5, 3.5], (8, 8)), face_size=4)
    args.update(kwargs)
    camera, face_size = args.pop("camera"), args.pop("face_size")
    with pytest.raises(error, match=match):
        ot.OmniProjection(camera, face_size, **args)


def test_cache_follows_a_replaced_params_tensor():
    """Cached rays, grid and lookup table belong to one params tensor: a replaced one gets its
    own (the cache is keyed by the tensor's identity, kept alive by the cache, so that a new
    tensor allocated where a freed one was is not mistaken for it)."""
    cam = ot.presets.fisheye((24, 24), fov=math.radians(180))
    layer = ot.OmniProjection(cam, 8)
    cube = torch.rand(1, 6, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        layer(cube)
        for scale in (0.8, 1.3):
            values = cam.params.tolist()
            values[0] *= scale
            values[1] *= scale
            cam.params = None   # the old tensor is freed: the new one may take its storage
            cam.params = torch.tensor(values)
            got, _ = layer(cube)
            expected, _ = ot.OmniProjection(ot.Camera(cam.model, values, (24, 24),
                                                      fov=cam.fov), 8)(cube)
            assert torch.equal(got, expected)
