"""Detection targets through the augmentation: boxes, keypoints and instance maps (issue 35).

Oracles, independent of the box and keypoint code: the module's own rendering of the object
(a filled rectangle as a label map, nearest, the tight box of its output pixels taken here in
numpy), and of a marker (a small disc, one per image channel, bilinear: the intensity centroid
of its output). Sizes are small (64-96 px); the sweep over many boxes is in the slow tier.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.render import detection

DEG = math.pi / 180
#: Boxes: within a pixel of the tight box of their object's output pixels (the issue's bound).
BOX_PX = 1.0
#: Keypoints: within 0.75 px of their marker's output centroid (the issue's bound).
KEYPOINT_PX = 0.75


def tight_box(mask: torch.Tensor) -> np.ndarray | None:
    """XYXY corner box of the True pixels of ``mask (H, W)`` (numpy), None if none."""
    rows, cols = np.nonzero(mask.numpy())
    if len(rows) == 0:
        return None
    return np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=float)


def discs(size: tuple[int, int], centres: torch.Tensor, radius: float = 2.5) -> torch.Tensor:
    """``(K, H, W)``: channel k a disc of ``radius`` px around corner coordinates
    ``centres[k]``, anti-aliased by 4 x 4 supersampling."""
    h, w = size
    sub = (torch.arange(4, dtype=torch.float64) + 0.5) / 4
    y = (torch.arange(h, dtype=torch.float64)[:, None] + sub).reshape(-1)
    x = (torch.arange(w, dtype=torch.float64)[:, None] + sub).reshape(-1)
    inside = ((x[None, None, :] - centres[:, 0, None, None]) ** 2 +
              (y[None, :, None] - centres[:, 1, None, None]) ** 2) <= radius ** 2
    return inside.double().reshape(len(centres), h, 4, w, 4).mean((2, 4)).float()


def centroids(image: torch.Tensor) -> torch.Tensor:
    """``(K, 2)`` corner-coordinate intensity centroids of the channels of ``(K, H, W)``."""
    h, w = image.shape[-2:]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64),
                          torch.arange(w, dtype=torch.float64), indexing="ij")
    mass = image.double().sum((-2, -1))
    cu = (image.double() * u).sum((-2, -1)) / mass
    cv = (image.double() * v).sum((-2, -1)) / mass
    return torch.stack((cu, cv), -1) + 0.5


def whole_markers(image: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``(K,)`` True where channel k of ``image (K, H, W)`` shows a marker none of whose pixels
    touches an invalid pixel or the image's edge (``valid (1, H, W)``)."""
    invalid = torch.nn.functional.pad((~valid).float()[None], (1, 1, 1, 1), value=1.0)
    near = torch.nn.functional.max_pool2d(invalid, 3, stride=1)[0, 0] > 0
    return (image.sum((-2, -1)) > 0) & ~((image > 0) & near).any(-1).any(-1)


def random_boxes(n: int, size: tuple[int, int], gen: torch.Generator, low: float = 8,
                 high: float = 0.6) -> torch.Tensor:
    """``(n, 4)`` integer XYXY boxes within ``size``, sides at least ``low`` px."""
    h, w = size
    scale = torch.tensor([w, h], dtype=torch.float64)
    centre = torch.rand(n, 2, generator=gen, dtype=torch.float64) * scale
    half = (torch.rand(n, 2, generator=gen, dtype=torch.float64) * high * scale + low) / 2
    lo = (centre - half).round().clamp(min=0)
    hi = torch.minimum((centre + half).round(), scale)
    hi = torch.maximum(hi, lo + low).clamp(max=scale)
    lo = torch.minimum(lo, hi - low)
    return torch.cat((lo, hi), -1)


def rectangles(boxes: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``(N, H, W)`` int64 label maps, map j holding 1 on box j's pixels."""
    out = torch.zeros(len(boxes), *size, dtype=torch.int64)
    for j, (x0, y0, x1, y1) in enumerate(boxes.long().tolist()):
        out[j, y0:y1, x0:x1] = 1
    return out


def check_boxes_against_pixels(aug, source: dict, boxes: torch.Tensor, size) -> int:
    """Boxes of one image through ``aug`` against the tight boxes of their objects rendered
    (nearest) through the same draw; returns how many objects were compared."""
    out = aug({**source, "boxes": [boxes]})
    maps = rectangles(boxes, size)
    again = aug({"labels": maps}, params=_repeat(out["params"], len(boxes)),
                **({"intrinsics": source["intrinsics"]} if "intrinsics" in source else {}))
    compared = 0
    for j in range(len(boxes)):
        expected = tight_box(again["labels"][j] == 1)
        got = out["boxes"][0][out["box_index"][0] == j]
        if expected is None:   # nothing left: its box may be a sliver or dropped
            continue
        assert len(got) == 1, f"box {j}: object has pixels, box dropped"
        assert np.abs(got[0].double().numpy() - expected).max() <= BOX_PX, (j, got, expected)
        compared += 1
    return compared


def _repeat(params: dict, n: int) -> dict:
    """One sample's drawn parameters for ``n`` images."""
    return {key: (value * n if key == "model" else
                  value.expand(n, *value.shape[1:]) if isinstance(value, torch.Tensor)
                  else value) for key, value in params.items()}


@pytest.mark.parametrize("models, options", [
    (("equidistant", "kannala_brandt", "double_sphere"), {}),
    (("unified",), dict(unified_xi_range=(0.8, 1.0))),                 # catadioptric (Mei)
    (("equisolid",), dict(focal_scale_range=(1.4, 1.6), center_jitter=8.0)),   # cropped
])
def test_outline_boxes_match_their_objects_pixels(models, options):
    """Outline mode, perspective source: each box within a pixel of the tight box of its
    object's output pixels, for fisheye and catadioptric lenses, and for a cropped image
    circle (the image's edge cuts objects)."""
    size = (48, 64)
    aug = ot.augment.RandomReproject((64, 64), source_fov=100 * DEG, fisheye_models=models,
                                     interpolation="nearest", yaw_range=(-30 * DEG, 30 * DEG),
                                     seed=5, **options)
    gen = torch.Generator().manual_seed(1)
    compared = 0
    for _ in range(2):
        boxes = random_boxes(10, size, gen)
        compared += check_boxes_against_pixels(aug, {"rgb": torch.zeros(1, 1, *size)}, boxes,
                                               size)
    assert compared >= 15


def test_boxes_crossing_the_field_of_view_keep_their_valid_part():
    """A destination camera whose ``fov`` cone cuts through the objects (their interior
    reaches the cone): ``reproject_boxes`` gives the box of the part inside, within a pixel of
    the tight box of the pixels ``ot.reproject`` renders."""
    src = ot.Camera("pinhole", [20.0, 20.0, 31.5, 23.5], (48, 64))        # ~116 deg wide
    dst = ot.Camera("equidistant", [30.0, 30.0, 31.5, 31.5], (64, 64), fov=80 * DEG)
    gen = torch.Generator().manual_seed(2)
    boxes = random_boxes(12, (48, 64), gen, low=10, high=0.9)
    got, index = ot.render.detection.reproject_boxes([boxes], src, dst)
    maps = rectangles(boxes, (48, 64))
    labels, _ = ot.reproject(maps, src, dst, labels=True, ignore_index=0)
    cut = 0
    for j in range(len(boxes)):
        expected = tight_box(labels[j] == 1)
        if expected is None:   # nothing inside the cone (a sliver may keep a box)
            continue
        row = got[0][index[0] == j]
        assert len(row) == 1
        assert np.abs(row[0].numpy() - expected).max() <= BOX_PX, (j, row, expected)
        x0, y0, x1, y1 = boxes[j].tolist()
        corners = torch.tensor([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
        cut += int(not bool(detection.reproject_keypoints(corners, src, dst)[1].all()))
    assert cut >= 2   # the cone cut some objects (else the test shows nothing new)


@pytest.mark.parametrize("ops", [True, False])
def test_outline_boxes_at_the_valid_areas_border_under_strong_distortion(ops):
    """The outline's sampling (OUTLINE_STEP apart in the output) against the object's pixels
    where it is hardest: strongly distorting lenses (Kannala-Brandt, double sphere, unified)
    whose drawn cone (120-170 deg, about the 130 deg source's) and cropped image circle cut
    the objects, boxes reaching the source's edges turned towards the cone's edge; every
    box within a pixel of its object's tight pixel box, with the C++ ops (``ops``) and with
    their torch twins (``backend="torch"``)."""
    if ops and not ot.render.kernels.available():
        pytest.skip("the C++ ops cannot be built here")
    size = (48, 64)
    aug = ot.augment.RandomReproject(
        (64, 64), source_fov=130 * DEG, interpolation="nearest", seed=3,
        fisheye_models=("kannala_brandt", "double_sphere", "unified"),
        fov_range=(120 * DEG, 170 * DEG), focal_scale_range=(1.0, 1.4),
        yaw_range=(-35 * DEG, 35 * DEG), pitch_range=(-25 * DEG, 25 * DEG),
        backend="cpp" if ops else "torch")
    gen = torch.Generator().manual_seed(4)
    compared = cut = 0
    for _ in range(2):
        boxes = torch.cat((random_boxes(8, size, gen, low=6, high=0.9),
                           torch.tensor([[0.0, 0, 30, 48], [34, 0, 64, 20], [0, 30, 64, 48]])))
        corners = boxes[:, [0, 1, 2, 1, 2, 3, 0, 3]].reshape(1, -1, 2)   # each box's corners
        out = aug({"rgb": torch.zeros(1, 1, *size), "boxes": [boxes], "keypoints": corners})
        again = aug({"labels": rectangles(boxes, size)}, params=_repeat(out["params"],
                                                                          len(boxes)))
        outside = ~out["keypoints_valid"][0].reshape(-1, 4).all(-1)   # the outline leaves
        for j in range(len(boxes)):
            expected = tight_box(again["labels"][j] == 1)
            got = out["boxes"][0][out["box_index"][0] == j]
            if expected is None:
                continue
            assert len(got) == 1, f"box {j}: object has pixels, box dropped"
            assert np.abs(got[0].double().numpy() - expected).max() <= BOX_PX, (j, got,
                                                                               expected)
            compared += 1
            cut += int(outside[j])
    assert cut >= 4 and compared - cut >= 4


def test_instance_boxes_are_exact_and_carry_wide_ids():
    """Exact mode: the box of a box's instance's output pixels, ids beyond 2**31 carried
    exactly (nearest, never blended), 0 (the instances' ignore value) outside the valid area
    while the labels keep 255; a box whose instance leaves the image is dropped."""
    size = (48, 64)
    inst = torch.zeros(2, *size, dtype=torch.int64)
    big = 2 ** 40 + 7
    inst[:, 10:30, 12:40] = big
    inst[:, 0:4, 0:4] = 300
    aug = ot.augment.RandomReproject((64, 64), source_fov=90 * DEG, seed=3,
                                     focal_scale_range=(1.6, 1.6))
    out = aug({"labels": torch.full((2, *size), 4), "instances": inst,
               "boxes": [torch.tensor([[12.0, 10, 40, 30], [0, 0, 4, 4]])] * 2,
               "box_instance_ids": [torch.tensor([big, 300])] * 2})
    valid = out["valid"][:, 0]
    assert set(out["instances"][valid].unique().tolist()) <= {0, 300, big}
    assert bool((out["instances"][~valid] == 0).all())
    assert bool((out["labels"][~valid] == 255).all())
    for i in range(2):
        for box, j in zip(out["boxes"][i], out["box_index"][i].tolist()):
            expected = tight_box(out["instances"][i] == [big, 300][j])
            assert np.array_equal(box.numpy(), expected)
        kept = out["box_index"][i].tolist()
        assert (tight_box(out["instances"][i] == 300) is None) == (1 not in kept)


@pytest.mark.parametrize("models, options", [
    (("equidistant", "eucm"), {}),
    (("unified",), dict(unified_xi_range=(0.8, 1.0))),
])
def test_keypoints_land_on_their_markers(models, options):
    """Keypoints (perspective source) within 0.75 px of the output centroid of a disc drawn
    around each; a keypoint outside the source image or NaN is invalid and NaN."""
    size = (64, 80)
    gen = torch.Generator().manual_seed(4)
    kp = torch.rand(6, 2, generator=gen, dtype=torch.float64) * torch.tensor([60.0, 44.0]) + 10
    aug = ot.augment.RandomReproject((96, 96), source_fov=90 * DEG, fisheye_models=models,
                                     seed=6, focal_scale_range=(1.0, 1.0), **options)
    # (the whole source in view: the framing default may crop its rim, and keypoints there)
    image = discs(size, kp)[None]
    extra = torch.tensor([[-3.0, 5.0], [math.nan, math.nan]], dtype=torch.float64)
    for _ in range(2):
        out = aug({"rgb": image, "keypoints": torch.cat((kp, extra))[None].float()})
        valid = out["keypoints_valid"][0]
        assert valid[:6].all() and not valid[6:].any()
        assert bool(torch.isnan(out["keypoints"][0, 6:]).all())
        err = (out["keypoints"][0, :6].double() - centroids(out["rgb"][0])).norm(dim=-1)
        assert float(err.max()) <= KEYPOINT_PX, err
        # a half-pixel slip of the corner convention would move every keypoint ~0.5-0.7 px
        assert float(err.mean()) <= 0.35, err


@pytest.mark.parametrize("mode", ["fisheye", "catadioptric"])
def test_cubemap_keypoints_and_instance_boxes(mode):
    """Cubemap source: keypoints ``(face, x, y)`` within 0.75 px of their markers' output
    centroids (those the camera sees whole), invalid ones NaN; boxes from the cube's instance
    ids equal the tight boxes of the output instance pixels."""
    face = 48
    gen = torch.Generator().manual_seed(7)
    k = 12
    faces = torch.arange(k) % 6
    xy = torch.rand(k, 2, generator=gen, dtype=torch.float64) * (face - 16) + 8
    cube = torch.zeros(1, 6, k, face, face)
    disc = discs((face, face), xy)
    for j in range(k):
        cube[0, int(faces[j]), j] = disc[j]
    inst = torch.zeros(1, 6, face, face, dtype=torch.int32)
    inst[0, 0, 10:30, 5:20] = 70000
    inst[0, 5, 0:48, 0:48] = 2
    kp = torch.cat((faces[:, None].double(), xy), -1)[None]
    aug = ot.augment.RandomOmniCamera((96, 96), face, mode=mode, seed=8)
    out = aug({"rgb": cube, "instances": inst, "keypoints": kp,
               "box_instance_ids": [torch.tensor([70000, 2])]})
    whole = whole_markers(out["rgb"][0], out["valid"][0])
    valid = out["keypoints_valid"][0]
    assert int(whole.sum()) >= 3 and bool(valid[whole].all())   # seen whole: valid
    err = (out["keypoints"][0][whole].double() - centroids(out["rgb"][0][whole])).norm(dim=-1)
    assert float(err.max()) <= KEYPOINT_PX, err
    assert float(err.mean()) <= 0.35, err   # (a half-pixel slip: ~0.5-0.7 px)
    assert bool(torch.isnan(out["keypoints"][0][~valid]).all())
    for box, j in zip(out["boxes"][0], out["box_index"][0].tolist()):
        assert np.array_equal(box.numpy(), tight_box(out["instances"][0] == [70000, 2][j]))


def test_label_keys_carry_their_own_ignore_values():
    """Declared label keys and instances come back with their own ignore values outside the
    valid area, ids exact inside, as the labels would be."""
    aug = ot.augment.RandomReproject((40, 40), source_fov=90 * DEG, seed=0,
                                     label_keys={"parts": 99})
    ids = torch.randint(1, 2 ** 20, (2, 32, 40), generator=torch.Generator().manual_seed(0))
    out = aug({"labels": ids, "parts": ids.int(), "instances": ids})
    valid = out["valid"][:, 0]
    assert torch.equal(out["parts"][valid], out["labels"][valid])
    assert torch.equal(out["instances"][valid], out["labels"][valid])
    assert bool((out["parts"][~valid] == 99).all()) and bool((out["instances"][~valid] == 0).all())
    cube_aug = ot.augment.RandomOmniCamera((32, 32), 8, seed=0, label_keys={"parts": 7})
    cube_ids = torch.randint(1, 5, (1, 6, 8, 8), generator=torch.Generator().manual_seed(1))
    out = cube_aug({"parts": cube_ids})
    assert bool((out["parts"][~out["valid"][:, 0]] == 7).all())
    assert set(out["parts"][out["valid"][:, 0]].unique().tolist()) <= {1, 2, 3, 4}


def test_bad_detection_inputs_name_the_key_and_sample():
    aug = ot.augment.RandomReproject((32, 32), source_fov=90 * DEG, seed=0)
    rgb = torch.rand(2, 3, 24, 32)
    box = torch.tensor([[2.0, 2, 10, 10]])
    with pytest.raises(ValueError, match=r"boxes\[1\].*NaN"):
        aug({"rgb": rgb, "boxes": [box, torch.tensor([[math.nan, 0, 4, 4]])]})
    with pytest.raises(ValueError, match="boxes: 1 samples"):
        aug({"rgb": rgb, "boxes": [box]})
    with pytest.raises(ValueError, match="keypoints: 3 samples"):
        aug({"rgb": rgb, "keypoints": torch.zeros(3, 1, 2)})
    inst = torch.zeros(2, 24, 32, dtype=torch.int64)
    inst[:, 2:10, 2:10] = 5
    with pytest.raises(ValueError, match=r"box_instance_ids\[0\].*6.*no pixel"):
        aug({"rgb": rgb, "instances": inst, "box_instance_ids": [torch.tensor([6]),
                                                                  torch.tensor([5])]})
    with pytest.raises(ValueError, match=r"instances.*stacked masks.*amax"):
        aug({"rgb": rgb, "instances": torch.zeros(2, 3, 24, 32, dtype=torch.bool)})
    with pytest.raises(ValueError, match="cubemap has no 2D boxes"):
        ot.augment.RandomOmniCamera((16, 16), 8)({"rgb": torch.rand(1, 6, 3, 8, 8),
                                                   "boxes": [box]})
    with pytest.raises(ValueError, match="label_keys"):
        ot.augment.RandomReproject((32, 32), source_fov=1.0, label_keys={"boxes": 0})
    # a box outside the source image, or of no area: dropped, box_index says which stayed
    boxes = torch.tensor([[40.0, 2, 50, 10], [3, 3, 3, 9], [4, 4, 12, 12]])
    out = aug({"rgb": rgb, "boxes": [boxes, box]})
    assert out["box_index"][0].tolist() == [2] and len(out["boxes"][0]) == 1


@pytest.mark.slow
def test_outline_boxes_sweep():
    """The bound over many objects (sides of 8 px and more at the source) and draws: every
    box within a pixel of its object's tight pixel box (docs/detection.md quotes the worst)."""
    size = (96, 128)
    gen = torch.Generator().manual_seed(11)
    compared = 0
    for models, options in ((("equidistant", "kannala_brandt", "eucm", "double_sphere"), {}),
                            (("unified",), dict(unified_xi_range=(0.7, 1.0))),
                            (("equisolid",), dict(focal_scale_range=(1.3, 1.8),
                                                  center_jitter=10.0))):
        aug = ot.augment.RandomReproject((128, 128), source_fov=100 * DEG, seed=1,
                                         fisheye_models=models, interpolation="nearest",
                                         pitch_range=(-0.5, 0.5), yaw_range=(-0.5, 0.5),
                                         **options)
        for _ in range(5):
            compared += check_boxes_against_pixels(
                aug, {"rgb": torch.zeros(1, 1, *size)}, random_boxes(12, size, gen), size)
    assert compared >= 150


def test_the_box_kernels_and_their_twins_agree():
    """`kernels.boxes`: the C++ ops `box_pixels`, `outline_points` + `outline_reduce` against
    their torch twins on the same inputs (rays of a drawn camera, boxes through a change)."""
    if not ot.render.kernels.available():
        pytest.skip("the C++ ops cannot be built here")
    from omniscape_torch.render.kernels import boxes as kb
    g = torch.Generator().manual_seed(7)
    rays = torch.nn.functional.normalize(torch.randn(3, 20, 24, 3, generator=g, dtype=torch.float64)
                                         + torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64), dim=-1)
    rotation = ot.presets.yaw_pitch_roll_to_matrix(*(torch.rand(3, 3, generator=g,
                                                                dtype=torch.float64) - 0.5).T)
    k = torch.tensor([[18.0, 18.0, 11.5, 9.5]], dtype=torch.float64)
    valid = torch.rand(3, 20, 24, generator=g) > 0.1
    sample = torch.tensor([0, 1, 2, 2])
    windows = torch.tensor([[0, 0, 23, 19], [3, 2, 15, 12], [0, 5, 20, 19], [10, 10, 12, 12]])
    rects = torch.tensor([[2.0, 3.0, 9.0, 12.0], [0.0, 0.0, 23.0, 19.0], [5.0, 1.0, 15.0, 12.0],
                          [30.0, 30.0, 31.0, 31.0]], dtype=torch.float64)
    got = [kb.box_pixels(rays, rotation, k, valid, sample, windows, rects, backend=b)
           for b in ("cpp", "torch")]
    assert torch.equal(got[0], got[1]) and bool((got[0][:3] >= 0).all()) and bool(
        (got[0][3] == -1).all())
    src = ot.Camera("pinhole", [20.0, 20.0, 15.5, 11.5], (24, 32))
    dst = ot.presets.fisheye((40, 40))
    change, size = detection._change(src, dst, None, 1, None)
    boxes = torch.tensor([[2.0, 2.0, 20.0, 14.0], [10.0, 5.0, 30.0, 22.0]], dtype=torch.float64)
    outs = [detection.Outline(change, [boxes], size, backend=b).result() for b in
            ("cpp", "torch")]
    for a, b in zip(*outs):
        torch.testing.assert_close(a[0], b[0], atol=1e-9, rtol=0)
