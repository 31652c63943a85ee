"""Datasets for tests/test_augment_workers.py, importable by module path (spawned DataLoader
workers unpickle them by name, so they cannot live in a test module)."""

import torch

from omniscape_torch.augment import FISHEYE_MODELS, RandomOmniCamera, RandomReproject

#: Small on purpose: output image (H, W), cube face side F, dataset length.
SIZE, FACE, ITEMS = (16, 16), 8, 8


def make_aug(seed: int | None = 0) -> RandomOmniCamera:
    """A fisheye module with a random centre and focal as well as a random attitude."""
    return RandomOmniCamera(SIZE, FACE, seed=seed, center_jitter=2.0,
                            focal_scale_range=(0.9, 1.1))


def params_rows(params: dict) -> torch.Tensor:
    """``(B, 13)`` float64: each sample's rotation (9) and camera params (fx, fy, cx, cy)."""
    return torch.cat((params["rotation"].flatten(1), params["camera_params"]), dim=1)


def cubes() -> torch.Tensor:
    """``(ITEMS, 6, 3, F, F)`` fixed RGB cubemaps."""
    return torch.rand(ITEMS, 6, 3, FACE, FACE, generator=torch.Generator().manual_seed(0))


class AugmentedCubes(torch.utils.data.Dataset):
    """Cubemaps augmented one at a time in ``__getitem__``: an item is its params row."""

    def __init__(self, aug: RandomOmniCamera) -> None:
        self.aug = aug
        self.cubes = cubes()

    def __len__(self) -> int:
        return ITEMS

    def __getitem__(self, i: int) -> torch.Tensor:
        return params_rows(self.aug(self.cubes[i:i + 1])["params"])[0]


class PlainCubes(torch.utils.data.Dataset):
    """The cubemaps as they are, for augmentation in ``collate_fn``."""

    def __init__(self) -> None:
        self.cubes = cubes()

    def __len__(self) -> int:
        return ITEMS

    def __getitem__(self, i: int) -> torch.Tensor:
        return self.cubes[i]


class AugmentCollate:
    """``collate_fn`` that augments the stacked batch: the batch's params rows ``(B, 13)``."""

    def __init__(self, aug: RandomOmniCamera) -> None:
        self.aug = aug

    def __call__(self, items: list[torch.Tensor]) -> torch.Tensor:
        return params_rows(self.aug(torch.stack(items))["params"])


def reseed_worker(worker_id: int) -> None:
    """``worker_init_fn`` pinning the dataset's module to ``100 + worker_id``."""
    torch.utils.data.get_worker_info().dataset.aug.reseed(100 + worker_id)


def make_reproject(seed: int | None = 0) -> RandomReproject:
    """A perspective -> fisheye module with a random attitude and lens of every model."""
    return RandomReproject(SIZE, source_fov=1.5, seed=seed, fisheye_models=FISHEYE_MODELS)


class AugmentedImages(torch.utils.data.Dataset):
    """Perspective images augmented one at a time (uint8 RGB and labels): an item is the params
    row and the valid pixel count of its fisheye image."""

    def __init__(self, aug: RandomReproject) -> None:
        self.aug = aug
        gen = torch.Generator().manual_seed(1)
        self.images = torch.randint(0, 256, (ITEMS, 3, 12, 16), generator=gen, dtype=torch.uint8)
        self.labels = torch.randint(0, 13, (ITEMS, 12, 16), generator=gen, dtype=torch.uint8)

    def __len__(self) -> int:
        return ITEMS

    def __getitem__(self, i: int) -> torch.Tensor:
        out = self.aug({"rgb": self.images[i:i + 1], "labels": self.labels[i:i + 1]})
        assert out["rgb"].dtype == torch.uint8 and out["labels"].dtype == torch.int64
        return torch.cat((params_rows(out["params"])[0], out["valid"].sum().reshape(1)))


def distorted_source():
    """A distorted OpenCV camera (the ``opencv`` model) of the 12 x 16 images."""
    import omniscape_torch as ot
    return ot.Camera("opencv", torch.tensor([14.0, 14.0, 7.5, 5.5, -0.2, 0.05, 1e-3, -5e-4]
                                            + [0.0] * 8, dtype=torch.float64), (12, 16))


class AugmentedSamples(AugmentedImages):
    """The same images, of a distorted source camera, augmented one at a time and returned
    whole (``rgb``, ``labels``, ``valid``, ``params``) for ``default_collate``."""

    def __getitem__(self, i: int) -> dict:
        out = self.aug({"rgb": self.images[i:i + 1], "labels": self.labels[i:i + 1]})
        out["params"]["model"] = out["params"]["model"][0]   # one name: collates to a list
        return {k: (v[0] if isinstance(v, torch.Tensor) else v) for k, v in out.items()}


class DetectionSamples(torch.utils.data.Dataset):
    """Unbatched perspective samples with boxes and keypoints, augmented one at a time in
    ``__getitem__`` (what a detection ``Dataset`` does): an item is the module's output dict,
    its input beside it under ``"input"`` (to replay it in the main process)."""

    def __init__(self, aug: RandomReproject) -> None:
        self.aug = aug
        gen = torch.Generator().manual_seed(3)
        self.images = torch.randint(0, 256, (ITEMS, 3, 24, 32), generator=gen,
                                    dtype=torch.uint8)
        corner = torch.rand(ITEMS, 4, 2, generator=gen) * torch.tensor([20.0, 14.0])
        self.boxes = torch.cat((corner, corner + 2 + 8 * torch.rand(ITEMS, 4, 2, generator=gen)),
                               -1)
        self.keypoints = torch.rand(ITEMS, 5, 2, generator=gen) * torch.tensor([32.0, 24.0])

    def __len__(self) -> int:
        return ITEMS

    def __getitem__(self, i: int) -> dict:
        sample = {"rgb": self.images[i], "boxes": self.boxes[i], "keypoints": self.keypoints[i]}
        return dict(self.aug(sample), input=sample)
