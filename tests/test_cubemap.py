"""Tests of omniscape_torch.cubemap: face table, ray <-> face, padded cube, atlas, depth.

Oracles are written here independently of the code under test: the face table literally from
DESIGN.md, simulator rig rotations as rotation matrices, the pinhole formula of a face pixel,
and a smooth analytic function of the ray direction whose value at any ray is known exactly.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F_nn

import omniscape_torch.cubemap as cubemap

from conftest import DESIGN_TABLE

f64 = torch.float64



def table(dtype=f64):
    """(6, 3, 3) (a, b, r) per face, FACES order, from the literal table above."""
    return torch.tensor([DESIGN_TABLE[name] for name in cubemap.FACES], dtype=dtype)


def pinhole_ray(face: int, u, v, size: int) -> torch.Tensor:
    """DESIGN.md: ray = r (u - c) / f + b (v - c) / f + a, f = F / 2, c = (F - 1) / 2."""
    a, b, r = table()[face]
    f, c = size / 2, (size - 1) / 2
    u = torch.as_tensor(u, dtype=f64)[..., None]
    v = torch.as_tensor(v, dtype=f64)[..., None]
    return r * (u - c) / f + b * (v - c) / f + a


def padded_rays(size: int, pad: int) -> torch.Tensor:
    """(6, n, n, 3) rays of every texel of padded faces: texel [i, j] is pixel (j - pad, i - pad)."""
    t = torch.arange(size + 2 * pad, dtype=f64) - pad
    v, u = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([pinhole_ray(k, u, v, size) for k in range(6)])


def smooth(d: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics of degree <= 2 (arbitrary coefficients) of the direction."""
    x, y, z = (d / d.norm(dim=-1, keepdim=True)).unbind(-1)
    return (
        0.3 + 0.5 * x - 0.4 * y + 0.7 * z
        + 0.6 * x * y - 0.5 * y * z + 0.4 * (3 * z * z - 1) + 0.8 * x * z + 0.5 * (x * x - y * y)
    )


def bilinear_error_bound(size: int) -> float:
    """Textbook bound of bilinear interpolation on a unit grid: (|g_uu| + |g_vv|)_max / 8.

    g(u, v) = smooth(face ray at pixel (u, v)); second derivatives by central differences on the
    tangent plane (x, y) in [-1, 1]^2 (the face), scaled by (1 / f)^2 to pixel units.
    """
    h = 1e-3
    t = torch.linspace(-1, 1, 81, dtype=f64)
    x, y = torch.meshgrid(t, t, indexing="ij")
    worst = 0.0
    for a, b, r in table():
        def g(dx, dy):
            return smooth(r * (x + dx)[..., None] + b * (y + dy)[..., None] + a)

        g_xx = (g(h, 0) - 2 * g(0, 0) + g(-h, 0)) / h**2
        g_yy = (g(0, h) - 2 * g(0, 0) + g(0, -h)) / h**2
        worst = max(worst, float((g_xx.abs() + g_yy.abs()).max()))
    focal = size / 2
    return worst / focal**2 / 8


def border_masks(size: int, pad: int):
    """(n, n) masks of a padded face: all border texels, and the corner blocks (outside on both axes)."""
    t = torch.arange(size + 2 * pad)
    inside = (t >= pad) & (t < pad + size)
    return ~(inside[:, None] & inside[None, :]), ~inside[:, None] & ~inside[None, :]


# ----------------------------------------------------------------------------------------------
# Face table and orientation


def test_faces_order():
    assert cubemap.FACES == ("front", "back", "left", "right", "up", "down")


def test_face_axes_match_design_table():
    axes = cubemap.face_axes(f64)
    assert axes.shape == (6, 3, 3) and axes.dtype == f64
    assert torch.equal(axes, table())
    a, b, r = axes.unbind(1)
    assert torch.equal(r, torch.linalg.cross(b, a))
    assert cubemap.face_axes(torch.float32).dtype == torch.float32


def rot_yaw(deg: float) -> torch.Tensor:
    # OpenCV frame, y down: a positive rotation about +y turns +z (forward) towards +x (right),
    # i.e. a positive yaw turns right, as a simulator's yaw does.
    t = math.radians(deg)
    c, s = math.cos(t), math.sin(t)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=f64)


def rot_pitch(deg: float) -> torch.Tensor:
    # A positive rotation about +x turns +z (forward) towards -y (up): a positive pitch looks up.
    t = math.radians(deg)
    c, s = math.cos(t), math.sin(t)
    return torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=f64)


def test_face_rotations_match_simulator_rig():
    rig = {
        "front": torch.eye(3, dtype=f64),
        "back": rot_yaw(180),
        "left": rot_yaw(-90),
        "right": rot_yaw(90),
        "up": rot_pitch(90),
        "down": rot_pitch(-90),
    }
    rot = cubemap.face_rotations(f64)
    axes = table()
    for k, name in enumerate(cubemap.FACES):
        torch.testing.assert_close(rot[k], rig[name], atol=1e-15, rtol=0)
        # A rig camera's (right, down, forward) are the face's (r, b, a).
        a, b, r = axes[k]
        for column, axis in enumerate((r, b, a)):
            unit = torch.eye(3, dtype=f64)[column]
            torch.testing.assert_close(rig[name] @ unit, axis, atol=1e-15, rtol=0)


# ----------------------------------------------------------------------------------------------
# Rays <-> faces


def test_face_pixel_to_ray_is_the_pinhole_formula():
    size = 9
    gen = torch.Generator().manual_seed(1)
    uv = torch.rand(6, 50, 2, generator=gen, dtype=f64) * 14 - 3  # also outside the face
    face = torch.arange(6)[:, None]
    rays = cubemap.face_pixel_to_ray(face, uv, size)
    expected = torch.stack([pinhole_ray(k, uv[k, :, 0], uv[k, :, 1], size) for k in range(6)])
    torch.testing.assert_close(rays, expected, atol=1e-14, rtol=0)
    unit = cubemap.face_pixel_to_ray(face, uv, size, normalize=True)
    torch.testing.assert_close(unit.norm(dim=-1), torch.ones(6, 50, dtype=f64))
    torch.testing.assert_close(
        cubemap.face_rays(size, pad=2, dtype=f64), padded_rays(size, 2), atol=1e-14, rtol=0
    )


def test_texel_centre_convention():
    size = 8
    f, c = size / 2, (size - 1) / 2
    assert cubemap.face_intrinsics(size) == (f, c)
    rays = cubemap.face_rays(size, dtype=f64)
    assert rays.shape == (6, size, size, 3)
    front = cubemap.FACES.index("front")
    # (0, 0) is the centre of the top-left texel: half a texel in from the corner (-1, -1, 1).
    half = 0.5 / f
    torch.testing.assert_close(rays[front, 0, 0], torch.tensor([-1 + half, -1 + half, 1], dtype=f64))
    torch.testing.assert_close(rays[front, -1, -1], torch.tensor([1 - half, 1 - half, 1], dtype=f64))
    # Indexing is [face, v, u]: moving along the last axis moves right (+x on the front face).
    assert rays[front, 0, 1, 0] > rays[front, 0, 0, 0] and rays[front, 1, 0, 1] > rays[front, 0, 0, 1]
    # The face spans [-0.5, F - 0.5]: directions just inside its corners land there.
    eps = 1e-9
    corners = torch.tensor([[-1 + eps, -1 + eps, 1], [1 - eps, 1 - eps, 1]], dtype=f64)
    face, uv = cubemap.ray_to_face(corners, size)
    assert face.tolist() == [front, front]
    expected = torch.tensor([[-0.5, -0.5], [size - 0.5, size - 0.5]], dtype=f64)
    torch.testing.assert_close(uv, expected, atol=1e-7, rtol=0)
    # Texel centres map back to integer pixels.
    face, uv = cubemap.ray_to_face(rays, size)
    t = torch.arange(size, dtype=f64)
    v, u = torch.meshgrid(t, t, indexing="ij")
    assert torch.equal(face, torch.arange(6)[:, None, None].expand(6, size, size))
    torch.testing.assert_close(uv, torch.stack([u, v], -1).expand(6, size, size, 2), atol=1e-12, rtol=0)


def test_round_trip_pixel_ray_pixel():
    size = 17
    gen = torch.Generator().manual_seed(2)
    face = torch.randint(0, 6, (2000,), generator=gen)
    uv = torch.rand(2000, 2, generator=gen, dtype=f64) * (size - 1.02) - 0.49  # strictly inside
    rays = cubemap.face_pixel_to_ray(face, uv, size)
    scale = torch.rand(2000, 1, generator=gen, dtype=f64) * 10 + 0.01  # rays need not be unit
    face2, uv2 = cubemap.ray_to_face(rays * scale, size)
    assert torch.equal(face2, face)
    torch.testing.assert_close(uv2, uv, atol=1e-11, rtol=0)
    # float32 in, float32 out
    face3, uv3 = cubemap.ray_to_face(rays.float(), size)
    assert uv3.dtype == torch.float32 and torch.equal(face3, face)
    torch.testing.assert_close(uv3, uv.float(), atol=1e-4, rtol=0)


def test_face_centres_edges_and_corners():
    size = 6
    c, hi = (size - 1) / 2, size - 0.5
    idx = {name: k for k, name in enumerate(cubemap.FACES)}
    cases = [
        # (ray, face, (u, v))
        ((0, 0, 1), "front", (c, c)),
        ((0, 0, -3), "back", (c, c)),
        ((-2, 0, 0), "left", (c, c)),
        ((0.5, 0, 0), "right", (c, c)),
        ((0, -1, 0), "up", (c, c)),
        ((0, 1, 0), "down", (c, c)),
        # just inside the front face's right edge: u -> F - 0.5
        ((1 - 1e-9, 0, 1), "front", (hi, c)),
        # just past it, on the right face's left edge: u -> -0.5
        ((1 + 1e-9, 0, 1), "right", (-0.5, c)),
        # up face: its top edge (v = -0.5) borders the back face, its bottom edge the front face
        ((0, -1, -1 + 1e-9), "up", (c, -0.5)),
        ((0, -1, 1 - 1e-9), "up", (c, hi)),
        # down face: its top edge borders the front face
        ((0, 1, 1 - 1e-9), "down", (c, -0.5)),
        # exact edge and corner directions: ties go to x, then y, then z
        ((1, 0, 1), "right", (-0.5, c)),
        ((0, 1, 1), "down", (c, -0.5)),
        ((1, 1, 1), "right", (-0.5, hi)),
        ((-1, -1, -1), "left", (-0.5, -0.5)),
        ((1, -1, -1), "right", (hi, -0.5)),
    ]
    rays = torch.tensor([r for r, _, _ in cases], dtype=f64)
    face, uv = cubemap.ray_to_face(rays, size)
    assert face.tolist() == [idx[name] for _, name, _ in cases]
    torch.testing.assert_close(uv, torch.tensor([e for _, _, e in cases], dtype=f64), atol=1e-7, rtol=0)


def test_zero_ray_is_finite_with_finite_gradient():
    size = 4
    rays = torch.zeros(3, 3, dtype=f64, requires_grad=True)
    face, uv = cubemap.ray_to_face(rays, size)
    assert face.tolist() == [0, 0, 0]
    torch.testing.assert_close(uv.detach(), torch.full((3, 2), (size - 1) / 2, dtype=f64))
    uv.sum().backward()
    assert torch.isfinite(rays.grad).all()


def test_ray_to_face_gradcheck():
    size = 5
    gen = torch.Generator().manual_seed(3)
    face = torch.randint(0, 6, (20,), generator=gen)
    uv = torch.rand(20, 2, generator=gen, dtype=f64) * 3 + 0.5  # away from seams
    rays = cubemap.face_pixel_to_ray(face, uv, size).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda r: cubemap.ray_to_face(r, size)[1], (rays,))
    uv.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q: cubemap.face_pixel_to_ray(face, q, size), (uv,))


# ----------------------------------------------------------------------------------------------
# Padded cube


@pytest.mark.parametrize("size,pad", [(16, 2), (24, 3)])
def test_padded_border_equals_function_at_border_rays(size, pad):
    cube = smooth(padded_rays(size, 0))[None, :, None]  # [1, 6, 1, F, F]
    padded = cubemap.pad_faces(cube, pad)
    n = size + 2 * pad
    assert padded.shape == (1, 6, 1, n, n) and padded.dtype == f64
    truth = smooth(padded_rays(size, pad))[None, :, None]
    border, corner = border_masks(size, pad)
    seam = border & ~corner
    # The interior is the input, untouched.
    assert torch.equal(padded[..., pad:-pad, pad:-pad], cube)
    # Every border texel is the function at its own ray, within the bilinear interpolation error
    # at the source point on the neighbour face (corner blocks included).
    bound = bilinear_error_bound(size)
    err = (padded - truth).abs()
    assert err[..., border].max() <= bound
    # A copied (clamped) border is measurably worse, on the edges and in the corners.
    copied = F_nn.pad(cube.reshape(6, 1, size, size), (pad,) * 4, mode="replicate").reshape(1, 6, 1, n, n)
    err_copy = (copied - truth).abs()
    assert err_copy[..., seam].max() > 20 * err[..., seam].max()
    assert err_copy[..., corner].max() > 20 * err[..., corner].max()
    assert err_copy[..., border].mean() > 20 * err[..., border].mean()


def test_padded_border_is_self_consistent():
    """A border texel equals bilinear sampling of the padded cube along its ray on the face the
    ray hits (also where that sample reads the neighbour's own border, near edges and corners)."""
    size, pad = 7, 2
    gen = torch.Generator().manual_seed(4)
    cube = torch.rand(2, 6, 3, size, size, generator=gen, dtype=f64)
    atlas = cubemap.cubemap_to_atlas(cube, pad)
    n = size + 2 * pad
    border, _ = border_masks(size, pad)
    rays = padded_rays(size, pad)[:, border]  # [6, M, 3]
    grid = cubemap.rays_to_grid(rays, size, pad).reshape(1, -1, 1, 2).expand(2, -1, -1, -1)
    sampled = F_nn.grid_sample(atlas, grid, mode="bilinear", align_corners=False).reshape(2, 3, 6, -1)
    stored = cubemap.atlas_to_faces(atlas)[..., border].transpose(1, 2)  # [2, 3, 6, M]
    torch.testing.assert_close(sampled, stored, atol=1e-11, rtol=0)
    # constants are reproduced exactly (weights sum to one)
    ones = cubemap.pad_faces(torch.ones(1, 6, 1, size, size, dtype=f64), pad)
    torch.testing.assert_close(ones, torch.ones(1, 6, 1, n, n, dtype=f64), atol=1e-12, rtol=0)
    plan = cubemap.border_plan(size, pad)
    assert plan.residual < 1e-11 and plan.src_index.shape[0] == 6 * (n * n - size * size)


def test_nearest_border_takes_the_texel_nearest_to_the_border_ray():
    size, pad = 8, 2
    n = size + 2 * pad
    ids = torch.arange(6 * size * size).reshape(1, 6, 1, size, size)  # every texel unique, int64
    padded = cubemap.pad_faces(ids, pad, mode="nearest")
    assert padded.dtype == torch.int64 and padded.shape == (1, 6, 1, n, n)
    border, _ = border_masks(size, pad)
    src = padded[0, :, 0][:, border].reshape(-1)  # ids of the chosen source texels
    rays = padded_rays(size, pad)[:, border].reshape(-1, 3)
    src_face, rem = src // (size * size), src % (size * size)
    src_uv = torch.stack([rem % size, rem // size], -1).to(f64)
    a, b, r = table()[src_face].unbind(1)
    depth = (a * rays).sum(-1)
    assert (depth > 0).all()
    f, c = size / 2, (size - 1) / 2
    uv = torch.stack([c + f * (r * rays).sum(-1) / depth, c + f * (b * rays).sum(-1) / depth], -1)
    # The ray lies on the source face, and the chosen texel is its nearest texel there.
    assert (uv >= -0.5 - 1e-12).all() and (uv <= size - 0.5 + 1e-12).all()
    assert ((uv - src_uv).abs() <= 0.5 + 1e-12).all()


@pytest.mark.parametrize("dtype", [torch.float32, f64])
@pytest.mark.parametrize("size,pad", [(5, 1), (12, 2), (9, 3)])
def test_atlas_texel_centres_return_the_face_texels(dtype, size, pad):
    gen = torch.Generator().manual_seed(5)
    cube = torch.rand(2, 6, 3, size, size, generator=gen, dtype=dtype)
    atlas = cubemap.cubemap_to_atlas(cube, pad)
    n = size + 2 * pad
    assert atlas.shape == (2, 3, 6 * n, n) and atlas.dtype == dtype
    assert torch.equal(atlas, cubemap.faces_to_atlas(cubemap.pad_faces(cube, pad)))
    assert torch.equal(cubemap.atlas_to_faces(atlas)[..., pad:-pad, pad:-pad], cube)
    t = torch.arange(size, dtype=dtype)
    v, u = torch.meshgrid(t, t, indexing="ij")
    uv = torch.stack([u, v], -1).expand(6, size, size, 2)
    face = torch.arange(6).view(6, 1, 1)
    grid = cubemap.face_uv_to_grid(face, uv, size, pad).reshape(1, 6 * size, size, 2).expand(2, -1, -1, -1)
    assert grid.dtype == dtype and grid.abs().max() < 1
    for mode in ("nearest", "bilinear"):
        out = F_nn.grid_sample(atlas, grid, mode=mode, align_corners=False)
        out = out.reshape(2, 3, 6, size, size).transpose(1, 2)
        if mode == "nearest":
            assert torch.equal(out, cube)
        else:
            # float32 grids carry ~1e-7 relative rounding of the atlas coordinate (rows up to 6 n).
            tol = 1e-12 if dtype == f64 else 1e-5
            torch.testing.assert_close(out, cube, atol=tol, rtol=0)


def test_face_uv_to_grid_maps_padded_face_edges_to_atlas_edges():
    size, pad = 10, 2
    n = size + 2 * pad
    lo, hi = -pad - 0.5, size + pad - 0.5  # padded face edges in face pixels
    uv = torch.tensor([[lo, lo], [hi, hi]], dtype=f64)
    # face 0 fills the top sixth of the atlas, face 5 the bottom sixth
    first = torch.tensor([[-1.0, -1.0], [1.0, -1 + 2 / 6]], dtype=f64)
    last = torch.tensor([[-1.0, 1 - 2 / 6], [1.0, 1.0]], dtype=f64)
    torch.testing.assert_close(cubemap.face_uv_to_grid(0, uv, size, pad), first)
    torch.testing.assert_close(cubemap.face_uv_to_grid(5, uv, size, pad), last)
    # texel centre (0, 0) of face k is atlas pixel (pad, k n + pad)
    g = cubemap.face_uv_to_grid(torch.tensor([3]), torch.zeros(1, 2, dtype=f64), size, pad)
    x, y = pad, 3 * n + pad
    torch.testing.assert_close(
        g, torch.tensor([[(2 * x + 1) / n - 1, (2 * y + 1) / (6 * n) - 1]], dtype=f64)
    )


def _paths():
    t = torch.linspace(-0.15, 0.15, 1501, dtype=f64)[:, None]
    return {
        # front -> right across the middle of the seam
        "seam": torch.cat([torch.sin(math.pi / 4 + t), 0.2 + 0 * t, torch.cos(math.pi / 4 + t)], -1),
        # down -> right exactly through the cube corner (1, 1, 1)
        "corner": torch.tensor([1.0, 1, 1], dtype=f64) + t * torch.tensor([2.0, -3, 1], dtype=f64),
        # down -> front -> right, passing next to the corner: three faces
        "near corner": torch.tensor([1.0, 1, 1.02], dtype=f64) + t * torch.tensor([2.0, -3, 1], dtype=f64),
    }


def test_atlas_sampling_is_continuous_across_seams_and_corners():
    size, pad = 32, 1
    n = size + 2 * pad
    cube = smooth(padded_rays(size, 0))[None, :, None]
    atlas = cubemap.cubemap_to_atlas(cube, pad)
    copied = cubemap.faces_to_atlas(
        F_nn.pad(cube.reshape(6, 1, size, size), (pad,) * 4, mode="replicate").reshape(1, 6, 1, n, n)
    )
    bound = bilinear_error_bound(size)
    expected_faces = {"seam": {0, 3}, "corner": {3, 5}, "near corner": {0, 3, 5}}
    for name, rays in _paths().items():
        assert set(cubemap.ray_to_face(rays, size)[0].tolist()) == expected_faces[name]
        grid = cubemap.rays_to_grid(rays, size, pad).view(1, 1, -1, 2)
        truth = smooth(rays)
        jump_allowed = truth.diff().abs().max() + bound
        got = F_nn.grid_sample(atlas, grid, mode="bilinear", align_corners=False).flatten()
        assert (got - truth).abs().max() <= bound, name
        assert got.diff().abs().max() <= jump_allowed, name
        # the same check fails with a copied border: it is sensitive to seams
        bad = F_nn.grid_sample(copied, grid, mode="bilinear", align_corners=False).flatten()
        assert bad.diff().abs().max() > 2 * jump_allowed, name


def test_bicubic_sampling_with_pad_two_matches_an_exact_border():
    """torch's bicubic kernel (Keys, A = -0.75) has its own error even in a face's interior, so
    the oracle here is bicubic sampling of an atlas whose border holds the function's exact
    values at the border rays. Ours differs by at most the border's error times the cubic's
    weights on border texels (absolute sum < 2 in 2-D)."""
    size, pad = 32, 2
    n = size + 2 * pad
    cube = smooth(padded_rays(size, 0))[None, :, None]
    atlas = cubemap.cubemap_to_atlas(cube, pad)
    exact = cubemap.faces_to_atlas(smooth(padded_rays(size, pad))[None, :, None])
    copied = cubemap.faces_to_atlas(
        F_nn.pad(cube.reshape(6, 1, size, size), (pad,) * 4, mode="replicate").reshape(1, 6, 1, n, n)
    )
    border_error = (atlas - exact).abs().max()  # interior texels agree exactly
    assert border_error <= bilinear_error_bound(size)
    bound = 2 * border_error
    for name, rays in _paths().items():
        grid = cubemap.rays_to_grid(rays, size, pad).view(1, 1, -1, 2)
        ref = F_nn.grid_sample(exact, grid, mode="bicubic", align_corners=False).flatten()
        got = F_nn.grid_sample(atlas, grid, mode="bicubic", align_corners=False).flatten()
        bad = F_nn.grid_sample(copied, grid, mode="bicubic", align_corners=False).flatten()
        assert (got - ref).abs().max() <= bound, name
        assert got.diff().abs().max() <= ref.diff().abs().max() + bound, name
        assert (bad - ref).abs().max() > 2 * bound, name


def test_pad_faces_gradcheck_and_pad_zero():
    size, pad = 3, 2
    gen = torch.Generator().manual_seed(6)
    cube = torch.rand(1, 6, 2, size, size, generator=gen, dtype=f64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: cubemap.pad_faces(x, pad), (cube,))
    assert cubemap.pad_faces(cube, 0) is cube
    # a plan can be prepared once and passed (as a layer would hold it)
    plan = cubemap.border_plan(size, pad).to("cpu", torch.float32)
    out = cubemap.pad_faces(cube.detach().float(), pad, plan=plan)
    torch.testing.assert_close(out, cubemap.pad_faces(cube.detach(), pad).float())


# ----------------------------------------------------------------------------------------------
# Depth <-> range


def test_depth_range_round_trip_and_planes():
    size = 10
    rays = padded_rays(size, 0)  # [6, F, F, 3], a-component 1
    unit = rays / rays.norm(dim=-1, keepdim=True)
    # Plane z = 4 seen by the front face: planar depth 4, range 4 / cos(angle to the axis).
    front = cubemap.FACES.index("front")
    depth = torch.full((size, size), 4.0, dtype=f64)
    torch.testing.assert_close(cubemap.depth_to_range(depth), 4.0 / unit[front, ..., 2])
    # Ground plane y = 1.5 (y down) seen by every face, where the ray goes down.
    height = 1.5
    a = table()[:, 0]  # [6, 3]
    hits = unit[..., 1] > 1e-6
    dist = torch.where(hits, height / unit[..., 1].clamp_min(1e-6), torch.zeros_like(unit[..., 1]))
    point = unit * dist[..., None]
    planar = (point * a[:, None, None, :]).sum(-1)  # along each face's axis
    cube_depth = planar[None, :, None]  # [1, 6, 1, F, F]
    got = cubemap.depth_to_range(cube_depth)
    torch.testing.assert_close(got[0, :, 0][hits], dist[hits], atol=1e-12, rtol=1e-12)
    down = cubemap.FACES.index("down")
    torch.testing.assert_close(planar[down], torch.full((size, size), height, dtype=f64))
    # round trip, including padded faces and float32
    gen = torch.Generator().manual_seed(7)
    d = torch.rand(2, 6, 1, size + 4, size + 4, generator=gen, dtype=f64) * 50
    torch.testing.assert_close(cubemap.range_to_depth(cubemap.depth_to_range(d, pad=2), pad=2), d)
    torch.testing.assert_close(
        cubemap.depth_to_range(d, pad=2)[0, :, 0] / d[0, :, 0], padded_rays(size, 2).norm(dim=-1)
    )
    assert cubemap.depth_to_range(d.float()).dtype == torch.float32
    assert cubemap.depth_to_range(torch.tensor([[float("inf")]])).isinf().all()


# ----------------------------------------------------------------------------------------------
# Bad inputs


@pytest.mark.parametrize(
    "call,exc,match",
    [
        (lambda: cubemap.pad_faces(torch.zeros(1, 5, 1, 4, 4), 1), ValueError, "cubemap"),
        (lambda: cubemap.pad_faces(torch.zeros(1, 6, 1, 4, 3), 1), ValueError, "cubemap"),
        (lambda: cubemap.pad_faces(torch.zeros(6, 1, 4, 4), 1), ValueError, "cubemap"),
        (lambda: cubemap.pad_faces([[0.0]], 1), TypeError, "cubemap"),
        (lambda: cubemap.pad_faces(torch.zeros(1, 6, 1, 4, 4), -1), ValueError, "pad"),
        (lambda: cubemap.pad_faces(torch.zeros(1, 6, 1, 4, 4), 1.0), TypeError, "pad"),
        (lambda: cubemap.pad_faces(torch.zeros(1, 6, 1, 4, 4), 1, mode="cubic"), ValueError, "mode"),
        (lambda: cubemap.pad_faces(torch.zeros(1, 6, 1, 4, 4, dtype=torch.long), 1), TypeError, "bilinear"),
        (
            lambda: cubemap.pad_faces(torch.zeros(1, 6, 1, 4, 4), 1, plan=cubemap.border_plan(4, 2)),
            ValueError,
            "plan",
        ),
        (lambda: cubemap.ray_to_face(torch.zeros(4, 2), 4), ValueError, "rays"),
        (lambda: cubemap.ray_to_face(torch.zeros(4, 3, dtype=torch.long), 4), TypeError, "rays"),
        (lambda: cubemap.ray_to_face(torch.zeros(4, 3), 0), ValueError, "face_size"),
        (lambda: cubemap.ray_to_face(torch.zeros(4, 3), 4.0), TypeError, "face_size"),
        (lambda: cubemap.face_pixel_to_ray(6, torch.zeros(2), 4), ValueError, "face"),
        (lambda: cubemap.face_pixel_to_ray(0, torch.zeros(3), 4), ValueError, "uv"),
        (lambda: cubemap.face_pixel_to_ray(torch.zeros(2), torch.zeros(2, 2), 4), TypeError, "face"),
        (lambda: cubemap.face_uv_to_grid(0, torch.zeros(2, 2), 4, -1), ValueError, "pad"),
        (lambda: cubemap.face_uv_to_grid(0, torch.zeros(2, 3), 4, 1), ValueError, "uv"),
        (lambda: cubemap.border_plan(4, 0), ValueError, "pad"),
        (lambda: cubemap.atlas_to_faces(torch.zeros(1, 1, 10, 4)), ValueError, "atlas"),
        (lambda: cubemap.depth_to_range(torch.zeros(3, 4)), ValueError, "depth"),
        (lambda: cubemap.depth_to_range(torch.zeros(4, 4, dtype=torch.int32)), TypeError, "depth"),
        (lambda: cubemap.range_to_depth(torch.zeros(4, 4), pad=2), ValueError, "range_"),
    ],
)
def test_bad_inputs_raise_clear_errors(call, exc, match):
    with pytest.raises(exc, match=match):
        call()
