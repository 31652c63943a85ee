"""The containers around the augmentation modules (``augment/containers.py``,
``augment/adapters.py``): unbatched samples, torchvision's ``tv_tensors`` and ``transforms.v2``,
kornia's ``AugmentationSequential``, and the albumentations adapter.

torchvision and albumentations are optional: their tests skip where they do not import (the
PyPI torchvision beside this project's CPU torch raises a RuntimeError at import; albumentations
is no dev dependency). How they were run: docs/augmentation.md, "Containers".
"""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
import torch
from torch.utils.data import default_collate

import omniscape_torch as ot
from omniscape_torch.augment import containers

SRC = (24, 28)
OUT = (32, 32)
DEG = math.pi / 180


def _torchvision():
    """``(tv_tensors, transforms.v2)``, or skip where torchvision does not import (an
    ImportError, or the RuntimeError / OSError of wheels built for another torch)."""
    try:
        from torchvision import tv_tensors
        from torchvision.transforms import v2
    except (ImportError, RuntimeError, OSError) as err:
        pytest.skip(f"torchvision does not import here: {type(err).__name__}: {err}")
    return tv_tensors, v2


def _albumentations():
    try:
        import albumentations
    except (ImportError, RuntimeError, OSError) as err:
        pytest.skip(f"albumentations does not import here: {type(err).__name__}: {err}")
    return albumentations


def _accepts_boxes() -> bool:
    """Whether the modules take the detection keys yet (boxes, keypoints)."""
    aug = ot.augment.RandomReproject((8, 8), source_fov=90 * DEG, seed=0)
    try:
        aug({"rgb": torch.rand(1, 3, 8, 8), "boxes": [torch.tensor([[1.0, 1.0, 4.0, 4.0]])]})
    except ValueError as err:
        if "unknown keys" in str(err):
            return False
        raise
    return True


needs_boxes = pytest.mark.skipif(not _accepts_boxes(), reason="the modules take no boxes yet")


def _sample(gen: torch.Generator, batch: tuple[int, ...] = ()) -> dict:
    return {"rgb": torch.rand(*batch, 3, *SRC, generator=gen),
            "labels": torch.randint(0, 13, (*batch, *SRC), generator=gen),
            "depth": 1 + torch.rand(*batch, *SRC, generator=gen)}


def _plain(value):
    return value.as_subclass(torch.Tensor) if isinstance(value, torch.Tensor) else value


# ---------------------------------------------------------------------------------------------
# Unbatched samples
# ---------------------------------------------------------------------------------------------
def test_unbatched_samples_collate_into_the_batch():
    """Per-sample calls on what a Dataset holds ((C, H, W), (H, W)) return unbatched outputs
    and per-sample params; ``default_collate`` of those is the batch's: it replays the stacked
    samples in one batched call to the same pixels."""
    gen = torch.Generator().manual_seed(1)
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=2,
                                     fisheye_models=("equidistant", "kannala_brandt"))
    samples = [_sample(gen) for _ in range(2)]
    with torch.no_grad():
        outs = [aug(s) for s in samples]
        batch = aug(default_collate(samples), params=default_collate([o["params"] for o in outs]))
    for b, out in enumerate(outs):
        assert out["rgb"].shape == (3, *OUT) and out["labels"].shape == OUT
        assert out["depth"].shape == (1, *OUT) and out["valid"].shape == (1, *OUT)
        assert isinstance(out["params"]["model"], str) and out["params"]["rotation"].shape == (3, 3)
        for key in ("rgb", "labels", "depth", "valid"):
            assert torch.equal(out[key], batch[key][b])
        assert bool(out["valid"].any()) and not bool(out["valid"].all())
    again = aug(samples[0], params=outs[0]["params"])   # per-sample params replay
    assert torch.equal(again["rgb"], outs[0]["rgb"])


def test_unbatched_cubes():
    gen = torch.Generator().manual_seed(3)
    cube = torch.rand(6, 3, 8, 8, generator=gen)
    ids = torch.randint(0, 13, (6, 8, 8), generator=gen)
    omni = ot.augment.RandomOmniCamera((16, 16), 8, seed=0)
    with torch.no_grad():
        out = omni({"rgb": cube, "labels": ids})
        batched = omni({"rgb": cube[None], "labels": ids[None]},
                       params=default_collate([out["params"]]))
    assert out["rgb"].shape == (3, 16, 16) and out["labels"].shape == (16, 16)
    assert torch.equal(out["rgb"], batched["rgb"][0])
    assert torch.equal(out["labels"], batched["labels"][0])


@needs_boxes
def test_unbatched_detection_keys():
    """One sample's boxes ``(N, 4)`` and keypoints ``(K, 2)`` come back unbatched: what the
    batch of one gives, without its list and batch dimension."""
    gen = torch.Generator().manual_seed(8)
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=9,
                                     fov_range=(100 * DEG, 120 * DEG))
    rgb = torch.rand(3, *SRC, generator=gen)
    boxes = torch.tensor([[8.0, 6.0, 20.0, 18.0], [2.0, 2.0, 6.0, 5.0]])
    points = torch.tensor([[14.0, 12.0], [1.0, 1.0]])
    with torch.no_grad():
        one = aug({"rgb": rgb, "boxes": boxes, "keypoints": points})
        batch = aug({"rgb": rgb[None], "boxes": [boxes], "keypoints": points[None]},
                    params=default_collate([one["params"]]))
    assert one["boxes"].dim() == 2 and one["box_index"].dim() == 1
    assert one["keypoints"].shape == (2, 2) and one["keypoints_valid"].shape == (2,)
    assert torch.equal(one["boxes"], batch["boxes"][0])
    assert torch.equal(one["box_index"], batch["box_index"][0])
    assert torch.equal(one["keypoints_valid"], batch["keypoints_valid"][0])
    torch.testing.assert_close(one["keypoints"], batch["keypoints"][0], equal_nan=True)


# ---------------------------------------------------------------------------------------------
# kornia
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("data_keys", [None, ["input", "mask"]])
def test_kornia_container_is_refused(data_keys):
    """kornia's AugmentationSequential calls an unknown module with the image alone and passes
    the mask on untransformed: a TypeError says how to compose instead."""
    K = pytest.importorskip("kornia.augmentation")
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=0)
    image, mask = torch.rand(2, 3, *SRC), torch.randint(0, 4, (2, 1, *SRC)).float()
    seq = K.AugmentationSequential(aug, **({} if data_keys is None else
                                           {"data_keys": data_keys}))
    with pytest.raises(TypeError, match="AugmentationSequential.*nn.Sequential"):
        seq(image) if data_keys is None else seq(image, mask)


# ---------------------------------------------------------------------------------------------
# tv_tensors
# ---------------------------------------------------------------------------------------------
class _Format:
    name = "XYWHR"


class _RotatedBoxes(torch.Tensor):
    """A stand-in for rotated ``BoundingBoxes`` (a format attribute)."""
    format = _Format()


def test_box_formats():
    """torchvision's formats, by their definitions: XYWH (x, y, w, h), CXCYWH (centre, size)."""
    xyxy = torch.tensor([[1.0, 2.0, 5.0, 8.0]])
    assert torch.equal(containers.to_xyxy(torch.tensor([[1.0, 2.0, 4.0, 6.0]]), "XYWH"), xyxy)
    assert torch.equal(containers.to_xyxy(torch.tensor([[3.0, 5.0, 4.0, 6.0]]), "CXCYWH"), xyxy)
    for fmt in containers.BOX_FORMATS:
        assert torch.equal(containers.to_xyxy(containers.from_xyxy(xyxy, fmt), fmt), xyxy)
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=0)
    rotated = torch.ones(1, 5).as_subclass(_RotatedBoxes)
    with pytest.raises(ValueError, match="boxes: format XYWHR"):
        aug({"rgb": torch.rand(1, 3, *SRC), "boxes": [rotated]})


def test_v2_compose_flips_valid_with_the_rest():
    """``v2.Compose([RandomReproject, RandomHorizontalFlip])`` moves rgb, labels and valid
    (a ``Mask``) together, for a batch and for an unbatched sample."""
    tv_tensors, v2 = _torchvision()
    gen = torch.Generator().manual_seed(4)
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=5)
    flip = v2.Compose([aug, v2.RandomHorizontalFlip(p=1.0)])
    for batch in ((2,), ()):
        sample = _sample(gen, batch)
        with torch.no_grad():
            out = flip({"rgb": tv_tensors.Image(sample["rgb"]),
                        "labels": tv_tensors.Mask(sample["labels"])})
            plain = aug({"rgb": sample["rgb"], "labels": sample["labels"]},
                        params=out["params"])
        assert type(out["valid"]) is tv_tensors.Mask and type(out["rgb"]) is tv_tensors.Image
        for key in ("rgb", "labels", "valid"):
            assert torch.equal(_plain(out[key]), plain[key].flip(-1))
        assert not torch.equal(plain["valid"], plain["valid"].flip(-1))   # the flip shows
        with torch.no_grad():   # plain labels and depth beside an Image: moved as Masks
            out = flip({"rgb": tv_tensors.Image(sample["rgb"]), "labels": sample["labels"],
                        "depth": sample["depth"]})
            plain = aug(sample, params=out["params"])
        for key in ("rgb", "labels", "depth", "valid"):
            assert torch.equal(_plain(out[key]), plain[key].flip(-1))


def test_tv_boxes_and_keypoints_containers():
    """``BoundingBoxes`` in any supported format are read as XYXY corners and written back in
    their format with the output size as canvas; ``KeyPoints`` get the output canvas."""
    tv_tensors, _ = _torchvision()
    boxes = tv_tensors.BoundingBoxes(torch.tensor([[1.0, 2.0, 4.0, 6.0]]), format="XYWH",
                                     canvas_size=SRC)
    points = tv_tensors.KeyPoints(torch.tensor([[3.0, 4.0]]), canvas_size=SRC)
    image = tv_tensors.Image(torch.rand(3, *SRC))
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=0)
    sample, _, _, _, wrapping = containers.enter(
        {"rgb": image, "boxes": boxes, "keypoints": points}, None, None, None,
        batch_dims={"rgb": 4, "labels": 3, "depth": 3}, owner=aug)
    assert type(sample["boxes"][0]) is torch.Tensor
    assert torch.equal(sample["boxes"][0], torch.tensor([[1.0, 2.0, 5.0, 8.0]]))
    assert sample["rgb"].shape == (1, 3, *SRC) and sample["keypoints"].shape == (1, 1, 2)
    out = containers.leave({"valid": torch.ones(1, 1, *OUT, dtype=torch.bool),
                            "boxes": [torch.tensor([[2.0, 3.0, 10.0, 7.0]])],
                            "keypoints": torch.tensor([[[5.0, 6.0]]])}, wrapping)
    assert type(out["boxes"]) is tv_tensors.BoundingBoxes
    assert out["boxes"].format == tv_tensors.BoundingBoxFormat.XYWH
    assert tuple(out["boxes"].canvas_size) == OUT
    assert torch.equal(_plain(out["boxes"]), torch.tensor([[2.0, 3.0, 8.0, 4.0]]))
    assert type(out["keypoints"]) is tv_tensors.KeyPoints
    assert tuple(out["keypoints"].canvas_size) == OUT and out["keypoints"].shape == (1, 2)
    assert type(out["valid"]) is tv_tensors.Mask
    _, _, _, _, wrapping = containers.enter({"rgb": image, "boxes": _plain(boxes)}, None, None,
                                            None, batch_dims={"rgb": 4}, owner=aug)
    out = containers.leave({"valid": torch.ones(1, 1, *OUT, dtype=torch.bool),
                            "boxes": [torch.tensor([[2.0, 3.0, 10.0, 7.0]])],
                            "keypoints": torch.tensor([[[5.0, 6.0]]])}, wrapping)
    assert type(out["boxes"]) is tv_tensors.BoundingBoxes   # plain boxes beside tv_tensors
    assert out["boxes"].format == tv_tensors.BoundingBoxFormat.XYXY
    assert tuple(out["boxes"].canvas_size) == OUT and type(out["keypoints"]) is tv_tensors.KeyPoints


@needs_boxes
def test_v2_compose_moves_boxes():
    """Boxes through the module then a v2 flip: in their format, canvas the output size, and
    where a flip of the module's own output puts them."""
    tv_tensors, v2 = _torchvision()
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, seed=6)
    boxes = tv_tensors.BoundingBoxes(torch.tensor([[8.0, 8.0, 6.0, 5.0]]), format="XYWH",
                                     canvas_size=SRC)
    image = tv_tensors.Image(torch.rand(3, *SRC))
    with torch.no_grad():
        out = v2.Compose([aug, v2.RandomHorizontalFlip(p=1.0)])({"rgb": image,
                                                                 "boxes": boxes})
        plain = aug({"rgb": _plain(image), "boxes": torch.tensor([[8.0, 8.0, 14.0, 13.0]])},
                    params=out["params"])
    assert out["boxes"].format == tv_tensors.BoundingBoxFormat.XYWH
    x0, y0, x1, y1 = plain["boxes"][0].tolist()
    expected = torch.tensor([[OUT[1] - x1, y0, x1 - x0, y1 - y0]])
    assert torch.allclose(_plain(out["boxes"]).float(), expected, atol=1e-4)


# ---------------------------------------------------------------------------------------------
# albumentations
# ---------------------------------------------------------------------------------------------
def _image_and_mask(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    mask = rng.integers(0, 6, (SRC[0] // 4, SRC[1] // 4)).repeat(4, 0).repeat(4, 1)
    image = np.stack([mask * 40, rng.integers(0, 255, SRC), 255 - mask * 40], -1)
    return image.astype(np.uint8), mask.astype(np.uint8)


def test_albumentations_moves_image_and_masks():
    """In ``A.Compose``, with albumentations' layout (HWC uint8): the mask lands where the
    image does (the image's first channel encodes the mask, nearest sampling), invalid pixels
    are 0 / ignore_index, and the Compose's seed reproduces the draw."""
    A = _albumentations()
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, interpolation="nearest",
                                     fov_range=(100 * DEG, 120 * DEG))
    image, mask = _image_and_mask(0)
    compose = A.Compose([ot.augment.to_albumentations(aug), A.HorizontalFlip(p=1.0)], seed=7)
    out = compose(image=image, mask=mask, masks=[mask, 5 - mask])
    assert out["image"].shape == (*OUT, 3) and out["image"].dtype == np.uint8
    assert out["mask"].shape == OUT and out["mask"].dtype == np.uint8
    valid = out["mask"] != aug.ignore_index
    assert 0.2 < valid.mean() < 1.0
    np.testing.assert_array_equal(out["image"][..., 0][valid], out["mask"][valid] * 40)
    np.testing.assert_array_equal(out["image"][~valid], 0)
    masks = np.asarray(out["masks"])
    np.testing.assert_array_equal(masks[0], out["mask"])
    np.testing.assert_array_equal(masks[1][valid], 5 - out["mask"][valid])
    again = A.Compose([ot.augment.to_albumentations(aug), A.HorizontalFlip(p=1.0)], seed=7)
    np.testing.assert_array_equal(again(image=image, mask=mask)["image"], out["image"])
    other = A.Compose([ot.augment.to_albumentations(aug)], seed=8)(image=image)["image"]
    assert not np.array_equal(other, out["image"][:, ::-1])


def test_albumentations_adapter_pickles_and_refuses():
    A = _albumentations()
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG)
    transform = ot.augment.to_albumentations(aug)
    image, _ = _image_and_mask(1)
    first = A.Compose([transform], seed=2)(image=image)["image"]
    copy = pickle.loads(pickle.dumps(transform))
    assert isinstance(copy, A.DualTransform)
    np.testing.assert_array_equal(A.Compose([copy], seed=2)(image=image)["image"], first)
    with pytest.raises(TypeError, match=r"targets \[.volume.\] are not supported"):
        A.Compose([transform])(image=image, volume=np.zeros((2, *SRC, 3), np.uint8))
    with pytest.raises(TypeError, match="mask: expected integer"):
        A.Compose([transform])(image=image, mask=np.zeros(SRC, np.float32))
    with pytest.raises(TypeError, match="module"):
        ot.augment.to_albumentations("RandomReproject")


def _pascal_voc(box, fmt: str) -> np.ndarray:
    """An albumentations box of format ``fmt`` on the output image as pixel corners."""
    a, b = np.asarray(box[:2], float), np.asarray(box[2:4], float)
    if fmt == "coco":       # x_min, y_min, width, height
        return np.concatenate((a, a + b))
    if fmt == "yolo":       # normalised centre and size
        size = np.array([OUT[1], OUT[0]], float)
        return np.concatenate(((a - b / 2) * size, (a + b / 2) * size))
    return np.concatenate((a, b))


@needs_boxes
@pytest.mark.parametrize("fmt", ["pascal_voc", "coco", "yolo"])
def test_albumentations_boxes_and_keypoints(fmt):
    """A box around a bright square and a keypoint at its centre: the box comes back as the
    tight box of the square's output pixels (within 1 px), with its label, and the keypoint
    at the square's output centroid, in albumentations' conventions."""
    A = _albumentations()
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, interpolation="nearest",
                                     fov_range=(120 * DEG, 140 * DEG))
    image = np.zeros((*SRC, 3), np.uint8)
    image[8:14, 10:18] = 255                                   # rows 8..13, columns 10..17
    corners = {"pascal_voc": [10, 8, 18, 14], "coco": [10, 8, 8, 6],
               "yolo": [14 / SRC[1], 11 / SRC[0], 8 / SRC[1], 6 / SRC[0]]}[fmt]
    compose = A.Compose([ot.augment.to_albumentations(aug)], seed=1,
                        bbox_params=A.BboxParams(fmt, label_fields=["cls"]),   # (its first
                        keypoint_params=A.KeypointParams("xy"))   # argument's name varies)
    out = compose(image=image, bboxes=[corners], cls=[3], keypoints=[(13.5, 10.5)])
    rows, cols = np.nonzero(out["image"][..., 0] > 127)
    tight = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], float)
    np.testing.assert_allclose(_pascal_voc(out["bboxes"][0], fmt), tight, atol=1.0)
    assert list(out["cls"]) == [3]
    np.testing.assert_allclose(out["keypoints"][0], [cols.mean(), rows.mean()], atol=0.75)


@needs_boxes
def test_albumentations_exact_boxes_and_polygons():
    """The adapter's exact mode: from ``masks`` (bbox j the box of masks[j]) and from an
    instance ``mask`` with each bbox's id in a label field, every box equals the tight box of
    its object's output pixels (the square's, read off the image, nearest); from ``polygons``
    (a custom key), within a pixel of it, with the rings and ``polygon_index`` back; bad
    pairings raise naming what is wrong."""
    A = _albumentations()
    aug = ot.augment.RandomReproject(OUT, source_fov=90 * DEG, interpolation="nearest",
                                     fov_range=(120 * DEG, 140 * DEG))
    image = np.zeros((*SRC, 3), np.uint8)
    square = np.zeros(SRC, np.uint8)
    square[8:14, 10:18] = 1                                    # rows 8..13, columns 10..17
    image[square > 0] = 255
    other = np.zeros(SRC, np.uint8)
    other[2:6, 2:12] = 1
    ids = (square.astype(np.uint16) * 300 + other * 7)
    boxes, labels = [[10, 8, 18, 14], [2, 2, 12, 6]], dict(cls=["car", "bus"], iid=[300, 7])
    params = A.BboxParams("pascal_voc", label_fields=["cls", "iid"])
    runs = {
        "masks": (dict(boxes_from="masks"), dict(masks=[square, other])),
        "mask": (dict(boxes_from="mask", instance_field="iid"), dict(mask=ids)),
        "polygons": ({}, dict(polygons=[[10, 8, 18, 8, 18, 14, 10, 14],
                                        [[2.0, 2], [12, 2], [12, 6], [2, 6]]])),
    }
    for name, (options, targets) in runs.items():
        compose = A.Compose([ot.augment.to_albumentations(aug, **options)], seed=1,
                            bbox_params=params)
        out = compose(image=image, bboxes=boxes, **labels, **targets)
        rows, cols = np.nonzero(out["image"][..., 0] > 127)
        tight = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], float)
        assert list(out["cls"]) == ["car", "bus"]
        if name == "polygons":
            np.testing.assert_allclose(out["bboxes"][0], tight, atol=1.0)
            assert out["polygon_index"].tolist() == [0, 1] and len(out["polygons"]) == 2
            ring = out["polygons"][0]
            np.testing.assert_allclose(out["bboxes"][0], np.r_[ring.min(0), ring.max(0)],
                                       atol=1e-4)
        else:
            np.testing.assert_array_equal(out["bboxes"][0], tight)
    with pytest.raises(ValueError, match=r"2 bboxes and 1 masks"):
        A.Compose([ot.augment.to_albumentations(aug, boxes_from="masks")],
                  bbox_params=params)(image=image, bboxes=boxes, **labels, masks=[square])
    with pytest.raises(ValueError, match=r"instance_field: 'id' is not a label field"):
        A.Compose([ot.augment.to_albumentations(aug, boxes_from="mask", instance_field="id")],
                  bbox_params=params)(image=image, bboxes=boxes, **labels, mask=ids)
    with pytest.raises(ValueError, match=r"bboxes\[1\]: its object has no pixel"):
        A.Compose([ot.augment.to_albumentations(aug, boxes_from="mask", instance_field="iid")],
                  bbox_params=params)(image=image, bboxes=boxes, cls=["car", "bus"],
                                      iid=[300, 8], mask=ids)
    with pytest.raises(ValueError, match="instance_field"):
        ot.augment.to_albumentations(aug, boxes_from="mask")
    with pytest.raises(ValueError, match="boxes_from"):
        ot.augment.to_albumentations(aug, boxes_from="instances")
    copy = pickle.loads(pickle.dumps(ot.augment.to_albumentations(aug, boxes_from="masks")))
    assert copy.boxes_from == "masks"
