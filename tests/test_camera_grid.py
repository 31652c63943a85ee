"""Tests of ``render.kernels.camera_grid``: every pixel of ``B`` cameras -> rotated atlas grid, fused.

The oracle is the chain it replaces, built from public pieces: ``ot.Camera(model, params,
fov=..., blind_fov=...).ray_grid()`` (rays and validity: model domain, image, cones), then
``rotated_rays_to_grid_reference`` (einsum + ``cubemap.rays_to_grid``), invalid pixels at
(-2, -2). Images are small: compilation dominates (a kernel per model; inductor caches them).
"""

from __future__ import annotations

import warnings

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.cubemap import grid as cgrid
from omniscape_torch.render.kernels import camera as fg, image as fast

from conftest import CASES
from test_fastgrid import random_rotations

FACE, PAD = 16, 1
SIZE = (24, 32)


def scaled(params: list[float], size: tuple[int, int], model: str) -> list[float]:
    """``params`` of a CASES entry rescaled from its image size to ``SIZE``."""
    s = SIZE[1] / size[1]
    p = list(params)
    if model == "scaramuzza":   # cx, cy in pixels; the polynomial maps pixels -> z
        return p   # not closed form, not scaled: used at its own size below
    if model == "woodscape":   # cx, cy first; the polynomial's coefficients in pixels
        return [(p[0] + 0.5) * s - 0.5, (p[1] + 0.5) * s - 0.5, p[2], *(k * s for k in p[3:])]
    p[0:4] = [p[0] * s, p[1] * s, (p[2] + 0.5) * s - 0.5, (p[3] + 0.5) * s - 0.5]
    return p


def reference(model, params, size, rotation, fov, blind):
    grids, valids = [], []
    for i in range(params.shape[0]):
        cam = ot.Camera(model, params[i], size,
                        fov=None if fov is None else float(fov[i]),
                        blind_fov=None if blind is None or blind[i] == 0 else float(blind[i]))
        rays, valid = cam.ray_grid()
        grid = cgrid.rotated_rays_to_grid_reference(rays, rotation[i], FACE, PAD)[0]
        grids.append(torch.where(valid[..., None], grid, torch.full_like(grid, -2.0)))
        valids.append(valid)
    return torch.stack(grids), torch.stack(valids)


def theta_of(model, params, size) -> torch.Tensor:
    """Angle from the axis of every pixel's ray, per camera (to excuse cone-edge rounding)."""
    out = []
    for i in range(params.shape[0]):
        rays, _ = ot.Camera(model, params[i], size).ray_grid()
        out.append(torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2]))
    return torch.stack(out)


def batch_of(model: str, dtype):
    params, size = CASES[model][-1]
    if model != "scaramuzza":
        params, size = scaled(params, size, model), SIZE
    batch = 3
    p = torch.tensor(params, dtype=torch.float64).repeat(batch, 1)
    cx = 0 if model in ("scaramuzza", "woodscape") else 2
    p[:, cx] += torch.tensor([0.0, 0.7, -1.3])   # a different camera per sample
    return p.to(dtype), size


@pytest.mark.parametrize("model", sorted(CASES))
@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_matches_the_camera_chain(model, compiled):
    params, size = batch_of(model, torch.float32)
    if compiled and model not in fg._CLOSED_FORM and model not in fg.RADIAL:
        pytest.skip("neither closed form nor radial: the eager unprojection, tested with "
                    "compiled=False")
    rot = random_rotations(3, torch.float32, seed=4)
    fov = torch.tensor([3.0, 2.5, 1.9])
    blind = torch.tensor([0.2, 0.0, 0.4])
    grid, valid = fg.camera_grid(model, params, size, FACE, PAD, rotation=rot, fov=fov,
                                 blind_fov=blind, compiled=compiled)
    ref_grid, ref_valid = reference(model, params, size, rot, fov, blind)
    assert grid.shape == ref_grid.shape and grid.dtype == torch.float32
    # the cones are compared with atan2 of float32 rays: a pixel within rounding of a cone's
    # edge may fall either way, nowhere else
    theta = theta_of(model, params, size)
    edge = ((theta - 0.5 * fov[:, None, None]).abs() < 1e-5) \
        | ((theta - 0.5 * blind[:, None, None]).abs() < 1e-5)
    assert torch.equal(valid & ~edge, ref_valid & ~edge)
    assert bool(valid.any()) and not bool(valid.all())
    both = valid & ref_valid
    assert torch.allclose(grid[both], ref_grid[both], rtol=0, atol=2e-5)
    assert bool((grid[~valid] == -2).all())


def test_defaults_are_the_models_domain_and_identity():
    params, size = batch_of("equidistant", torch.float64)
    grid, valid = fg.camera_grid("equidistant", params, size, FACE, PAD, compiled=False)
    eye = torch.eye(3, dtype=torch.float64).expand(3, 3, 3)
    ref_grid, ref_valid = reference("equidistant", params, size, eye, None, None)
    assert torch.equal(valid, ref_valid) and torch.equal(grid, ref_grid)


@pytest.mark.slow
def test_unified_with_distortion_goes_eager_and_matches():
    params, size = batch_of("unified", torch.float64)
    assert bool(params[:, 5:].ne(0).any())
    rot = random_rotations(3, torch.float64, seed=5)
    grid, valid = fg.camera_grid("unified", params, size, FACE, PAD, rotation=rot)
    ref_grid, ref_valid = reference("unified", params, size, rot, None, None)
    assert torch.equal(valid, ref_valid)
    assert torch.allclose(grid, ref_grid, rtol=0, atol=1e-12)


def test_zero_blind_cone_keeps_the_axis_pixel():
    params = torch.tensor([[10.0, 10.0, 15.0, 11.0]])   # the axis through pixel (15, 11)
    _, valid = fg.camera_grid("equidistant", params, SIZE, FACE, PAD,
                              fov=torch.tensor([3.0]), blind_fov=torch.tensor([0.0]))
    assert bool(valid[0, 11, 15])
    _, valid = fg.camera_grid("equidistant", params, SIZE, FACE, PAD,
                              blind_fov=torch.tensor([0.05]))
    assert not bool(valid[0, 11, 15]) and bool(valid[0, 11, 17])


def test_forward_only_even_with_grad_inputs():
    params, size = batch_of("equisolid", torch.float32)
    params.requires_grad_(True)
    grid, valid = fg.camera_grid("equisolid", params, size, FACE, PAD)
    assert not grid.requires_grad and not valid.requires_grad


def test_compile_failure_warns_once_and_falls_back(monkeypatch):
    monkeypatch.setattr(cgrid, "_COMPILED", {})
    monkeypatch.setattr(cgrid, "_FAILURES", {})

    def broken_compile(*args, **kwargs):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(fg.torch, "compile", broken_compile)
    monkeypatch.setattr(fg, "radial_table", lambda *args: None)   # the compiled kernel's case
    params, size = batch_of("stereographic", torch.float32)
    expected = fg.camera_grid("stereographic", params, size, FACE, PAD, compiled=False)
    with pytest.warns(UserWarning) as rec:   # the camera kernel, then the rotated grid's
        got = fg.camera_grid("stereographic", params, size, FACE, PAD)
    assert [str(w.message).split(":")[0] for w in rec] == ["camera_grid", "rotated_rays_to_grid"]
    assert "stereographic" in str(rec[0].message) and rec[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = fg.camera_grid("stereographic", params, size, FACE, PAD)
    for a, b in ((got, expected), (again, expected)):
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert ("camera", "stereographic", torch.float32, torch.float32, "cpu", True) \
        in cgrid.compile_failures()


@pytest.mark.parametrize("kwargs, match", [
    (dict(model="nope"), "nope"),
    (dict(params=torch.ones(4)), "params"),
    (dict(image_size=(0, 4)), "image_size"),
    (dict(rotation=torch.eye(3)), "rotation"),
    (dict(fov=torch.ones(2)), "fov"),
    (dict(blind_fov=[0.1, 0.1, 0.1]), "blind_fov"),
    (dict(dtype=torch.int32), "dtype"),
])
def test_bad_inputs_raise(kwargs, match):
    params, size = batch_of("equidistant", torch.float32)
    args = dict(model="equidistant", params=params, image_size=size, face_size=FACE, pad=PAD)
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError, KeyError), match=match):
        fg.camera_grid(**args)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kannala_brandt_table_is_within_a_hundredth_of_a_pixel(dtype):
    """The camera kernel unprojects Kannala-Brandt through a radius -> angle table per camera
    (then one Newton step): projected back by the model's own forward polynomial, every valid
    pixel within the field of view of the cameras ``RandomOmniCamera`` draws (1024 px wide, up
    to 200 degrees, its distortion; the fov stays a margin short of the fold, where the inverse
    has a square-root singularity) lands within 0.01 px of where it started, as with Newton's
    per-pixel inverse."""
    from omniscape_torch.cameras.radial import (kannala_brandt_project,
                                                kannala_brandt_tabulate,
                                                kannala_brandt_unproject_table_xyz)
    aug = ot.augment.RandomOmniCamera((1024, 1024), 8, mode="fisheye",
                                      fisheye_models=("kannala_brandt",), seed=3)
    drawn = aug.forward_parameters(6)
    params = drawn["camera_params"][:, :8].to(dtype)
    half_fov = 0.5 * drawn["fov"].to(dtype)[:, None, None]   # the field the module renders
    table = kannala_brandt_tabulate(params, (1024, 1024))
    v, u = torch.meshgrid(torch.arange(0, 1024, 7, dtype=dtype),
                          torch.arange(0, 1024, 7, dtype=dtype), indexing="ij")
    x, y, z, valid = kannala_brandt_unproject_table_xyz(u, v, table[:, None, None])
    assert bool(valid.any(dim=(1, 2)).all())
    pixels, ok = kannala_brandt_project(torch.stack((x, y, z), -1), params[:, None, None])
    error = (pixels - torch.stack((u, v), -1).expand_as(pixels)).norm(dim=-1)
    keep = valid & ok & (z >= torch.cos(half_fov))
    assert float(error[keep].max()) <= 0.01
    # the pixels beyond the table's last radius (the fold or pi) are invalid, as for Newton
    _, newton_valid = ot.Camera("kannala_brandt", params[0], (1024, 1024)).ray_grid()
    assert torch.equal(valid[0], newton_valid[::7, ::7])


def test_kannala_brandt_sweep_is_newtons_inverse():
    """The radial tables' Kannala-Brandt inverse (a forward sweep, interpolated in
    ``sqrt(r_end - r)``, polished by two Newton steps) gives the safeguarded Newton's angles of
    the model's own unprojection to 1e-9 rad, up to next to the fold, for lenses distorted
    well beyond RandomOmniCamera's draws."""
    from omniscape_torch.cameras.radial import kannala_brandt_angles, kannala_brandt_domain_end
    aug = ot.augment.RandomOmniCamera((512, 512), 8, fisheye_models=("kannala_brandt",),
                                      kb_distortion=0.08, seed=4)
    params = aug.forward_parameters(12)["camera_params"][:, :8]
    end = kannala_brandt_domain_end(params)
    w = torch.linspace(0, 1, 500, dtype=torch.float64)
    radii = end[:, None] * (1 - (1 - w) ** 2)       # crowded next to the fold
    radii[:, -1] = end * (1 - 1e-10)
    theta = kannala_brandt_angles(params, radii)
    pixels = torch.stack((params[:, 2:3] + radii * params[:, 0:1],
                          params[:, 3:4].expand_as(radii)), -1)
    rays, ok = ot.cameras.get_model("kannala_brandt").unproject(pixels, params[:, None])
    newton = torch.atan2(rays[..., 0], rays[..., 2])
    assert float(ok.double().mean()) > 0.99
    assert float((theta - newton)[ok].abs().max()) < 1e-9   # 1.6e-7 px at focal 160


@pytest.mark.slow
@pytest.mark.parametrize("mode, model", [("fisheye", m) for m in ot.augment.FISHEYE_MODELS]
                         + [("catadioptric", "unified")])
def test_radial_table_grid_is_within_half_a_hundredth_of_a_texel_at_full_size(mode, model):
    """On the CPU every radially symmetric camera goes through a radius -> ray table per
    camera (``radial_table``, the C++ op): for the cameras ``RandomOmniCamera`` draws at 1024 px
    (Kannala-Brandt up to its fold, unified mirrors), the grid is within 0.005 texel of the
    exact chain in float64 (closed forms, Newton's inverse per pixel) on 512-texel faces (0.005
    texel is 1e-5 rad), the same pixels valid; a texel there spans about 1.3 px of the image."""
    face, pad, size = 512, 2, (1024, 1024)
    aug = ot.augment.RandomOmniCamera(size, face, mode=mode, seed=3, **(
        dict(fisheye_models=(model,)) if mode == "fisheye" else {}))
    drawn = aug.forward_parameters(4)
    params = drawn["camera_params"][:, :len(ot.cameras.registry.get_model(model).param_names)]
    cones = dict(rotation=drawn["rotation"], fov=drawn["fov"], blind_fov=drawn["blind_fov"])
    grid, valid = fg.camera_grid(model, params, size, face, pad, **cones)
    n = face + 2 * pad
    for i in range(4):
        blind = float(drawn["blind_fov"][i])
        cam = ot.Camera(model, params[i].double(), size, fov=float(drawn["fov"][i]),
                        blind_fov=blind if blind > 0 else None)
        rays, ref_valid = cam.ray_grid()
        ref = cgrid.rotated_rays_to_grid_reference(rays, drawn["rotation"][i].double(), face,
                                                   pad)[0]
        assert torch.equal(valid[i], ref_valid)
        texels = (grid[i].double() - ref)[ref_valid] * torch.tensor([n / 2, 6 * n / 2],
                                                                    dtype=torch.float64)
        assert float(texels.norm(dim=-1).max()) <= 5e-3


def test_radial_table_refuses_what_is_not_radial():
    """Tangential distortion (unified ``p1, p2``) has no radius -> ray table: those cameras
    take the exact path, as does a model that is not radial."""
    params, size = batch_of("unified", torch.float64)
    tangential = params.clone()
    tangential[:, 7] = 1e-3
    assert fg.radial_table("unified", tangential, size) is None
    assert fg.radial_table("unified", params.clone().index_fill_(1, torch.tensor([7, 8]), 0.0),
                           size) is not None
    eq = torch.tensor([[100.0, 100.0, 50.0, 40.0]], dtype=torch.float64)
    assert fg.radial_table("equirectangular", eq, (80, 100)) is None


def test_radial_table_of_a_real_ocamcalib_calibration():
    """The shared OCamCalib file (1600 x 1600, a real lens with its affine terms) through the
    table path: the same valid pixels as the exact chain (Scaramuzza's polynomial, Newton per
    pixel, float64) and grid points within 0.005 texel on 512-texel faces, except where a ray
    lies within float32 rounding of an edge between two faces (one pixel here, 2e-8 apart):
    there either face is right."""
    from conftest import OCAMCALIB_FILE
    cam = ot.Camera.from_ocamcalib(OCAMCALIB_FILE)
    face, pad = 512, 2
    rot = random_rotations(2, torch.float64, seed=7)
    params = cam.params.double()[None].expand(2, -1)
    assert fg.radial_table("scaramuzza", params, cam.image_size) is not None
    grid, valid = fg.camera_grid("scaramuzza", params.float(), cam.image_size, face, pad,
                                 rotation=rot.float())
    rays, ref_valid = cam.ray_grid()
    n = face + 2 * pad
    for i in range(2):
        ref = cgrid.rotated_rays_to_grid_reference(rays.double(), rot[i], face, pad)[0]
        assert torch.equal(valid[i], ref_valid)
        top = (rays.double() @ rot[i].T).abs().sort(-1, descending=True).values
        tie = (top[..., 0] - top[..., 1]) < 1e-6
        assert int((ref_valid & tie).sum()) <= 5
        keep = ref_valid & ~tie
        texels = (grid[i].double() - ref)[keep] * torch.tensor([n / 2, 6 * n / 2],
                                                               dtype=torch.float64)
        assert float(texels.norm(dim=-1).max()) <= 5e-3


# ------------------------------------------------------------------------------------------
# camera_grid(lazy=True): the cameras' rays, read by the sampling pass
# ------------------------------------------------------------------------------------------
def lazy_and_eager(model: str, dtype=torch.float32):
    params, size = batch_of(model, dtype)
    kwargs = dict(rotation=random_rotations(3, dtype, seed=4),
                  fov=torch.tensor([3.0, 2.5, 1.9], dtype=dtype),
                  blind_fov=torch.tensor([0.2, 0.0, 0.4], dtype=dtype))
    lazy = fg.camera_grid(model, params, size, FACE, PAD, lazy=True, **kwargs)
    return lazy, fg.camera_grid(model, params, size, FACE, PAD, **kwargs), size


@pytest.mark.parametrize("model", sorted(m for m in CASES if m in fg.RADIAL))
def test_lazy_grid_is_the_tables_grid(model):
    """The lazy grid's validity is the table path's exactly; its grid, built from its rays by
    the compiled grid maths, is the one the C++ op writes from the same rays (to float32
    rounding of the rotation); ``rows`` are views of both."""
    lazy, (grid, valid), size = lazy_and_eager(model)
    if fg.radial_table(model, batch_of(model, torch.float32)[0], size) is None:
        assert isinstance(lazy, tuple)   # no table (tangential distortion): the grid itself
        return
    assert isinstance(lazy, fast.CameraGrid) and len(lazy) == 3
    assert lazy.rays.shape == (3, *size, 3) and lazy.dtype == torch.float32
    assert torch.equal(lazy.valid, valid) and bool(valid.any())
    torch.testing.assert_close(lazy.tensor(), grid, atol=1e-6, rtol=0)
    part = lazy.rows(1, 3)
    assert len(part) == 2 and torch.equal(part.valid, valid[1:3])
    assert torch.equal(part.tensor(), lazy.tensor()[1:3])
    assert torch.equal(lazy.rows(0, 2).rays, lazy.rays[:2])   # before tensor(): built apart
    norms = torch.linalg.vector_norm(lazy.rays[lazy.valid], dim=-1)
    torch.testing.assert_close(norms, torch.ones_like(norms), atol=1e-5, rtol=0)


@pytest.mark.parametrize("fast_path", [True, False])
def test_layer_renders_a_lazy_grid_as_the_grid(fast_path):
    """``OmniProjection.render(grid=CameraGrid)`` gives the images of the grid itself: labels and
    validity exactly (nearest taps go through the grid point), RGB and depth to the grid's
    float32 rounding (bilinear taps come from the rays directly), uint8 within a level; on the
    reference path (no fast sampler) the grid is built and the images are the grid's."""
    lazy, (grid, valid), size = lazy_and_eager("kannala_brandt")
    gen = torch.Generator().manual_seed(3)
    cube = torch.rand(3, 6, 3, FACE, FACE, generator=gen)
    depth = 1 + 9 * torch.rand(3, 6, FACE, FACE, generator=gen)
    labels = torch.randint(0, 13, (3, 6, FACE, FACE), generator=gen)
    layer = ot.OmniProjection(ot.Camera("equidistant", [10.0, 10.0, 15.5, 11.5], size), FACE,
                              fast=fast_path)
    with torch.no_grad():
        got = layer.render(rgb=cube, depth=depth, labels=labels, grid=lazy)
        want = layer.render(rgb=cube, depth=depth, labels=labels, grid=(grid, valid))
        u8 = (cube * 255).round().to(torch.uint8)
        got_u8 = layer.render(rgb=u8, grid=lazy)["rgb"]
        want_u8 = layer.render(rgb=u8, grid=(grid, valid))["rgb"]
    assert torch.equal(got["valid"], want["valid"]) and torch.equal(got["labels"],
                                                                     want["labels"])
    rounding = 3 * (FACE + 2 * PAD) * torch.finfo(torch.float32).eps   # tests/test_fastpath.py
    for key, span in (("rgb", 1.0), ("depth", 9.0)):
        torch.testing.assert_close(got[key], want[key], atol=rounding * span + 1e-6, rtol=0)
    assert (got_u8.int() - want_u8.int()).abs().max() <= 1
    with pytest.raises(ValueError, match="grid: expected cameras"):
        ot.OmniProjection(layer.camera, FACE + 2).render(
            rgb=torch.rand(3, 6, 3, FACE + 2, FACE + 2), grid=lazy)
    with pytest.raises(ValueError, match="grid: a given grid already holds the attitude"):
        layer.render(rgb=cube, grid=lazy, rotation=torch.eye(3))
