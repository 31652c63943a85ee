"""Past one machine (issue 21): ``generate`` and ``convert`` on a real local Ray cluster,
``--shard K/N``, and WebDataset shards; each checked by hashing every file against the run of
one process with the same arguments, and the shard reader against the folder reader."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
import tarfile
from pathlib import Path

import pytest
import torch
from torch.utils.data import DataLoader

from omniscape_torch import cli
from omniscape_torch.data import distributed
from omniscape_torch.data.captures import convert_captures
from omniscape_torch.data.datasets import OmniDataset, OmniShardDataset
from omniscape_torch.data.generate import DatasetConfig, generate
from omniscape_torch.data.shards import shard_urls
from omniscape_torch.io.atomic import LOCK_NAME

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_carla import _three_captures, _truncate  # noqa: E402

CAMERAS = ("fisheye_left", "catadioptric_right")
WEATHER = ("clear_noon", "sunset")
#: Tiny frames (32 x 32 pixels, 16-texel faces): these tests check where bytes go, not how
#: they look. 3 frames, WebDataset shards of 2: shard 0 = frames 0-1, shard 1 = frame 2.
CONFIG = DatasetConfig(frames=3, image_size=(32, 32), face_size=16, cameras=CAMERAS,
                       weather=WEATHER)
ARGS = ["--frames", "3", "--image-size", "32", "--face-size", "16", "--cameras",
        ",".join(CAMERAS), "--weather", ",".join(WEATHER), "--no-progress"]
SHARD_ARGS = ["--format", "webdataset", "--frames-per-shard", "2"]


def _hashes(root: Path, skip: str | None = None) -> dict[str, str]:
    """SHA-256 of every file under ``root`` by relative path; not the locks (they hold the
    id of the last process that wrote the folder), nor the paths under ``skip``."""
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != LOCK_NAME
            and not (skip and p.relative_to(root).as_posix().startswith(skip))}


def _markers(root: Path) -> list[int]:
    return sorted(int(p.name) for p in (root / ".done").iterdir())


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The dataset with its WebDataset shards, written by this process alone."""
    out = tmp_path_factory.mktemp("reference") / "data"
    result = generate(out, CONFIG, format="webdataset", frames_per_shard=2, progress=False)
    assert result["rendered"] == [0, 1, 2]
    assert sorted(p.name for p in (out / "shards").iterdir()) == [
        "index.json", "shard-000000.tar", "shard-000001.tar"]
    return out


@pytest.mark.slow
def test_generate_on_ray_writes_the_same_bytes_reports_a_failed_frame_and_resumes(
        ray_cluster, reference, tmp_path, capsys):
    """On a real Ray cluster (2 CPUs): frame 1 cannot be written (a folder stands where its
    first image goes): the run reports that frame with its error and exits 1, the others
    are written (and the shard of frame 2); once the folder is gone the same command renders
    frame 1 only, and the dataset and its shards equal the single-process run's, byte for
    byte."""
    out = tmp_path / "ray"
    blocker = out / "fisheye_left" / "rgb" / "000001.png"
    blocker.mkdir(parents=True)
    argv = ["generate", "--out", str(out), *ARGS, *SHARD_ARGS, "--ray"]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    failed = [line for line in err.splitlines() if line.strip().startswith("frame ")]
    assert len(failed) == 1 and failed[0].strip().startswith("frame 1:"), err
    assert "000001.png" in failed[0]
    assert _markers(out) == [0, 2]
    assert (out / "shards" / "shard-000001.tar").is_file()
    assert not (out / "shards" / "shard-000000.tar").exists()
    blocker.rmdir()
    assert cli.main(argv) == 0
    assert "wrote 1 frame(s), skipped 2 finished" in capsys.readouterr().out
    assert _hashes(out) == _hashes(reference)


def test_runs_of_shares_together_write_one_run(reference, tmp_path, capsys):
    """``--shard 0/2`` and ``--shard 1/2`` take disjoint frames (0 and 2; 1), and together
    write the single-process dataset byte for byte; with ``--format webdataset`` a share is
    whole WebDataset shards."""
    out = tmp_path / "shares"
    assert cli.main(["generate", "--out", str(out), *ARGS, "--shard", "0/2"]) == 0
    assert _markers(out) == [0, 2]
    assert cli.main(["generate", "--out", str(out), *ARGS, "--shard", "1/2"]) == 0
    assert _markers(out) == [0, 1, 2]
    assert _hashes(out) == _hashes(reference, skip="shards/")

    out = tmp_path / "shard-shares"
    assert cli.main(["generate", "--out", str(out), *ARGS, *SHARD_ARGS, "--shard", "1/2"]) == 0
    assert _markers(out) == [2]
    assert sorted(p.name for p in (out / "shards").glob("*.tar")) == ["shard-000001.tar"]
    assert cli.main(["generate", "--out", str(out), *ARGS, *SHARD_ARGS, "--shard", "0/2"]) == 0
    assert _hashes(out) == _hashes(reference)
    capsys.readouterr()


def _same_items(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], torch.Tensor):
            assert a[key].dtype == b[key].dtype and torch.equal(a[key], b[key]), key
        else:
            assert a[key] == b[key], key


def test_pack_writes_the_same_shards_and_they_read_as_the_folder(reference, tmp_path, capsys):
    """``pack`` of the folder writes the shards ``generate --format webdataset`` wrote, byte
    for byte; their tar members are one sample per camera and frame; ``OmniShardDataset``
    (webdataset) reads them into the items ``OmniDataset`` reads from the folder, also
    through a DataLoader with 2 workers."""
    root = tmp_path / "data"
    shutil.copytree(reference, root)
    shutil.rmtree(root / "shards")
    assert cli.main(["pack", str(root), "--frames-per-shard", "2", "--no-progress"]) == 0
    assert "wrote 2 shard(s)" in capsys.readouterr().out
    assert _hashes(root) == _hashes(reference)
    with tarfile.open(root / "shards" / "shard-000001.tar") as tar:
        assert tar.getnames() == [f"000002_{c}.{f}" for c in CAMERAS for f in (
            "camera.json", "dynamics.json", "rgb.png", "depth.exr", "labels.png", "valid.png",
            "instances.npy", "objects.json")]
    # the index lists them (written by generate before any frame, and by pack)
    index = json.loads((root / "shards" / "index.json").read_text())
    assert index["sample"]["files"] == ["camera.json", "dynamics.json", "rgb.png", "depth.exr",
                                        "labels.png", "valid.png", "instances.npy",
                                        "objects.json"]

    modalities = ("rgb", "depth", "labels", "labels_color", "valid", "instances", "objects")
    folder = OmniDataset(root, modalities=modalities)
    assert len(folder) == 6
    expected = {(item["frame"], item["camera"]): item for item in folder}
    streamed = list(OmniShardDataset(root, modalities=modalities))
    assert [(i["frame"], i["camera"]) for i in streamed] == folder.items   # the same order
    for item in streamed:
        _same_items(item, expected[item["frame"], item["camera"]])
    loader = DataLoader(OmniShardDataset(root / "shards", shuffle=4, seed=1), batch_size=None,
                        num_workers=2)
    loaded = list(loader)
    assert sorted((i["frame"], i["camera"]) for i in loaded) == sorted(folder.items)
    plain = {(i["frame"], i["camera"]): i for i in OmniDataset(root)}
    for item in loaded:
        _same_items(item, plain[item["frame"], item["camera"]])
    one = OmniShardDataset(shard_urls(root)[:1], cameras=["catadioptric_right"], rgb_uint8=True)
    reference_one = OmniDataset(root, cameras=["catadioptric_right"], frames=[0, 1],
                                rgb_uint8=True)
    for a, b in zip(one, reference_one, strict=True):
        _same_items(a, b)


@pytest.mark.slow
def test_convert_on_ray_reports_a_corrupt_face_by_file_and_a_rerun_finishes(
        ray_cluster, tmp_path, capsys):
    """``convert --ray`` with a truncated face image: that capture is reported by file, the
    others are written (the bytes of a single-process run); after the file is repaired the
    same command converts it, and the output equals the single-process run's."""
    cubes = tmp_path / "cubemaps"
    bad = _three_captures(cubes)
    good = (bad / "back_rgb.png").read_bytes()
    local = tmp_path / "local"
    convert_captures(cubes, local, label_set="new", image_size=(16, 16), cameras=("fisheye",))
    _truncate(bad / "back_rgb.png")
    out = tmp_path / "ray"
    argv = ["convert", "--cubemaps", str(cubes), "--out", str(out), "--label-set", "new",
            "--size", "16", "16", "--cameras", "fisheye", "--ray", "--no-progress"]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert "1 of 3 captures failed" in err and "000002" in err and "back_rgb.png" in err
    assert not (out / "000002").exists()
    assert _hashes(out) == _hashes(local, skip="000002/")
    (bad / "back_rgb.png").write_bytes(good)
    assert cli.main(argv) == 0
    assert _hashes(out) == _hashes(local)


def test_without_ray_the_option_fails_at_once_naming_the_install(tmp_path, capsys,
                                                                monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)      # `import ray` raises ImportError
    out = tmp_path / "never"
    assert cli.main(["generate", "--out", str(out), *ARGS, "--ray"]) == 1
    err = capsys.readouterr().err
    assert distributed.RAY_INSTALL in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    assert cli.main(["convert", "--cubemaps", str(tmp_path), "--out", str(out), "--ray"]) == 1
    assert distributed.RAY_INSTALL in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--shard", "2/2"], "0 <= K < N"),
    (["--shard", "1"], "K/N"),
    (["--frames-per-shard", "4"], "webdataset"),
    (["--ray", "--workers", "2"], "workers"),
])
@pytest.mark.parametrize("ray_installed", [True, False])
def test_bad_options_are_one_line_and_exit_2(tmp_path, capsys, monkeypatch, argv, message,
                                             ray_installed):
    """A usage error is exit 2 whether or not the optional Ray is installed (a machine without
    it once answered ``--ray --workers 2`` with "Ray is not installed", exit 1)."""
    if not ray_installed:
        monkeypatch.setitem(sys.modules, "ray", None)      # `import ray` raises ImportError
    with pytest.raises(SystemExit) as info:   # argparse's usage error, or ours
        sys.exit(cli.main(["generate", "--out", str(tmp_path / "x"), *ARGS, *argv]))
    assert info.value.code == 2
    assert message in capsys.readouterr().err


def test_shares_are_disjoint_and_cover_every_item():
    items = list(range(11))
    parts = [distributed.shard_part(items, distributed.parse_shard(f"{k}/4")) for k in range(4)]
    assert sorted(i for part in parts for i in part) == items
    assert parts[1] == [1, 5, 9]
    for bad in ((1, 1), (-1, 2), (0, 0), (True, 2), "0/2"):
        with pytest.raises(ValueError, match="shard"):
            distributed.check_shard(bad)
