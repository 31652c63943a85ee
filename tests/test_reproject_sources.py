"""Issue 34, part 4: ``RandomReproject`` and ``ot.reproject`` from any source camera of the
registry (an Aria ``fisheye624`` calibration, a distorted OpenCV camera, a 3 x 3 K), and the five
models of other tools as reprojection targets."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import augment

DATA = Path(__file__).parent / "data" / "camera_files"
ARIA = DATA / "aria" / "DeviceModelTests-calib.json"
OPENCV = DATA / "opencv" / "left_intrinsics.yml"
#: Where the centroid of a reprojected dot may lie from the projection of its ray (the issue's
#: bound; the warp of a 1-pixel Gaussian moves its centroid by far less).
DOT_TOL_PX = 0.5

# Per-model parameters of cameras of 480 x 640 pixels (tests/conftest.py's first cases).
FIVE = {
    "fov": [500.0, 505.0, 319.5, 239.5, 0.9],
    "division": [400.0, 402.0, 320.0, 240.0, -0.3],
    "opencv": [500.0, 502.0, 320.3, 239.7, -0.28, 0.07, 1e-3, -5e-4, 0.0, 0.0, 0.0, 0.0, 0.0,
               0.0, 0.0, 0.0],
    "thin_prism_fisheye": [285.0, 286.0, 319.5, 239.5, -0.0134, 0.0513, 1e-3, -2e-3, -0.0437,
                           0.0089, 5e-4, -3e-4],
    "fisheye624": [240.0, 241.0, 320.2, 239.6, -0.02, 0.003, -2e-4, 1e-5, 0.0, 0.0, 4e-4, -3e-4,
                   2e-4, 1e-5, -3e-4, 2e-5],
}


def scaled(camera: ot.Camera, s: float) -> ot.Camera:
    """``camera`` for its image resized by ``s`` (``round(s H) x round(s W)``): the pixel edges
    scale, so ``fx' = s fx``, ``cx' = s (cx + 0.5) - 0.5`` (pixel centres at integers); the
    distortion coefficients of these models act on normalised coordinates and stay."""
    p = camera.params.clone()
    p[..., :2] = s * p[..., :2]
    p[..., 2:4] = s * (p[..., 2:4] + 0.5) - 0.5
    h, w = camera.image_size
    return ot.Camera(camera.model, p, (round(s * h), round(s * w)), fov=camera.fov,
                     blind_fov=camera.blind_fov)


@pytest.fixture(scope="module")
def aria():
    return ot.Camera.load(ARIA)


@pytest.fixture(scope="module")
def opencv():
    return ot.Camera.load(OPENCV)


@pytest.mark.parametrize("path", [ARIA, OPENCV], ids=["aria", "opencv"])
def test_scaled_camera_moves_pixel_edges(path):
    """The scaled camera sees a point where the resized image shows it: ``u' + 0.5 = s (u +
    0.5)``, for directions across the field (so the distortion terms take part)."""
    cam = ot.Camera.load(path)
    assert cam.image_size == (480, 640)           # as written in the file
    small = scaled(cam, 1 / 8)
    assert small.image_size == (60, 80)
    g = torch.linspace(-0.8, 0.8, 9, dtype=torch.float64)
    pts = torch.stack(torch.broadcast_tensors(g[:, None], g[None, :], torch.ones(1, 1,
                      dtype=torch.float64)), -1).reshape(-1, 3)
    full, ok = cam.model.project(pts, cam.params)
    part, ok_small = small.model.project(pts, small.params)
    assert bool(ok.all()) and torch.equal(ok, ok_small)
    torch.testing.assert_close(part + 0.5, (full + 0.5) / 8, rtol=0, atol=1e-9)


def _target(aug: augment.RandomReproject, params: dict, i: int) -> ot.Camera:
    """The drawn camera of sample ``i`` with its drawn field of view (float64)."""
    p = int(params["num_params"][i])
    return ot.Camera(params["model"][i], params["camera_params"][i, :p], aug.image_size,
                     fov=float(params["fov"][i]))


def _independent_valid(aug, params, source: ot.Camera) -> torch.Tensor:
    """Per sample: the drawn camera's ray grid (its domain, image and field of view), rotated
    into the source frame, projected by the source model's ``project``, inside its image."""
    out = []
    for i in range(len(params["model"])):
        rays, ok = _target(aug, params, i).ray_grid()
        src = rays @ params["rotation"][i].T
        cam = source if not source.batch_shape else ot.Camera(
            source.model, source.params[i], source.image_size)
        px, seen = cam.model.project(src, cam.params.to(torch.float64))
        h, w = cam.image_size
        inside = (px[..., 0] >= -0.5) & (px[..., 0] <= w - 0.5) & (px[..., 1] >= -0.5) & \
            (px[..., 1] <= h - 0.5)
        out.append(ok & seen & inside)
    return torch.stack(out).unsqueeze(1)


@pytest.mark.parametrize("which", ["aria", "opencv"])
def test_valid_mask_is_the_source_model_projection(which, aria, opencv):
    """``valid`` is where the source model sees: the drawn camera's rays projected by the source
    (fisheye624 from the Aria file, OpenCV's full distortion) into its image."""
    cam = scaled(aria if which == "aria" else opencv, 1 / 8)
    # point samples: the fast and exact paths' prefilters differ (each tested against its rule
    # in test_mip_image.py and test_antialias.py)
    aug = augment.RandomReproject((48, 48), source_camera=cam, seed=3, antialias=False)
    image = torch.rand(3, 3, *cam.image_size)
    labels = torch.randint(0, 2, (3, *cam.image_size)) * 100    # blended ids would lie between
    out = aug({"rgb": image, "labels": labels})
    expected = _independent_valid(aug, out["params"], cam)
    assert expected.any() and (~expected).any()
    assert torch.equal(out["valid"], expected)
    assert bool((out["rgb"] * ~out["valid"] == 0).all())
    assert bool((out["labels"][~out["valid"][:, 0]] == 255).all())
    inside = out["labels"][out["valid"][:, 0]]
    assert set(inside.unique().tolist()) == {0, 100}
    # antialiased (the default): the same valid mask and labels, RGB in the image's range
    smooth = augment.RandomReproject((48, 48), source_camera=cam, seed=3)(
        {"rgb": image, "labels": labels}, params=out["params"])
    assert torch.equal(smooth["valid"], out["valid"])
    assert torch.equal(smooth["labels"], out["labels"])
    assert 0 <= float(smooth["rgb"].min()) and float(smooth["rgb"].max()) <= 1
    # the exact chain (a gradient asked for) agrees with the fast one
    with torch.enable_grad():
        leaf = image.clone().requires_grad_()
        exact = aug.render(leaf, out["params"], labels=torch.randint(0, 13, (3, *cam.image_size)),
                           source_camera=cam)
        exact["rgb"].sum().backward()
    assert torch.equal(exact["valid"], out["valid"]) and leaf.grad.abs().sum() > 0
    # (the fast path's rays from tables good to 0.01 px, on noise of slope <= 1 a pixel)
    torch.testing.assert_close(exact["rgb"].detach(), out["rgb"], rtol=0, atol=1e-2)


def _dot_image(size, centre, sigma=1.0):
    h, w = size
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64),
                          torch.arange(w, dtype=torch.float64), indexing="ij")
    d2 = (u - centre[0]) ** 2 + (v - centre[1]) ** 2
    return torch.exp(-d2 / (2 * sigma ** 2))


@pytest.mark.parametrize("which", ["aria", "opencv"])
def test_a_dot_lands_where_its_ray_projects(which, aria, opencv):
    """A small bright dot at a source pixel: its centroid in the output lies where the drawn
    camera projects that pixel's ray (through the attitude), within ``DOT_TOL_PX``."""
    cam = scaled(aria if which == "aria" else opencv, 1 / 4)     # 120 x 160
    aug = augment.RandomReproject((96, 96), source_camera=cam, fov_range=(
        math.radians(100), math.radians(120)), seed=1)
    params = aug.forward_parameters(1)
    h, w = cam.image_size
    checked = 0
    for at in ((0.45 * w, 0.55 * h), (0.6 * w, 0.4 * h)):
        pixel = torch.tensor(at, dtype=torch.float64)
        ray, ok = cam.unproject(pixel)
        assert bool(ok)
        target = _target(aug, params, 0)
        expect, seen = target.project(params["rotation"][0].T @ ray)
        assert bool(seen)
        image = _dot_image((h, w), pixel).expand(1, 1, h, w).to(torch.float64)
        out = aug.render(image, params, source_camera=cam)
        weight = out["rgb"][0, 0]
        v, u = torch.meshgrid(torch.arange(96.0, dtype=torch.float64),
                              torch.arange(96.0, dtype=torch.float64), indexing="ij")
        near = ((u - expect[0]) ** 2 + (v - expect[1]) ** 2) < 8 ** 2
        weight = torch.where(near, weight, torch.zeros_like(weight))
        centroid = torch.stack(((weight * u).sum(), (weight * v).sum())) / weight.sum()
        assert float((centroid - expect).norm()) < DOT_TOL_PX, (centroid, expect)
        checked += 1
    assert checked == 2


def test_a_3x3_K_is_the_4_intrinsics_bit_for_bit():
    """``K (B, 3, 3)``, ``K (3, 3)`` and a pinhole ``source_camera`` render exactly what
    ``intrinsics (B, 4)`` renders (the fast op's own pinhole)."""
    aug = augment.RandomReproject((40, 40), seed=0)
    image = (torch.rand(2, 3, 30, 40) * 255).to(torch.uint8)
    labels = torch.randint(0, 13, (2, 30, 40))
    k4 = torch.tensor([[30.0, 31.0, 19.5, 14.5], [28.0, 28.5, 20.0, 15.0]], dtype=torch.float64)
    K = torch.zeros(2, 3, 3, dtype=torch.float64)
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = *k4.T, 1.0
    params = aug.forward_parameters(2)
    ref = aug.render(image, params, labels=labels, intrinsics=k4)
    for out in (aug.render(image, params, labels=labels, intrinsics=K),
                aug.render(image, params, labels=labels,
                           source_camera=ot.Camera("pinhole", k4, (30, 40)))):
        for key in ("rgb", "labels", "valid"):
            assert torch.equal(out[key], ref[key]), key
        assert torch.equal(out["params"]["intrinsics"], k4)
    one = aug.render(image, params, labels=labels, intrinsics=K[0].float())
    assert torch.equal(one["rgb"], aug.render(image, params, labels=labels,
                                              intrinsics=k4[0].float())["rgb"])


def test_source_camera_at_construction_per_call_batched_and_replayed(aria):
    """One camera at construction, the same per call, a batch (B,) of equal rows: the same
    output; a batch of different rows renders each sample with its own; a replay of the
    output's params (``source_camera`` recorded) renders the same."""
    cam = scaled(aria, 1 / 8)
    image = torch.rand(2, 3, *cam.image_size)
    shared = augment.RandomReproject((32, 32), source_camera=cam, seed=0)
    plain = augment.RandomReproject((32, 32), seed=0)
    a = shared(image)
    b = plain(image, source_camera=cam)
    batch = ot.Camera(cam.model, cam.params.expand(2, -1), cam.image_size)
    c = plain.render(image, a["params"], source_camera=batch)
    d = plain(image, params=a["params"])
    e = plain({"rgb": image, "source_camera": cam}, params=a["params"])
    for out in (b, c, d, e):
        assert torch.equal(out["rgb"], a["rgb"]) and torch.equal(out["valid"], a["valid"])
    assert a["params"]["source_camera"]["model"] == "fisheye624"
    assert a["params"]["source_camera"]["params"].shape == (2, 16)
    # different rows: sample 1 as if rendered alone with its camera
    other = cam.params.clone()
    other[2] += 3.0
    two = ot.Camera(cam.model, torch.stack((cam.params, other)), cam.image_size)
    mixed = plain.render(image, a["params"], source_camera=two)
    one = {k: (v[1:] if not isinstance(v, tuple) else v[1:]) for k, v in a["params"].items()
           if k != "source_camera"}
    alone = plain.render(image[1:], one, source_camera=ot.Camera(cam.model, other,
                                                                  cam.image_size))
    assert torch.equal(mixed["rgb"][1:], alone["rgb"])
    assert torch.equal(mixed["rgb"][:1], a["rgb"][:1])


def test_depth_from_a_fisheye_source_is_zero_past_90_degrees():
    """Planar depth has no meaning for source rays at or past 90 degrees (a fisheye sees
    them): 0 there, the range ``z / cos`` elsewhere."""
    wide = torch.tensor(FIVE["fisheye624"], dtype=torch.float64)
    wide[:2] = 100.0                                  # 90 degrees at 157 px: inside the image
    cam = scaled(ot.Camera("fisheye624", wide, (480, 640)), 1 / 8)
    aug = augment.RandomReproject((32, 32), source_camera=cam, seed=0, yaw_range=(1.4, 1.4),
                                  fov_range=(math.radians(200), math.radians(200)))
    out = aug(None, depth=torch.full((1, *cam.image_size), 2.0, dtype=torch.float64))
    rays, _ = _target(aug, out["params"], 0).ray_grid()
    cos = (rays @ out["params"]["rotation"][0].T)[..., 2]
    valid = out["valid"][0, 0]
    behind, ahead = valid & (cos <= 0), valid & (cos > 0.05)
    assert behind.any() and ahead.any()
    assert bool((out["depth"][0, 0][behind] == 0).all())
    torch.testing.assert_close(out["depth"][0, 0][ahead], 2.0 / cos[ahead], rtol=1e-6, atol=0)


@pytest.mark.parametrize("model", sorted(FIVE))
def test_the_five_models_as_reprojection_targets(model):
    """``ot.reproject`` from a full panorama into each of the five models: every pixel the
    target sees is valid, and a smooth panorama's value is that of the pixel's ray."""
    dst = scaled(ot.Camera(model, torch.tensor(FIVE[model], dtype=torch.float64), (480, 640)),
                 1 / 16)                                                    # 30 x 40
    pano_cam = ot.equirectangular_camera(256, 128, dtype=torch.float64)
    rays = pano_cam.ray_grid()[0]
    pano = (rays.permute(2, 0, 1).unsqueeze(0) + 1) / 2        # the ray itself, smooth
    out, valid = ot.reproject(pano, pano_cam, dst)
    rays_dst, ok = dst.ray_grid()
    assert torch.equal(valid[0, 0], ok) and bool(ok.any())
    expect = ((rays_dst.permute(2, 0, 1) + 1) / 2)[:, ok]
    torch.testing.assert_close(out[0][:, ok], expect, rtol=0, atol=0.02)


def test_reproject_takes_a_K_and_any_source(opencv):
    """``ot.reproject(image, K, dst)`` is the pinhole of ``K``; a skewed K is refused naming
    ``src_camera``."""
    image = torch.rand(1, 3, 30, 40, dtype=torch.float64)
    K = torch.tensor([[30.0, 0.0, 19.5], [0.0, 31.0, 14.5], [0.0, 0.0, 1.0]],
                     dtype=torch.float64)
    dst = ot.Camera("equidistant", [12.0, 12.0, 15.5, 15.5], (32, 32))
    a = ot.reproject(image, K, dst)
    b = ot.reproject(image, ot.Camera("pinhole", torch.tensor([30.0, 31.0, 19.5, 14.5],
                                                              dtype=torch.float64), (30, 40)), dst)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    with pytest.raises(ValueError, match=r"src_camera: K has skew K\[0, 1\] = 0.5"):
        ot.reproject(image, K + torch.tensor([[0.0, 0.5, 0.0], [0, 0, 0], [0, 0, 0]],
                                             dtype=torch.float64), dst)


def _skewed():
    K = torch.tensor([[30.0, 0.25, 19.5], [0.0, 31.0, 14.5], [0.0, 0.0, 1.0]])
    return K


def _last_row():
    K = _skewed()
    K[0, 1] = 0.0
    K[2] = torch.tensor([0.0, 0.1, 1.0])
    return K


@pytest.mark.parametrize("call, error, match", [
    (lambda a, c: a(torch.rand(2, 3, 30, 40), intrinsics=_skewed()), ValueError,
     r"intrinsics: K has skew K\[0, 1\] = 0.25"),
    (lambda a, c: a(torch.rand(2, 3, 30, 40), intrinsics=_last_row()), ValueError,
     r"intrinsics: the last row of K must be \[0, 0, 1\]"),
    (lambda a, c: a(torch.rand(2, 3, 30, 40), intrinsics=_last_row()[None].expand(3, 3, 3)),
     ValueError, r"intrinsics: a batch of 3 camera matrices K for 2 images"),
    (lambda a, c: a(torch.rand(2, 3, 30, 40), intrinsics=torch.eye(4)), ValueError,
     r"intrinsics: expected finite \(B=2, 4\)"),
    (lambda a, c: a(torch.rand(2, 3, 60, 80), source_camera=ot.Camera(
        c.model, c.params.expand(3, -1), c.image_size)), ValueError,
     r"source_camera: expected one camera or a batch of 2 \(the images' batch\), got a batch "
     r"\(3,\)"),
    (lambda a, c: a(torch.rand(2, 3, 30, 40), source_camera=c), ValueError,
     r"source_camera: image_size \(60, 80\) does not match the images' \(30, 40\)"),
    (lambda a, c: a(torch.rand(2, 3, 60, 80), source_camera=c, intrinsics=torch.ones(4)),
     ValueError, "source_camera: pass intrinsics or source_camera, not both"),
    (lambda a, c: a(torch.rand(2, 3, 60, 80), source_camera=[c, c]), TypeError,
     "source_camera: expected one ot.Camera"),
    (lambda a, c: a(torch.rand(2, 3, 60, 80), intrinsics=c), TypeError,
     "intrinsics: got an ot.Camera; pass it as source_camera"),
    (lambda a, c: augment.RandomReproject((8, 8), source_camera=ot.Camera(
        c.model, c.params.expand(2, -1), c.image_size)), ValueError,
     r"source_camera: at construction one camera"),
    (lambda a, c: augment.RandomReproject((8, 8), source_camera=c, source_fov=1.0), ValueError,
     "source_camera: pass source_fov or source_camera, not both"),
])
def test_bad_source(call, error, match, aria):
    aug = augment.RandomReproject((16, 16), seed=0)
    with pytest.raises(error, match=match):
        call(aug, scaled(aria, 1 / 8))


def test_a_module_with_a_source_camera_pickles(aria):
    """DataLoader workers get the module pickled: its source camera travels with it; a module
    pickled before ``source_camera`` existed loads with None."""
    import pickle
    cam = scaled(aria, 1 / 8)
    aug = augment.RandomReproject((16, 16), source_camera=cam, seed=0)
    copy = pickle.loads(pickle.dumps(aug))
    image = torch.rand(1, 3, *cam.image_size)
    assert torch.equal(copy(image)["rgb"], aug(image)["rgb"])
    state = augment.RandomReproject((16, 16), source_fov=1.5, seed=0).__getstate__()
    state.pop("source_camera")
    old = augment.RandomReproject.__new__(augment.RandomReproject)
    old.__setstate__(state)
    assert old.source_camera is None and old(torch.rand(1, 3, 8, 8))["valid"].any()


def test_reproject_refuses_a_source_batch_of_another_size(aria):
    cam = scaled(aria, 1 / 8)
    three = ot.Camera(cam.model, cam.params.expand(3, -1), cam.image_size)
    dst = ot.Camera("equidistant", torch.tensor([[8.0, 8.0, 7.5, 7.5]] * 2), (16, 16))
    with pytest.raises(ValueError, match="batch sizes disagree: src_camera 3, image 2"):
        ot.reproject(torch.rand(2, 3, *cam.image_size), three, dst)
    with pytest.raises(ValueError, match="batch sizes disagree: src_camera 3, dst_camera 2"):
        ot.reproject(torch.rand(1, 3, *cam.image_size), three, dst)
    out, valid = ot.reproject(torch.rand(1, 3, *cam.image_size), three,
                              ot.Camera("equidistant", [8.0, 8.0, 7.5, 7.5], (16, 16)))
    assert out.shape == (3, 3, 16, 16) and valid.any()


def test_a_source_fov_limits_valid(aria):
    """A source camera's ``fov`` is part of its validity: the output is valid only where the
    ray lies within it."""
    cam = scaled(aria, 1 / 8)
    narrow = ot.Camera(cam.model, cam.params, cam.image_size, fov=math.radians(90))
    aug = augment.RandomReproject((32, 32), seed=2)
    image = torch.rand(2, 3, *cam.image_size)
    params = aug.forward_parameters(2)
    wide = aug.render(image, params, source_camera=cam)["valid"]
    out = aug.render(image, params, source_camera=narrow)["valid"]
    assert bool((out <= wide).all()) and int(out.sum()) < int(wide.sum())
    for i in range(2):
        rays, _ = _target(aug, params, i).ray_grid()
        src = rays @ params["rotation"][i].T
        assert bool((torch.atan2(src[..., :2].norm(dim=-1), src[..., 2])[out[i, 0]]
                     <= math.radians(45) + 1e-6).all())


def test_per_sample_outputs_with_a_camera_source_collate_and_replay(aria):
    """As a Dataset's __getitem__ applies the module: per-sample outputs (params included)
    go through DataLoader's default_collate, and the collated params replay the batch."""
    from torch.utils.data import default_collate

    cam = scaled(aria, 1 / 8)
    aug = augment.RandomReproject((24, 24), source_camera=cam, seed=1)
    images = torch.rand(3, 3, *cam.image_size)
    outs = [aug(images[i:i + 1]) for i in range(3)]
    params = default_collate([o["params"] for o in outs])
    record = params["source_camera"]
    assert record["model"] == ["fisheye624"] * 3 and record["params"].shape == (3, 1, 16)
    flat = {k: (v.flatten(0, 1) if isinstance(v, torch.Tensor) else
                tuple(m for row in zip(*v) for m in row) if k == "model" else v)
            for k, v in params.items() if k != "source_camera"}
    again = augment.RandomReproject((24, 24), seed=9).render(images, flat,
                                                             source_camera=record)
    assert torch.equal(again["rgb"], torch.cat([o["rgb"] for o in outs]))
    mixed = dict(record, model=["fisheye624", "opencv", "fisheye624"])
    with pytest.raises(ValueError, match="the samples differ"):
        augment.RandomReproject((24, 24), seed=9).render(images, flat, source_camera=mixed)
