"""Polygons through the augmentation, and the outline boxes' `box_visible` (issue 45, items 2-3).

Oracles, independent of the ring code: matplotlib's point-in-polygon (`Path.contains_points`)
for every rasterisation; the object's own pixels rendered through the module (a filled polygon
as a label map, nearest) for the boxes; and for the clipped rings, the output pixel centres whose
ray the cameras see and whose source point lies in the ring (`Change.backward`, the mapping
itself, point by point), and the box of many points of the ring's region mapped forward.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from test_detection import _repeat
from omniscape_torch.render import detection

Path = pytest.importorskip("matplotlib.path").Path

DEG = math.pi / 180
#: Boxes of rings against the continuous box of their region (many points mapped): the points'
#: spacing (0.1 source px) bounds the oracle's own error.
CONTINUOUS_PX = 0.1
#: Boxes of rings against the box of their object's output pixels: the half pixel between a
#: pixel's centre and its edge, and the half source pixel of the source's rasterisation.
PIXEL_PX = 1.0


def blob(rng: np.random.Generator, centre, size: float, n: int | None = None) -> np.ndarray:
    """A star-shaped ring (corner coordinates): ``n`` vertices about evenly spread, radii 0.8
    to 1 of ``size`` (no tip thinner than a pixel), or an ellipse where ``n`` is None."""
    if n is None:
        angle = np.linspace(0, 2 * math.pi, 24, endpoint=False)
        a, b, turn = size, size * rng.uniform(0.4, 1.0), rng.uniform(0, math.pi)
        x, y = a * np.cos(angle), b * np.sin(angle)
        x, y = x * math.cos(turn) - y * math.sin(turn), x * math.sin(turn) + y * math.cos(turn)
        return np.stack((centre[0] + x, centre[1] + y), -1)
    angle = (np.arange(n) + rng.uniform(-0.3, 0.3, n)) * 2 * math.pi / n
    radius = size * rng.uniform(0.8, 1.0, n)
    return np.stack((centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle)), -1)


def raster(rings, size: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` bool: pixel centres inside any of ``rings`` (each filled even-odd)."""
    h, w = size
    v, u = np.mgrid[0:h, 0:w]
    centres = np.stack((u.ravel() + 0.5, v.ravel() + 0.5), -1)
    out = np.zeros(h * w, dtype=bool)
    for ring in rings:
        out |= Path(np.asarray(ring, dtype=np.float64)).contains_points(centres)
    return out.reshape(h, w)


def tight_box(mask: np.ndarray) -> np.ndarray | None:
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return None
    return np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=float)


def region(ring: np.ndarray, change: detection.Change, size: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` bool: the output pixel centres both cameras see whose source point lies in
    ``ring``."""
    h, w = size
    v, u = np.mgrid[0:h, 0:w]
    centres = torch.from_numpy(np.stack((u.ravel(), v.ravel()), -1).astype(np.float64))
    source, seen = change.backward(centres, torch.zeros(len(centres), dtype=torch.long))
    inside = Path(ring).contains_points(source.numpy() + 0.5)
    return (seen.numpy() & inside).reshape(h, w)


def continuous_box(ring: np.ndarray, change: detection.Change, step: float = 0.1):
    """The box of the ring's region mapped forward: points every ``step`` source px inside it
    and every 0.01 px along its edges, those both cameras see."""
    lo, hi = ring.min(0), ring.max(0)
    x, y = np.meshgrid(np.arange(lo[0], hi[0], step), np.arange(lo[1], hi[1], step))
    grid = np.stack((x.ravel(), y.ravel()), -1)
    a, b = ring, np.roll(ring, -1, 0)
    edges = [a[k] + np.linspace(0, 1, int(np.linalg.norm(b[k] - a[k]) / 0.01) + 2)[:, None]
             * (b[k] - a[k]) for k in range(len(ring))]
    points = np.concatenate([grid[Path(ring).contains_points(grid)]] + edges)
    pixels, seen = change.forward(torch.from_numpy(points - 0.5),
                                  torch.zeros(len(points), dtype=torch.long))
    p = pixels[seen].numpy() + 0.5
    return None if len(p) == 0 else np.concatenate((p.min(0), p.max(0)))


SOURCE = ot.Camera("pinhole", [24.0, 24.0, 31.5, 23.5], (48, 64))             # ~106 deg wide
TURN = ot.presets.yaw_pitch_roll_to_matrix(torch.tensor(0.5), torch.tensor(0.3),
                                           torch.tensor(0.2)).double()
CASES = {   # output camera, rotation: each cuts the source's objects another way
    "field of view": (ot.Camera("equidistant", [30.0, 30.0, 31.5, 31.5], (64, 64),
                                fov=100 * DEG), None),
    "turned": (ot.Camera("kannala_brandt", [16.0, 16.0, 31.5, 31.5, 0.05, 0.01, 0, 0],
                         (64, 64), fov=190 * DEG), TURN),
    "blind cone": (ot.Camera("unified", [20.0, 20.0, 31.5, 31.5, 0.9, 0, 0, 0, 0], (64, 64),
                             blind_fov=50 * DEG), None),
    "cropped": (ot.Camera("equisolid", [40.0, 40.0, 35.5, 27.5], (64, 64)), None),
}


def _rings(seed: int, count: int = 10) -> list[np.ndarray]:
    """Blobs over (and past) the source image."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        centre = rng.uniform([-6, -6], [70, 54])
        out.append(blob(rng, centre, rng.uniform(4, 24), None if k % 3 == 0 else
                        int(rng.integers(6, 12))))
    return out


@pytest.mark.parametrize("case", sorted(CASES))
def test_rings_are_their_region_clipped_to_the_valid_area(case):
    """The output rings of each ring, filled, hold the output pixel centres both cameras see
    whose source point lies in the ring, all but a few within a pixel of the ring's mapped
    boundary; their box is that of the ring's region mapped point by point."""
    dst, rotation = CASES[case]
    rings = _rings(len(case))
    out, index = detection.reproject_polygons([[torch.from_numpy(r) for r in rings]], SOURCE,
                                              dst, rotation=rotation)
    change, _ = detection._change(SOURCE, dst, rotation, 1, None)
    compared = cut = 0
    for k, ring in enumerate(rings):
        mine = [r.numpy() for r, i in zip(out[0], index[0].tolist()) if i == k]
        truth = region(ring, change, dst.image_size)
        got = raster(mine, dst.image_size)
        wrong = truth ^ got
        assert wrong.sum() <= max(3, 0.02 * truth.sum()), (k, wrong.sum(), truth.sum())
        if wrong.any():   # a pixel centre on the region's boundary (chords, corners)
            rows, cols = np.nonzero(wrong)
            centres = np.stack((cols + 0.5, rows + 0.5), -1)
            edges = np.concatenate([np.stack((r, np.roll(r, -1, 0)), 1) for r in mine])
            a, d = edges[:, 0], edges[:, 1] - edges[:, 0]
            t = np.clip(((centres[:, None] - a) * d).sum(-1) / (d * d).sum(-1), 0, 1)
            near = np.linalg.norm(centres[:, None] - a - t[..., None] * d, axis=-1).min(1)
            assert near.max() <= 1.0, (k, near.max())
        box = continuous_box(ring, change)
        if box is None:
            assert not mine, k
            continue
        got_box = np.concatenate([np.concatenate(mine).min(0), np.concatenate(mine).max(0)])
        assert np.abs(got_box - box).max() <= CONTINUOUS_PX, (k, got_box, box)
        compared += 1
        cut += int(not bool(region(ring, change, dst.image_size).sum() ==
                            raster([ring], (48, 64)).sum()))
    assert compared >= 5 and cut >= 2


def test_a_ring_may_become_several_a_hole_or_none():
    """A U whose base the field of view cuts off: two rings; an object over the whole view of a
    catadioptric camera: the valid area, its blind cone a hole; one out of view: none; one
    around the whole view without a seen vertex: the valid area."""
    fish = ot.Camera("equidistant", [30.0, 30.0, 31.5, 31.5], (64, 64), fov=80 * DEG)
    # (the view: 20 source px around (31.5, 23.5); the base, y 0..2, lies past it)
    u_shape = np.array([[22.0, 0], [42, 0], [42, 30], [36, 30], [36, 2], [28, 2], [28, 30],
                        [22, 30]])
    rings, index = detection.reproject_polygons([[u_shape]], SOURCE, fish)
    assert index[0].tolist() == [0, 0]   # the arms, cut apart where the base leaves the view
    cata, _ = CASES["blind cone"]
    around = np.array([[-30.0, -30], [94, -30], [94, 78], [-30, 78]])
    inside = np.array([[30.0, 20], [34, 20], [34, 24], [30, 24]])   # behind the blind cone
    far = np.array([[200.0, 200], [210, 200], [205, 210]])
    rings, index = detection.reproject_polygons([[around, inside, far]], SOURCE, cata)
    assert 1 not in index[0].tolist() and 2 not in index[0].tolist()
    _, valid = ot.reproject(torch.zeros(1, 1, 48, 64), SOURCE, cata)
    whole = raster([r.numpy() for r in rings[0]], (64, 64))
    assert (whole ^ valid[0, 0].numpy()).sum() <= 4   # the view, less its blind cone
    change, _ = detection._change(SOURCE, cata, None, 1, None)
    hole = ~region(around, change, (64, 64)) & (np.hypot(*np.mgrid[-31.5:32.5, -31.5:32.5]) < 8)
    assert hole.sum() > 20 and not whole[hole].any()
    # around the whole view, no vertex seen: the valid area
    rings, index = detection.reproject_polygons([[around]], SOURCE, CASES["field of view"][0])
    _, valid = ot.reproject(torch.zeros(1, 1, 48, 64), SOURCE, CASES["field of view"][0])
    got = raster([r.numpy() for r in rings[0]], (64, 64))
    assert index[0].tolist() == [0] and (got ^ valid[0, 0].numpy()).sum() <= 4


@pytest.mark.parametrize("models, options", [
    (("equidistant", "kannala_brandt", "double_sphere"), {}),
    (("unified",), dict(unified_xi_range=(0.8, 1.0))),
    (("equisolid",), dict(focal_scale_range=(1.4, 1.6), center_jitter=8.0)),
])
def test_polygon_boxes_against_their_objects_pixels_and_the_exact_mode(models, options):
    """`RandomReproject` with polygons: each box the tight box of its object's mapped rings,
    within a pixel of the box of its object's output pixels (the polygon filled as a label map,
    rendered through the same draw, nearest; the exact mode's boxes on one instance map of
    them, the same call): at least as tight as the exact mode, within a pixel."""
    size = (64, 96)
    aug = ot.augment.RandomReproject((96, 96), source_fov=100 * DEG, fisheye_models=models,
                                     interpolation="nearest", yaw_range=(-30 * DEG, 30 * DEG),
                                     seed=4, **options)
    rng = np.random.default_rng(3)
    compared = 0
    for _ in range(2):
        rings = [blob(rng, ((c + 0.5) * 24 + rng.uniform(-3, 3), (r + 0.5) * 21 + rng.uniform(
            -3, 3)), rng.uniform(5, 10), None if (c + r) % 2 else 9)
            for r in range(3) for c in range(4)]   # one per cell: none overlap
        maps = np.stack([raster([ring], size) for ring in rings])
        keep = [k for k in range(len(rings)) if maps[k].any()]
        rings, maps = [rings[k] for k in keep], maps[keep]
        ids = torch.arange(1, len(rings) + 1)
        instances = torch.from_numpy((maps * ids.numpy()[:, None, None]).max(0))
        boxes = torch.stack([torch.from_numpy(tight_box(m)) for m in maps]).float()
        out = aug({"rgb": torch.zeros(1, 1, *size), "instances": instances[None], "boxes": [boxes],
                   "polygons": [[torch.from_numpy(r).float() for r in rings]]})
        exact = aug({"rgb": torch.zeros(1, 1, *size), "instances": instances[None],
                     "box_instance_ids": [ids]}, params=out["params"])
        again = aug({"labels": torch.from_numpy(maps.astype(np.int64))},
                    params=_repeat(out["params"], len(rings)))
        exact_boxes = dict(zip(exact["box_index"][0].tolist(), exact["boxes"][0].numpy()))
        assert bool(out["box_visible"][0].all())
        for k in range(len(rings)):
            pixels = tight_box(again["labels"][k].numpy() == 1)
            got = out["boxes"][0][out["box_index"][0] == k]
            if pixels is None or (again["labels"][k] == 1).sum() < 16:
                continue   # (a sliver: its rings may stand where no pixel centre is)
            assert len(got) == 1, f"object {k} has pixels, its box was dropped"
            got = got[0].double().numpy()
            assert np.abs(got - pixels).max() <= PIXEL_PX, (k, got, pixels)
            ex = exact_boxes[k]
            assert (got[:2] >= ex[:2] - 1).all() and (got[2:] <= ex[2:] + 1).all(), (got, ex)
            compared += 1
    assert compared >= 10


def test_polygon_box_owners_outline_boxes_and_the_exact_mode():
    """`polygon_box`: two rings of one box give one box (their union's), a box without rings
    keeps its outline box, a box whose rings all leave the view is dropped; `box_index` stays
    in the input's order; with `box_instance_ids` the boxes are the exact mode's and the
    polygons come out beside them."""
    aug = ot.augment.RandomReproject((64, 64), source_fov=90 * DEG, seed=0,
                                     focal_scale_range=(1.0, 1.0), pitch_range=(0, 0),
                                     yaw_range=(0, 0), roll_range=(0, 0))
    left = [[8.0, 8], [20, 8], [20, 20], [8, 20]]
    right = [[26.0, 8], [36, 8], [36, 20]]
    gone = [[-40.0, -40], [-30, -40], [-30, -30]]
    boxes = torch.tensor([[8.0, 8, 36, 20], [40, 30, 60, 44], [0, 0, 2, 2]])
    rgb = torch.zeros(1, 3, 48, 64)
    out = aug({"rgb": rgb, "boxes": [boxes], "polygons": [[left, right, gone]],
               "polygon_box": [torch.tensor([0, 0, 2])]})
    assert out["box_index"][0].tolist() == [0, 1]
    assert out["polygon_index"][0].tolist() == [0, 1]
    rings = out["polygons"][0]
    union = torch.cat(rings)
    torch.testing.assert_close(out["boxes"][0][0], torch.cat((union.amin(0), union.amax(0))))
    outline = aug({"rgb": rgb, "boxes": [boxes[1:2]]}, params=out["params"])
    torch.testing.assert_close(out["boxes"][0][1], outline["boxes"][0][0])
    # the exact mode, with polygons beside it
    inst = torch.zeros(1, 48, 64, dtype=torch.int64)
    inst[0, 8:20, 8:36] = 7
    exact = aug({"rgb": rgb, "instances": inst, "box_instance_ids": [torch.tensor([7])],
                 "boxes": [boxes[:1]], "polygons": [[left, right]],
                 "polygon_box": [torch.tensor([0, 0])]}, params=out["params"])
    rows, cols = torch.nonzero(exact["instances"][0] == 7, as_tuple=True)
    assert exact["boxes"][0][0].tolist() == [cols.min(), rows.min(), cols.max() + 1,
                                             rows.max() + 1]
    assert exact["polygon_index"][0].tolist() == [0, 1]
    for a, b in zip(exact["polygons"][0], rings):
        torch.testing.assert_close(a, b)


def test_coco_lists_unbatched_samples_and_dtypes():
    """COCO's flat lists give the rings their (N, 2) form gives; an unbatched sample comes back
    unbatched; rings come back in the input's floating dtype (float32 for lists)."""
    aug = ot.augment.RandomReproject((48, 48), source_fov=90 * DEG, seed=2)
    ring = torch.tensor([[10.0, 6], [30, 10], [26, 28], [8, 22]], dtype=torch.float64)
    rgb = torch.rand(3, 32, 40)
    as_pairs = aug({"rgb": rgb, "polygons": [ring]})
    as_coco = aug({"rgb": rgb, "polygons": [ring.reshape(-1).tolist()]}, params=as_pairs["params"])
    assert as_pairs["polygons"][0].dtype == torch.float64
    assert as_coco["polygons"][0].dtype == torch.float32
    torch.testing.assert_close(as_coco["polygons"][0], as_pairs["polygons"][0].float())
    assert as_pairs["polygon_index"].tolist() == [0]
    closed = aug({"rgb": rgb, "polygons": [torch.cat((ring, ring[:1]))]}, params=as_pairs["params"])
    torch.testing.assert_close(closed["polygons"][0], as_pairs["polygons"][0])


def test_bad_polygons_name_the_ring():
    aug = ot.augment.RandomReproject((32, 32), source_fov=90 * DEG, seed=0)
    rgb = torch.rand(2, 3, 24, 32)
    tri = [[1.0, 1], [5, 1], [3, 4]]
    for rings, match, err in (
            ([[tri], [tri, [[1.0, 1], [2, 2]]]], r"polygons\[1\]\[1\].*at least 3 points",
             ValueError),
            ([[tri], [[[1.0, math.nan], [2, 2], [3, 1]]]], r"polygons\[1\]\[0\].*finite",
             ValueError),
            ([[torch.zeros(4, 3)], [tri]], r"polygons\[0\]\[0\].*\(N, 2\)", ValueError),
            ([[[1.0, 2, 3, 4, 5]], [tri]], r"polygons\[0\]\[0\].*odd", ValueError),
            ([[tri], [["a", "b", "c"]]], r"polygons\[1\]\[0\]", TypeError),
            ([torch.zeros(3, 2), [tri]], r"polygons\[0\]: expected a list of rings", TypeError),
            ([[tri]], "polygons: 1 samples", ValueError)):
        with pytest.raises(err, match=match):
            aug({"rgb": rgb, "polygons": rings})
    box = torch.tensor([[0.0, 0, 8, 8]])
    with pytest.raises(ValueError, match=r"polygon_box\[1\]\[0\]: box 3 out of range.*0\.\.0"):
        aug({"rgb": rgb, "boxes": [box, box], "polygons": [[tri], [tri]],
             "polygon_box": [torch.tensor([0]), torch.tensor([3])]})
    with pytest.raises(ValueError, match=r"polygon_box\[0\].*2 rings and 1 boxes"):
        aug({"rgb": rgb, "boxes": [box, box], "polygons": [[tri, tri], [tri]]})
    with pytest.raises(ValueError, match="polygon_box: needs polygons"):
        aug({"rgb": rgb, "polygon_box": [torch.tensor([0]), torch.tensor([0])]})
    with pytest.raises(ValueError, match="polygons: a cubemap has no 2D"):
        ot.augment.RandomOmniCamera((16, 16), 8)({"rgb": torch.rand(1, 6, 3, 8, 8),
                                                   "polygons": [[tri]]})


def test_box_visible_flags_the_boxes_whose_object_may_be_out_of_view():
    """An outline box is flagged (False) where no side of it is seen whole: an L-shaped object
    along the far sides of a box whose near corner alone is in view is flagged and has no
    output pixel; a box seen whole is not. Over many objects from a catadioptric source, every
    outline box of an object with no output pixel is flagged."""
    src = ot.Camera("pinhole", [20.0, 20.0, 31.5, 23.5], (48, 64))
    dst = ot.Camera("equidistant", [30.0, 30.0, 31.5, 31.5], (64, 64), fov=70 * DEG)
    aug = ot.augment.RandomReproject((64, 64), source_camera=src, seed=0,
                                     focal_scale_range=(1.0, 1.0), roll_range=(0, 0),
                                     pitch_range=(0, 0), yaw_range=(0, 0))
    params = aug.forward_parameters(1)
    params["camera_params"][0, :4] = torch.tensor([30.0, 30.0, 31.5, 31.5], dtype=torch.float64)
    params["model"], params["fov"] = ("equidistant",), torch.tensor([70 * DEG],
                                                                    dtype=torch.float64)
    inst = torch.zeros(1, 48, 64, dtype=torch.int64)
    inst[0, 44:48, 40:64] = 1          # an L along the bottom and right sides of its box
    inst[0, 30:48, 60:64] = 1
    inst[0, 20:28, 28:36] = 2          # in the middle: seen whole
    boxes = torch.tensor([[40.0, 30, 64, 48], [28, 20, 36, 28]])
    out = aug({"rgb": torch.zeros(1, 1, 48, 64), "boxes": [boxes], "instances": inst},
              params=params)
    assert out["box_index"][0].tolist() == [0, 1]      # the L's box frames the seen corner
    assert out["box_visible"][0].tolist() == [False, True]
    assert not bool((out["instances"][0] == 1).any()) and bool((out["instances"][0] == 2).any())
    _, valid = ot.reproject(torch.zeros(1, 1, 48, 64), src, dst)
    assert bool(valid.any())
    # many objects from a catadioptric source: the hidden ones are all flagged
    cata = ot.Camera("unified", [16.0, 16.0, 31.5, 23.5, 0.9, 0, 0, 0, 0], (48, 64),
                     fov=200 * DEG, blind_fov=30 * DEG)
    aug = ot.augment.RandomReproject((64, 64), seed=3, interpolation="nearest",
                                     yaw_range=(-40 * DEG, 40 * DEG),
                                     pitch_range=(-40 * DEG, 40 * DEG))
    rng = np.random.default_rng(1)
    hidden = 0
    for _ in range(8):
        rings = [blob(rng, (16 * c + 8 + rng.uniform(-2, 2), 16 * r + 8 + rng.uniform(-2, 2)),
                      rng.uniform(3, 7), 8) for r in range(3) for c in range(4)]
        maps = np.stack([raster([ring], (48, 64)) for ring in rings])
        keep = [k for k in range(len(rings)) if maps[k].any()]
        ids = np.arange(1, len(keep) + 1)
        inst = torch.from_numpy((maps[keep] * ids[:, None, None]).max(0))[None]
        boxes = torch.stack([torch.from_numpy(tight_box(maps[k])) for k in keep]).float()
        out = aug({"rgb": torch.zeros(1, 1, 48, 64), "instances": inst, "boxes": [boxes]},
                  source_camera=cata)
        for j, seen in zip(out["box_index"][0].tolist(), out["box_visible"][0].tolist()):
            if not bool((out["instances"][0] == j + 1).any()):
                hidden += 1
                assert not seen, f"box {j}: its object has no output pixel, not flagged"
    assert hidden >= 2
