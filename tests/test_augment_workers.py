"""RandomOmniCamera in DataLoader workers (GitHub issue 17, item 1): the module's stream follows
PyTorch's worker seeds, so epochs and workers draw different cameras and attitudes, a module
used in the main process before the workers start does not make them repeat each other, and
the same ``seed`` with the same ``DataLoader(generator=...)`` repeats a whole run, with forked
and spawned workers alike. Asserted on the drawn params (rotation and camera params)."""

import pytest
import torch
from torch.utils.data import DataLoader, default_collate

import omniscape_torch as ot

from _worker_data import (FACE, ITEMS, AugmentCollate, AugmentedCubes, AugmentedImages,
                          AugmentedSamples, DetectionSamples, PlainCubes, distorted_source,
                          make_aug, make_reproject, params_rows, reseed_worker)
from omniscape_torch.augment import RandomReproject

EPOCHS = 2


def _loader(aug, style="dataset", generator_seed=None, **kw):
    """A loader of params rows: the module applied per item in the Dataset, or per batch in
    ``collate_fn`` (both ways of the README and notebook 02)."""
    kw.setdefault("batch_size", 2)
    if generator_seed is not None:
        kw["generator"] = torch.Generator().manual_seed(generator_seed)
    if style == "dataset":
        return DataLoader(AugmentedCubes(aug), **kw)
    return DataLoader(PlainCubes(), collate_fn=AugmentCollate(aug), **kw)


def _run(loader, epochs=EPOCHS):
    """``[epoch][batch] -> (B, 13)`` params rows."""
    return [list(loader) for _ in range(epochs)]


def _repeats(batches):
    """Pairs of batches (indices into the flat list) with equal params."""
    return [(i, j) for i in range(len(batches)) for j in range(i + 1, len(batches))
            if torch.equal(batches[i], batches[j])]


def _same_run(a, b):
    return len(a) == len(b) and all(
        len(x) == len(y) and all(torch.equal(u, v) for u, v in zip(x, y)) for x, y in zip(a, b))


def test_main_process_epochs_differ_and_a_seed_repeats_the_run():
    run = _run(_loader(make_aug(seed=3), num_workers=0))
    assert len(run) == EPOCHS and len(run[0]) == 4
    assert not _repeats(run[0] + run[1])
    assert not torch.equal(torch.cat(run[0]), torch.cat(run[1]))   # the stream continues
    assert _same_run(run, _run(_loader(make_aug(seed=3), num_workers=0)))
    assert not _same_run(run, _run(_loader(make_aug(seed=4), num_workers=0)))


@pytest.mark.parametrize("seed", [0, None])
@pytest.mark.parametrize("persistent", [False, True])
@pytest.mark.parametrize("style", ["dataset", "collate"])
def test_workers_and_epochs_draw_different_params(style, persistent, seed):
    loader = _loader(make_aug(seed=seed), style, num_workers=2, persistent_workers=persistent,
                     multiprocessing_context="fork")
    run = _run(loader)
    assert [len(epoch) for epoch in run] == [4] * EPOCHS
    # batches 0, 2 come from worker 0 and 1, 3 from worker 1; every batch differs from every
    # other, within the epoch (workers) and across epochs
    assert not _repeats(run[0]), "workers repeat each other"
    assert not _repeats(run[0] + run[1]), "epochs repeat each other"


@pytest.mark.parametrize("persistent", [False, True])
@pytest.mark.parametrize("style", ["dataset", "collate"])
def test_a_module_used_before_the_workers_start_does_not_make_them_repeat(style, persistent):
    aug = make_aug(seed=0)
    before = params_rows(aug(torch.rand(2, 6, 3, FACE, FACE))["params"])
    run = _run(_loader(aug, style, num_workers=2, persistent_workers=persistent,
                       multiprocessing_context="fork"))
    assert not _repeats(run[0] + run[1])
    assert not any(torch.equal(before, batch) for batch in run[0] + run[1])
    # and the main process's stream goes on from where it was
    assert not torch.equal(before, params_rows(aug.forward_parameters(2)))


def _reproducible_run(context, generator_seed, seed=5):
    aug = make_aug(seed=seed)
    aug.forward_parameters(2)   # used in the main process first: its state travels to workers
    return _run(_loader(aug, num_workers=2, generator_seed=generator_seed,
                        multiprocessing_context=context))


def test_seed_and_loader_generator_reproduce_a_forked_run():
    run = _reproducible_run("fork", generator_seed=7)
    assert not _repeats(run[0] + run[1])
    assert _same_run(run, _reproducible_run("fork", generator_seed=7))
    # the loader's generator and the module's seed both matter
    for other in (_reproducible_run("fork", generator_seed=8),
                  _reproducible_run("fork", generator_seed=7, seed=6)):
        assert not any(torch.equal(a, b) for a in run[0] + run[1] for b in other[0] + other[1])


@pytest.mark.slow
def test_seed_and_loader_generator_reproduce_a_spawned_run():
    # spawned workers unpickle the module (and its generator state): the same rule applies,
    # and the draws do not depend on the start method
    run = _reproducible_run("spawn", generator_seed=7)
    assert not _repeats(run[0] + run[1])
    assert _same_run(run, _reproducible_run("spawn", generator_seed=7))
    assert _same_run(run, _reproducible_run("fork", generator_seed=7))


def test_reseed_in_worker_init_fn_pins_each_workers_stream():
    loader = DataLoader(AugmentedCubes(make_aug(seed=0)), batch_size=2, num_workers=2,
                        worker_init_fn=reseed_worker, multiprocessing_context="fork")
    batches = list(loader)
    for worker in (0, 1):
        ref = make_aug(seed=100 + worker)
        expected = [torch.cat([params_rows(ref.forward_parameters(1)) for _ in range(2)])
                    for _ in batches[worker::2]]
        assert all(torch.equal(a, b) for a, b in zip(batches[worker::2], expected))


def test_a_calls_generator_wins_in_workers():
    class Fixed(AugmentCollate):
        def __call__(self, items):
            g = torch.Generator().manual_seed(42)
            return params_rows(self.aug(torch.stack(items), generator=g)["params"])
    expected = params_rows(make_aug(seed=0).forward_parameters(
        2, generator=torch.Generator().manual_seed(42)))
    loader = DataLoader(PlainCubes(), batch_size=2, num_workers=2, collate_fn=Fixed(make_aug()),
                        multiprocessing_context="fork")
    assert all(torch.equal(batch, expected) for batch in loader)


def test_per_sample_draws_of_different_models_collate():
    """Augmenting one sample at a time (in a ``Dataset``) with mixed models: the default
    ``collate_fn`` stacks the drawn parameters (``camera_params`` is padded to the largest
    model's count, ``num_params`` says how many are used) and the batch replays them."""
    aug = ot.augment.RandomOmniCamera((16, 16), 8, mode="mixed", seed=1)
    cube = torch.rand(1, 6, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    outs = [aug(cube) for _ in range(6)]
    assert len({o["params"]["model"][0] for o in outs}) == 2   # fisheye and catadioptric
    params = default_collate([{k: v for k, v in o["params"].items() if k != "model"}
                              for o in outs])
    assert params["camera_params"].shape == (6, 1, 9)
    for o, row, n in zip(outs, params["camera_params"][:, 0], params["num_params"][:, 0]):
        assert torch.equal(row[:n], o["params"]["camera_params"][0, :n])
        assert bool((row[n:] == 0).all())


@pytest.mark.parametrize("context", ["fork", pytest.param("spawn", marks=pytest.mark.slow)])
def test_random_reproject_in_workers(context):
    """RandomReproject shares RandomOmniCamera's randomness: in forked and spawned workers
    every batch of two epochs differs from every other, and the same seeds repeat the run."""
    def run():
        loader = DataLoader(AugmentedImages(make_reproject(seed=5)), batch_size=2,
                            num_workers=2, multiprocessing_context=context,
                            generator=torch.Generator().manual_seed(6))
        return _run(loader)
    first = run()
    assert [len(epoch) for epoch in first] == [4] * EPOCHS
    assert not _repeats(first[0] + first[1])
    assert all(bool((batch[:, -1] > 0).all()) for epoch in first for batch in epoch)
    assert _same_run(first, run())


@pytest.mark.parametrize("context", ["fork", pytest.param("spawn", marks=pytest.mark.slow)])
def test_a_distorted_source_in_workers_collates_and_replays(context):
    """RandomReproject from a distorted OpenCV camera, per sample in a Dataset that returns the
    whole output: DataLoader's default_collate stacks it (the source camera's record too), the
    two epochs differ, and the collated params of a batch replay its images."""
    aug = ot.augment.RandomReproject((16, 16), source_camera=distorted_source(), seed=3)
    data = AugmentedSamples(aug)
    loader = DataLoader(data, batch_size=4, num_workers=2, multiprocessing_context=context,
                        generator=torch.Generator().manual_seed(4))
    epochs = [list(loader) for _ in range(EPOCHS)]
    assert [len(e) for e in epochs] == [2] * EPOCHS
    batch = epochs[0][0]
    assert batch["rgb"].shape == (4, 3, 16, 16) and batch["rgb"].dtype == torch.uint8
    assert batch["params"]["source_camera"]["params"].shape == (4, 1, 16)   # stacked rows
    assert not torch.equal(epochs[0][0]["params"]["rotation"], epochs[1][0]["params"]["rotation"])
    params = {k: v.flatten(0, 1) if isinstance(v, torch.Tensor) else v   # (4, 1, ...) rows
              for k, v in batch["params"].items()}
    params["model"] = tuple(params["model"])
    again = aug.render(data.images[:4], params, labels=data.labels[:4],   # no shuffle
                       source_camera=batch["params"]["source_camera"])
    assert torch.equal(again["rgb"], batch["rgb"]) and torch.equal(again["valid"],
                                                                    batch["valid"])


@pytest.mark.parametrize("context", ["fork", pytest.param("spawn", marks=pytest.mark.slow)])
def test_boxes_and_keypoints_follow_each_workers_draw_across_epochs(context):
    """Detection targets augmented per sample in forked and spawned workers, two epochs (a
    detection ``Dataset`` with ``collate_fn=list``): every item's boxes and keypoints are those
    of its own draw (replayed in the main process from the item's params), and the epochs draw
    anew."""
    aug = RandomReproject((32, 32), source_fov=1.5, seed=0, fisheye_models=("equidistant",))
    loader = torch.utils.data.DataLoader(DetectionSamples(aug), batch_size=4, num_workers=2,
                                         collate_fn=list, multiprocessing_context=context)
    epochs = [[item for batch in loader for item in batch] for _ in range(2)]
    for items in epochs:
        assert len(items) == ITEMS
        # (something to compare: most boxes and keypoints stay in view)
        assert sum(len(item["boxes"]) for item in items) > 2 * ITEMS
        assert sum(int(item["keypoints_valid"].sum()) for item in items) > 2 * ITEMS
        for item in items:
            again = aug(item["input"], params=item["params"])
            assert torch.equal(again["box_index"], item["box_index"])
            assert torch.equal(again["boxes"], item["boxes"])
            assert torch.equal(again["keypoints_valid"], item["keypoints_valid"])
            assert torch.allclose(again["keypoints"], item["keypoints"], equal_nan=True)
    first, second = ([item["params"]["rotation"] for item in items] for items in epochs)
    assert not any(torch.equal(a, b) for a, b in zip(first, second))
