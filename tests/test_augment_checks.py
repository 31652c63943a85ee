"""Bad inputs the augmentation refuses on every route (issue 43, item 5): label maps of
another size than the images, negative instance ids, unknown keys, normalised boxes."""

from __future__ import annotations

import warnings

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.augment import RandomOmniCamera, RandomReproject

K = torch.tensor([30.0, 30.0, 31.5, 23.5])


def _perspective(batch=2, h=48, w=64):
    g = torch.Generator().manual_seed(0)
    image = torch.rand(batch, 3, h, w, generator=g)
    instances = torch.zeros(batch, h, w, dtype=torch.int64)
    instances[:, 10:30, 20:40] = 7
    return image, instances


@pytest.mark.parametrize("backend", ["auto", "torch"])
def test_instances_of_another_size_are_refused(backend):
    image, instances = _perspective()
    aug = RandomReproject((32, 32), seed=0, backend=backend)
    with pytest.raises(ValueError, match=r"instances: 40 x 56 pixels per sample, expected "
                                         r"48 x 64 \(the images'"):
        aug({"rgb": image, "intrinsics": K, "instances": instances[:, :40, :56],
             "boxes": [torch.tensor([[20.0, 10.0, 40.0, 30.0]])] * 2,
             "box_instance_ids": [torch.tensor([7])] * 2})


def test_a_declared_label_map_of_another_size_is_refused_without_an_image():
    """With no image, labels or depth the first map sets the size: the others must match."""
    _, instances = _perspective()
    aug = RandomReproject((32, 32), source_fov=1.2, seed=0, label_keys={"parts": 255})
    with pytest.raises(ValueError, match=r"parts: 24 x 32 pixels per sample, expected 48 x 64 "
                                         r"\(instances's"):
        aug({"instances": instances, "parts": torch.zeros(2, 24, 32, dtype=torch.int64)})
    out = aug({"instances": instances, "parts": torch.zeros(2, 48, 64, dtype=torch.int64)})
    assert out["parts"].shape == (2, 32, 32) and out["instances"].shape == (2, 32, 32)


def test_negative_instance_ids_are_refused():
    image, instances = _perspective()
    instances[1, 0, 0] = -3
    with pytest.raises(ValueError, match=r"instances: negative ids \(sample 1, min -3\)"):
        RandomReproject((32, 32), seed=0)({"rgb": image, "intrinsics": K,
                                           "instances": instances})
    cube = torch.zeros(2, 6, 8, 8, dtype=torch.int64)
    cube[0, 2, 1, 1] = -1
    with pytest.raises(ValueError, match=r"instances: negative ids \(sample 0, min -1\)"):
        RandomOmniCamera((16, 16), 8, seed=0)({"rgb": torch.rand(2, 6, 3, 8, 8),
                                               "instances": cube})


def test_a_cube_map_of_another_face_size_is_refused():
    with pytest.raises(ValueError, match=r"instances: 4 x 4 pixels per sample, expected 8 x 8 "
                                         r"\(the cube's faces"):
        RandomOmniCamera((16, 16), 8, seed=0)({"rgb": torch.rand(1, 6, 3, 8, 8),
                                               "instances": torch.ones(1, 6, 4, 4).long()})


def test_unknown_keys_are_listed_with_the_accepted_ones():
    image, _ = _perspective()
    with pytest.raises(ValueError, match=r"image: unknown keys \['bboxes'\]; the keys taken are "
                                         r"\[.*'boxes'.*\]"):
        RandomReproject((32, 32), seed=0)({"rgb": image, "intrinsics": K, "bboxes": []})
    with pytest.raises(ValueError, match=r"cubemap: unknown keys \['mask'\]; the keys taken "
                                         r"are \[.*'instances'.*\]"):
        RandomOmniCamera((16, 16), 8, seed=0)({"rgb": torch.rand(1, 6, 3, 8, 8), "mask": 1})


def test_normalised_boxes_get_one_warning():
    image, _ = _perspective()
    boxes = [torch.tensor([[0.1, 0.2, 0.4, 0.6]]), torch.tensor([[0.5, 0.5, 0.9, 1.0]])]
    with pytest.warns(UserWarning, match=r"boxes: every box lies within \[0, 1\] on images of "
                                         r"64 x 48 pixels"):
        RandomReproject((32, 32), seed=0)({"rgb": image, "intrinsics": K, "boxes": boxes})
    pixels = [b * torch.tensor([64.0, 48.0, 64.0, 48.0]) for b in boxes]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        RandomReproject((32, 32), seed=0)({"rgb": image, "intrinsics": K, "boxes": pixels})


def test_reproject_refuses_labels_of_another_size_than_their_camera():
    labels = torch.zeros(1, 40, 56, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"image: size \(40, 56\) does not match the camera's "
                                         r"image_size \(48, 64\)"):
        ot.reproject(labels, ot.Camera("pinhole", K, (48, 64)),
                     ot.presets.fisheye((32, 32)), labels=True)


def test_an_unbatched_cube_of_the_wrong_size_is_reported_as_passed():
    aug = RandomOmniCamera((16, 16), 8, seed=0)
    with pytest.raises(ValueError, match=r"expected shape \(6, C, F, F\) or \(B, 6, C, F, F\) "
                                         r".*got \(6, 3, 4, 4\)"):
        aug(torch.rand(6, 3, 4, 4))


def test_a_panorama_that_is_not_2_to_1_is_refused():
    with pytest.raises(ValueError, match=r"panorama: expected a full equirectangular panorama, "
                                         r"W = 2 H .* 300 x 300"):
        ot.equirect_to_cubemap(torch.rand(1, 3, 300, 300), 16)
    assert ot.equirect_to_cubemap(torch.rand(1, 3, 16, 32), 8).shape == (1, 6, 3, 8, 8)
