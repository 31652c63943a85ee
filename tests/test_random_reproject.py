"""Tests of ``ot.augment.RandomReproject``: perspective images through random fisheye lenses.

Oracles: an analytic one (a ramp image holds its own pixel coordinates, and each output pixel's
source pixel is computed here in numpy from the equidistant model's formula and the pinhole's:
no code of the package), ``ot.reproject`` itself (the exact chain the module's slow path is,
the drawn camera as its destination), and the fast path against the exact one.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import augment

DEG = math.pi / 180
SRC = (48, 64)     # source images (H, W)
OUT = (40, 44)     # fisheye images (H, W)
#: The C++ path's rays come from a table per camera: within 0.005 texel of the exact chain at
#: 1024 px (tests/test_camera_grid.py); at these sizes a hundredth of a source pixel bounds it.
TABLE_PX = 0.01


def ramp(batch: int, dtype=torch.float64) -> torch.Tensor:
    """``(B, 2, H, W)``: channel 0 holds the column, channel 1 the row of each pixel."""
    v, u = torch.meshgrid(torch.arange(SRC[0], dtype=dtype), torch.arange(SRC[1], dtype=dtype),
                          indexing="ij")
    return torch.stack((u, v)).expand(batch, 2, *SRC).contiguous()


def source_pixels(params: dict, intrinsics: np.ndarray, index: int) -> tuple[np.ndarray, ...]:
    """Each fisheye pixel's source pixel (u, v) and whether its ray meets the source image, in
    float64 numpy from the formulas: equidistant ``r = f theta``, ``R`` the drawn rotation,
    pinhole ``u = fx x / z + cx``."""
    fx, fy, cx, cy = params["camera_params"][index, :4].numpy()
    y, x = np.mgrid[0:OUT[0], 0:OUT[1]].astype(np.float64)
    mx, my = (x - cx) / fx, (y - cy) / fy
    theta = np.hypot(mx, my)
    s = np.where(theta > 0, np.sin(theta) / np.where(theta > 0, theta, 1), 1.0)
    rays = np.stack((s * mx, s * my, np.cos(theta)), -1)
    src = rays @ params["rotation"][index].numpy().T
    kx, ky, kcx, kcy = intrinsics[index]
    z = src[..., 2]
    u = kx * src[..., 0] / np.where(z > 0, z, 1) + kcx
    v = ky * src[..., 1] / np.where(z > 0, z, 1) + kcy
    fov = float(params["fov"][index])
    seen = (z > 0) & (theta <= fov / 2) & (u >= -0.5) & (u <= SRC[1] - 0.5) & (v >= -0.5) \
        & (v <= SRC[0] - 0.5)
    return u, v, seen, theta


@pytest.mark.parametrize("fast", [True, False])
def test_each_pixel_reads_its_ray_in_the_source_image(fast):
    """A ramp image sampled bilinearly gives back each output pixel's source coordinates: they
    match the formulas (interior pixels; at the rim the taps are clamped), validity too (away
    from the cone and image edges, where rounding decides). Point samples
    (``antialias=False``): the prefilter averages the ramp over footprints that the image
    edges clip."""
    aug = ot.augment.RandomReproject(OUT, source_fov=80 * DEG, seed=3,
                                     fov_range=(120 * DEG, 180 * DEG), antialias=False)
    image = ramp(3)
    params = aug.forward_parameters(3)
    k = aug.source_intrinsics(SRC, 3)
    with torch.set_grad_enabled(not fast):
        out = aug.render(image.requires_grad_(not fast), params)
    assert out["rgb"].dtype == torch.float64 and out["valid"].shape == (3, 1, *OUT)
    tol = TABLE_PX if fast else 1e-9
    compared = 0
    for b in range(3):
        u, v, seen, theta = source_pixels(params, k.numpy(), b)
        got = out["rgb"][b].detach().numpy()
        valid = out["valid"][b, 0].numpy()
        edges = (np.abs(theta - float(params["fov"][b]) / 2) < 1e-3) | (np.abs(u + 0.5) < tol) \
            | (np.abs(u - SRC[1] + 0.5) < tol) | (np.abs(v + 0.5) < tol) \
            | (np.abs(v - SRC[0] + 0.5) < tol)
        assert np.array_equal(valid & ~edges, seen & ~edges)
        inner = seen & (u >= 0) & (u <= SRC[1] - 1) & (v >= 0) & (v <= SRC[0] - 1)
        np.testing.assert_allclose(got[0][inner], u[inner], atol=tol, rtol=0)
        np.testing.assert_allclose(got[1][inner], v[inner], atol=tol, rtol=0)
        assert np.all(got[:, ~valid] == 0)
        compared += int(inner.sum())
    assert compared > 500


def drawn_camera(params: dict, index: int) -> ot.Camera:
    name = params["model"][index]
    p = params["camera_params"][index, :int(params["num_params"][index])]
    return ot.Camera(name, p, OUT, fov=float(params["fov"][index]))


def test_exact_path_is_ot_reproject_of_the_drawn_camera():
    """Without the fast path, each sample is ``ot.reproject`` of its image from the source
    pinhole into its drawn camera, turned by its drawn rotation: the same images, labels and
    validity."""
    gen = torch.Generator().manual_seed(0)
    image = torch.rand(2, 3, *SRC, generator=gen, dtype=torch.float64)
    labels = torch.randint(0, 13, (2, *SRC), generator=gen)
    k = torch.tensor([[50.0, 52.0, 31.0, 24.5], [40.0, 40.0, 32.5, 23.0]], dtype=torch.float64)
    aug = ot.augment.RandomReproject(OUT, seed=1, fisheye_models=("kannala_brandt",
                                                                  "double_sphere"))
    params = aug.forward_parameters(2)
    out = aug.render(image.requires_grad_(), params, labels=labels, intrinsics=k)
    for b in range(2):
        source = ot.Camera("pinhole", k[b], SRC)
        want, valid = ot.reproject(image[b:b + 1], source, drawn_camera(params, b),
                                   rotation=params["rotation"][b], antialias=aug.antialias)
        ids, _ = ot.reproject(labels[b:b + 1], source, drawn_camera(params, b),
                              rotation=params["rotation"][b])
        assert torch.equal(out["valid"][b], valid[0])
        torch.testing.assert_close(out["rgb"][b], want[0], atol=1e-12, rtol=0)
        assert torch.equal(out["labels"][b], ids[0])
    out["rgb"].sum().backward()   # differentiable with respect to the images
    assert image.grad is not None and bool(image.grad.abs().sum() > 0)


@pytest.mark.parametrize("models", [("equidistant",), augment.FISHEYE_MODELS])
def test_fast_path_is_the_exact_one(models):
    """The C++ path (table rays, ``sample_image``) against the exact chain on the same draws:
    validity equal away from edges, uint8 RGB within a level of the float image rounded (the
    table's hundredth of a pixel on a noise image), labels and depth the same except where a
    pixel lies within that of a texel boundary (nearest rounds either way). Point samples:
    the two paths' antialiasing filters differ (``fast.mip_image``, ``antialias.mip_sample``;
    each tested against its rule in test_mip_image.py and test_antialias.py)."""
    gen = torch.Generator().manual_seed(1)
    image = torch.randint(0, 256, (4, 3, *SRC), generator=gen, dtype=torch.uint8)
    labels = torch.randint(0, 13, (4, *SRC), generator=gen, dtype=torch.uint8)
    depth = 1 + torch.rand(4, *SRC, generator=gen) * 20
    aug = ot.augment.RandomReproject(OUT, source_fov=100 * DEG, seed=2, fisheye_models=models,
                                     antialias=False)
    params = aug.forward_parameters(4)
    with torch.no_grad():
        fast = aug.render(image, params, labels=labels, depth=depth)
    floats = image.double().requires_grad_()
    exact = aug.render(floats, params, labels=labels.long(), depth=depth.double())
    assert fast["rgb"].dtype == torch.uint8 and fast["labels"].dtype == torch.int64
    both = fast["valid"] & exact["valid"]
    assert float((fast["valid"] != exact["valid"]).float().mean()) < 0.002
    assert int(both.sum()) > 500
    rounded = (exact["rgb"].detach() + 0.5).floor()
    diff = (fast["rgb"].double() - rounded).abs()
    assert float(diff[both.expand_as(diff)].max()) <= 1
    agree = (fast["labels"] == exact["labels"])[both[:, 0]]
    assert float(agree.float().mean()) > 0.995
    same_depth = torch.isclose(fast["depth"].double(), exact["depth"].detach(), rtol=1e-5)
    assert float(same_depth[both].float().mean()) > 0.995
    assert bool((fast["labels"][~fast["valid"][:, 0]] == 255).all())
    assert bool((fast["rgb"][~fast["valid"].expand_as(fast["rgb"])] == 0).all())


def test_depth_is_range_or_z():
    """Planar source depth (a fronto-parallel wall at 10 m) comes back as the range along each
    fisheye ray, ``10 / cos(angle to the source axis)``, or as ``z`` along the fisheye's axis."""
    wall = torch.full((1, *SRC), 10.0)
    for output in ("range", "z"):
        aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=4, depth_output=output)
        params = aug.forward_parameters(1)
        with torch.no_grad():
            out = aug(None, depth=wall, params=params)
        valid = out["valid"][0, 0]
        rays, _ = drawn_camera(params, 0).ray_grid()
        src = rays.double() @ params["rotation"][0].T
        expect = 10 / src[..., 2]
        if output == "z":
            expect = expect * rays[..., 2].double()
        torch.testing.assert_close(out["depth"][0, 0][valid].double(), expect[valid],
                                   rtol=1e-4, atol=0)
        assert bool((out["depth"][0, 0][~valid] == 0).all())


def test_layouts_dtypes_and_replay():
    """Channels-last images give the channels-first values in (B, H, W, C); uint8 into float32
    is the uint8 image scaled; float16 is sampled in float32; a replay of ``params`` (with the
    intrinsics it recorded) renders the same; ``same_on_batch`` draws once."""
    gen = torch.Generator().manual_seed(5)
    image = torch.randint(0, 256, (2, 3, *SRC), generator=gen, dtype=torch.uint8)
    first = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=6)
    last = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=6, channels_last=True)
    scaled = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=6,
                                        out_dtype=torch.float32)
    with torch.no_grad():
        a = first(image)
        b = last(image.permute(0, 2, 3, 1).contiguous())
        c = scaled(image)
        again = first(image, params=a["params"])
        half = first(image.half() / 255, params=a["params"])
        single = first(image.float() / 255, params=a["params"])
    assert b["rgb"].shape == (2, *OUT, 3) and torch.equal(b["rgb"].permute(0, 3, 1, 2), a["rgb"])
    assert c["rgb"].dtype == torch.float32
    assert float((c["rgb"] * 255 - a["rgb"].float()).abs().max()) <= 0.5 + 1e-4
    assert torch.equal(again["rgb"], a["rgb"]) and torch.equal(again["valid"], a["valid"])
    assert half["rgb"].dtype == torch.float16
    torch.testing.assert_close(half["rgb"].float(), single["rgb"], atol=2e-3, rtol=0)
    assert a["params"]["intrinsics"].shape == (2, 4)
    same = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=6, same_on_batch=True)
    params = same.forward_parameters(3)
    assert torch.equal(params["rotation"][0], params["rotation"][2])


def test_seeds_calls_and_generators():
    """A seed reproduces a run; calls differ; a generator passed to a call wins; different
    lens models are drawn from one list."""
    def draws(**kwargs):
        aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, **kwargs)
        return [aug.forward_parameters(8) for _ in range(2)]
    one, two = draws(seed=7), draws(seed=7)
    assert torch.equal(one[0]["camera_params"], two[0]["camera_params"])
    assert not torch.equal(one[0]["rotation"], one[1]["rotation"])
    mixed = draws(seed=8, fisheye_models=augment.FISHEYE_MODELS)[0]
    assert len(set(mixed["model"])) > 2
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=9)
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert torch.equal(aug.forward_parameters(2, generator=g1)["rotation"],
                       aug.forward_parameters(2, generator=g2)["rotation"])


def test_draws_are_the_documented_uniforms():
    """The draw of a batch reads one stream, family after family (``u_model``, ``fov``,
    ``k (B, 4)``, ``lens (B, 2)``, ``scale``, ``jitter (B, 2)``, ``yaw``, ``pitch``, ``roll``,
    ``applied``, ``coverage``): each value is ``lo + (hi - lo) u`` of its uniforms, recomputed
    here from the generator's stream and the documented ranges (jitter ``(2u - 1) j``,
    ``applied`` ``u < p``, the attitude 0 where not applied, ``R`` of the angles)."""
    n, seed = 6, 13
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, center_jitter=3.0, p=0.5,
                                     fov_range=(150 * DEG, 190 * DEG),
                                     coverage_range=(0.4, 0.8))
    params = aug.forward_parameters(n, generator=torch.Generator().manual_seed(seed),
                                    intrinsics=aug.source_intrinsics(SRC, n), source_size=SRC)
    u = torch.rand(16 * n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    block = {name: u[n * a:n * b].reshape(n, b - a) for name, a, b in (
        ("fov", 1, 2), ("jitter", 9, 11), ("yaw", 11, 12), ("pitch", 12, 13), ("roll", 13, 14),
        ("applied", 14, 15), ("coverage", 15, 16))}
    def uniform(name, lo, hi):
        return lo + (hi - lo) * block[name][:, 0]
    applied = block["applied"][:, 0] < 0.5
    assert torch.equal(params["applied"], applied) and 0 < int(applied.sum()) < n
    assert torch.equal(params["fov"], uniform("fov", 150 * DEG, 190 * DEG))
    assert torch.equal(params["coverage"], uniform("coverage", 0.4, 0.8))
    for name, bound in (("yaw", 10 * DEG), ("pitch", 10 * DEG), ("roll", 25 * DEG)):
        want = torch.where(applied, uniform(name, -bound, bound), 0.0)
        assert torch.equal(params[name], want), name
    centre = torch.tensor([(OUT[1] - 1) / 2, (OUT[0] - 1) / 2], dtype=torch.float64)
    assert torch.equal(params["camera_params"][:, 2:4], (2 * block["jitter"] - 1) * 3.0 + centre)
    rotation = ot.presets.yaw_pitch_roll_to_matrix(params["yaw"], params["pitch"], params["roll"])
    torch.testing.assert_close(params["rotation"], rotation, atol=1e-15, rtol=0)


def test_drawn_lenses_see_their_drawn_field_of_view():
    """Every lens drawn is valid out to its returned fov / 2 and its image circle is inscribed
    in the image: the unified, EUCM and double sphere lenses whose reach is shorter than the
    drawn fov have it cut to their reach."""
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=10,
                                     fisheye_models=augment.FISHEYE_MODELS,
                                     fov_range=(190 * DEG, 230 * DEG),
                                     ds_xi_range=(-0.3, -0.3), ds_alpha_range=(0.7, 0.7))
    params = aug.forward_parameters(64)
    assert bool((params["fov"] <= 230 * DEG + 1e-12).all())
    for b in range(64):
        camera = drawn_camera(params, b)
        model = ot.cameras.get_model(params["model"][b])
        reach = float(model.max_angle(camera.params.double()))
        half = float(params["fov"][b]) / 2
        assert half <= reach - augment.draw._ANGLE_MARGIN + 1e-12
        edge = torch.tensor([[math.sin(half), 0.0, math.cos(half)]], dtype=torch.float64)
        pixel, ok = model.project(edge, camera.params.double())
        assert bool(ok.all())
        radius = float(pixel[0, 0] - camera.params[2])
        assert abs(radius - (min(OUT) / 2 - 0.5)) < 1e-6 * OUT[0]
    capped = [b for b in range(64) if params["model"][b] == "double_sphere"]
    assert capped and all(float(params["fov"][b]) < 197 * DEG for b in capped)


class Image(torch.Tensor):
    """A stand-in for torchvision's ``tv_tensors.Image`` (a ``torch.Tensor`` subclass: what
    the modules see of it; torchvision's own wheels on PyPI are CUDA builds that do not load
    with the CPU torch this project pins)."""


class Mask(torch.Tensor):
    """A stand-in for ``tv_tensors.Mask``."""


def test_tensor_subclasses_in_and_out():
    """``tv_tensors``-like inputs are read as the tensors they hold, and their outputs come back
    in their classes (torchvision's ``transforms.v2`` routes them by class), for both modules."""
    gen = torch.Generator().manual_seed(11)
    image = torch.rand(2, 3, *SRC, generator=gen).as_subclass(Image)
    labels = torch.randint(0, 13, (2, *SRC), generator=gen).as_subclass(Mask)
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=12)
    with torch.no_grad():
        out = aug({"rgb": image, "labels": labels})
        plain = aug({"rgb": image.as_subclass(torch.Tensor),
                     "labels": labels.as_subclass(torch.Tensor)}, params=out["params"])
    assert type(out["rgb"]) is Image and type(out["labels"]) is Mask
    assert type(out["valid"]) is Mask   # valid is a mask: v2's geometric transforms move it
    assert type(plain["valid"]) is torch.Tensor
    assert torch.equal(out["rgb"].as_subclass(torch.Tensor), plain["rgb"])
    assert torch.equal(out["valid"].as_subclass(torch.Tensor), plain["valid"])
    cube = torch.rand(2, 6, 3, 8, 8, generator=gen).as_subclass(Image)
    ids = torch.randint(0, 13, (2, 6, 8, 8), generator=gen).as_subclass(Mask)
    omni = ot.augment.RandomOmniCamera((16, 16), 8, seed=0)
    with torch.no_grad():
        got = omni({"rgb": cube, "labels": ids})
    assert type(got["rgb"]) is Image and type(got["labels"]) is Mask
    assert type(got["valid"]) is Mask


@pytest.mark.parametrize("call, error, match", [
    (lambda a: a(torch.rand(3, 8)), ValueError, r"image: expected \(B, C, H, W\)"),
    (lambda a: a(torch.randint(0, 9, (2, 3, 8, 8))), TypeError, "image: expected a floating"),
    (lambda a: a(torch.rand(2, 3, 8, 8), labels=torch.rand(2, 8, 8)), ValueError,
     "labels: expected integer class ids"),
    (lambda a: a(torch.rand(2, 3, 8, 8), labels=torch.zeros(3, 8, 8).long()), ValueError,
     "labels: shape .* does not match image"),
    (lambda a: a(torch.rand(2, 3, 8, 8), depth=torch.rand(2, 2, 8, 8)), ValueError,
     "depth: expected floating planar depth"),
    (lambda a: a(torch.rand(2, 3, 8, 8), intrinsics=torch.ones(3)), ValueError,
     r"intrinsics: expected finite \(B=2, 4\)"),
    (lambda a: a({"rgb": torch.rand(1, 3, 8, 8), "mask": None}), ValueError, "unknown keys"),
    (lambda a: a(None), ValueError, "pass at least one"),
    (lambda a: ot.augment.RandomReproject(OUT)(torch.rand(1, 3, 8, 8)), ValueError,
     "intrinsics: pass the images' pinhole intrinsics"),
    (lambda a: ot.augment.RandomReproject(OUT, source_fov=4.0), ValueError, "source_fov"),
    (lambda a: ot.augment.RandomReproject(OUT, fisheye_models=("pinhole",)), ValueError,
     "fisheye_models"),
    (lambda a: ot.augment.RandomReproject(OUT, fov_range=(100 * DEG, 400 * DEG)), ValueError,
     "fov_range"),
    (lambda a: ot.augment.RandomReproject(OUT, interpolation="area"), ValueError,
     "interpolation"),
    (lambda a: ot.augment.RandomReproject(OUT, ds_alpha_range=(0.8, 0.2)), ValueError,
     "ds_alpha_range"),
])
def test_bad_input(call, error, match):
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=0)
    with pytest.raises(error, match=match):
        call(aug)


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float64])
def test_one_intrinsics_row_serves_a_batch(dtype):
    """A ``(4,)`` row of intrinsics (expanded over the batch, not copied) gives the images of
    the same row repeated ``(B, 4)``: the fused C++ call once refused the expanded row (its
    strides ``(0, 1)``) for float64 images with labels."""
    g = torch.Generator().manual_seed(5)
    rgb = torch.randint(0, 256, (3, 3, *SRC), generator=g, dtype=torch.uint8).to(dtype)
    labels = torch.randint(0, 19, (3, *SRC), generator=g, dtype=torch.uint8)
    k = torch.tensor([40.0, 40.0, (SRC[1] - 1) / 2, (SRC[0] - 1) / 2], dtype=torch.float64)
    module = augment.RandomReproject(OUT, seed=2)
    one = module({"rgb": rgb, "labels": labels, "intrinsics": k})
    rows = module({"rgb": rgb, "labels": labels, "intrinsics": k.repeat(3, 1)},
                  params=one["params"])
    assert one["valid"].any()
    for key in ("rgb", "labels", "valid"):
        assert torch.equal(one[key], rows[key]), key
