"""Readers of generated datasets (``io.readers``), the torch datasets (``datasets``) and the
writer's contact sheet."""

from __future__ import annotations

import json
import pickle

import cv2
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

import omniscape_torch as ot
from omniscape_torch.cubemap import FACES
from omniscape_torch.data.generate import DatasetConfig, generate
from omniscape_torch.data.datasets import CubemapCaptureDataset, OmniDataset, collate
from omniscape_torch.data.readers import (list_cameras, list_frames, read_camera, read_dynamics,
                                        read_extrinsics, read_frame, read_manifest)

SIZE = (32, 32)
FRAMES = 2
CAMERAS = ("fisheye_left", "catadioptric_right")


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    out = tmp_path_factory.mktemp("readers") / "data"
    config = DatasetConfig(frames=FRAMES, fps=2.0, image_size=SIZE, max_face_size=32,
                           cameras=CAMERAS, weather=("clear_noon", "sunset"), seed=0)
    result = generate(out, config, workers=1, progress=False)
    assert result["rendered"] == list(range(FRAMES))
    return out


def _exr_direct(path):
    import OpenEXR
    channels = OpenEXR.File(str(path), separate_channels=True).channels()
    assert list(channels) == ["Z"]
    return np.asarray(channels["Z"].pixels)


def test_listing(root):
    assert list_cameras(root) == list(CAMERAS)
    assert list_frames(root) == list(range(FRAMES))
    assert read_manifest(root)["frames"] == FRAMES


def test_unfinished_frames_are_not_listed(root, tmp_path):
    import shutil
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    (copy / ".done" / "000001").unlink()
    assert list_frames(copy) == [0]
    (copy / CAMERAS[1] / "depth" / "000000.exr").unlink()  # marker but a file missing
    assert list_frames(copy) == []
    assert list_frames(copy, cameras=[CAMERAS[0]]) == [0]
    assert list_frames(copy, check_files=False) == [0]
    assert len(OmniDataset(copy, cameras=[CAMERAS[0]])) == 1


def test_read_frame_matches_files_decoded_directly(root):
    for cam in CAMERAS:
        for k in range(FRAMES):
            n = f"{k:06d}"
            item = read_frame(root, cam, k, ("rgb", "depth", "labels", "labels_color", "valid"))
            bgr = cv2.imread(str(root / cam / "rgb" / f"{n}.png"), cv2.IMREAD_UNCHANGED)
            rgb = torch.from_numpy(bgr[..., ::-1].copy()).permute(2, 0, 1)
            assert item["rgb"].shape == (3,) + SIZE and item["rgb"].dtype == torch.float32
            assert torch.equal(item["rgb"], rgb.float() / 255)
            assert torch.equal(read_frame(root, cam, n, ("rgb",), rgb_uint8=True)["rgb"], rgb)
            labels = cv2.imread(str(root / cam / "labels" / f"{n}.png"), cv2.IMREAD_UNCHANGED)
            assert item["labels"].dtype == torch.int64
            assert np.array_equal(item["labels"].numpy(), labels.astype(np.int64))
            valid = cv2.imread(str(root / cam / "valid" / f"{n}.png"), cv2.IMREAD_UNCHANGED)
            # (1, H, W): the augmentation's shape of one sample
            assert item["valid"].dtype == torch.bool and item["valid"].shape == (1,) + SIZE
            assert np.array_equal(item["valid"][0].numpy(), valid == 255)
            assert torch.equal(item["valid"][0], item["labels"] != 255)
            assert item["valid"].any() and (~item["valid"]).any()
            depth = _exr_direct(root / cam / "depth" / f"{n}.exr")
            assert item["depth"].dtype == torch.float32 and depth.dtype == np.float32
            assert np.array_equal(item["depth"].numpy(), depth)            # bit-exact
            colour = cv2.imread(str(root / cam / "labels_color" / f"{n}.png"))[..., ::-1]
            colour = torch.from_numpy(colour.copy()).permute(2, 0, 1)
            assert torch.equal(item["labels_color"], colour)
            assert torch.equal(item["labels_color"].permute(1, 2, 0),
                               torch.from_numpy(ot.io.colorize(item["labels"])))


def _tar_sample(path, key):
    """The members of sample ``key`` of a shard, as webdataset hands them over (no
    webdataset: the tar read with the standard library)."""
    import tarfile
    with tarfile.open(path) as tar:
        return {"__key__": key, **{m.name[len(key) + 1:]: tar.extractfile(m).read()
                                   for m in tar.getmembers() if m.name.startswith(key + ".")}}


def test_instances_and_objects_read_back(root, tmp_path):
    """``instances`` and ``objects`` from the folder (read_frame, OmniDataset, through
    ``collate``) and from a shard's sample: the 16-bit PNG's ids (read with OpenCV) and the
    JSON's boxes, classes and ids, in the augmentation's keys; a dataset written before them
    still reads, and asking it for them is a ValueError naming the modality."""
    import shutil

    from omniscape_torch.data.shards import decode_sample, write_shard

    ds = OmniDataset(root, modalities=("labels", "instances", "objects"))
    for item in ds:
        n = f"{item['frame']:06d}"
        ids = cv2.imread(str(root / item["camera"] / "instances" / f"{n}.png"),
                         cv2.IMREAD_UNCHANGED)
        assert ids.dtype == np.uint16 and item["instances"].dtype == torch.int64
        assert np.array_equal(item["instances"].numpy(), ids.astype(np.int64))
        objects = json.loads((root / item["camera"] / "objects" / f"{n}.json").read_text())
        assert item["boxes"].dtype == torch.float32 and item["boxes"].shape == (len(objects), 4)
        assert item["boxes"].tolist() == [o["box"] for o in objects]
        assert item["box_labels"].tolist() == [o["label"] for o in objects]
        assert item["box_instance_ids"].tolist() == [o["instance_id"] for o in objects]
    batch = collate([ds[0], ds[1]])
    assert batch["instances"].shape == (2,) + SIZE
    for key in ("boxes", "box_labels", "box_instance_ids"):   # per sample, as the augmentation
        assert isinstance(batch[key], list) and _same(batch[key], [ds[0][key], ds[1][key]])
    same = collate([ds[0], ds[0]])       # equal numbers of boxes: still a list, not (B, N, 4)
    assert isinstance(same["boxes"], list) and len(same["boxes"]) == 2
    # a WebDataset sample holds them too, and decodes into the same item
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    shard = write_shard(copy, 0, [1], CAMERAS)
    item = decode_sample(_tar_sample(shard, f"000001_{CAMERAS[1]}"),
                         ("labels", "instances", "objects"))
    assert _same({k: item[k] for k in ("instances", "boxes", "box_labels", "box_instance_ids")},
                 {k: ds[3][k] for k in ("instances", "boxes", "box_labels", "box_instance_ids")})
    # a dataset written before instances: the same frames and items, without them
    for cam in CAMERAS:
        shutil.rmtree(copy / cam / "instances")
        shutil.rmtree(copy / cam / "objects")
    assert list_frames(copy) == list(range(FRAMES))
    assert _same(OmniDataset(copy)[1], OmniDataset(root)[1])
    with pytest.raises(ValueError, match="'instances'"):
        OmniDataset(copy, modalities=("rgb", "instances"))
    old = write_shard(copy, 0, [1], CAMERAS)
    sample = _tar_sample(old, f"000001_{CAMERAS[0]}")
    assert "instances.npy" not in sample and "instances.png" not in sample
    assert "labels.png" in sample
    with pytest.raises(ValueError, match="instances"):
        decode_sample(sample, ("instances",))


def test_instance_ids_up_to_65535_survive_plain_webdataset_decoding(root, tmp_path):
    """Ids past 8 bits (256, 1000, 65535) through a shard: ``wds.WebDataset(url).decode()``
    with its defaults (and with an image decoder asked for) gives the map exactly, as
    ``instances.npy``; ``OmniShardDataset`` too; a shard packed before (``instances.png``)
    still reads; the index lists the files; the folder's PNG reads exactly with
    ``read_instances`` and the documented recipes (OpenCV ``IMREAD_UNCHANGED``, Pillow)."""
    import shutil

    from PIL import Image
    import webdataset as wds

    from omniscape_torch.data.datasets import OmniShardDataset
    from omniscape_torch.data.readers import read_instances
    from omniscape_torch.data.shards import decode_sample, pack

    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    for p in (copy / "shards").glob("*"):
        p.unlink()
    ids = np.zeros(SIZE, np.uint16)
    ids[0, :6] = [1, 255, 256, 1000, 65534, 65535]
    ids[5:9, 3:7] = 65535
    path = copy / CAMERAS[0] / "instances" / "000001.png"
    assert cv2.imwrite(str(path), ids)                 # written by OpenCV, not the package
    with Image.open(path) as im:
        assert im.mode == "I;16" and np.array_equal(np.asarray(im), ids)
    assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), ids)
    assert torch.equal(read_instances(path), torch.from_numpy(ids.astype(np.int64)))
    pack(copy, 2, progress=False)
    index = json.loads((copy / "shards" / "index.json").read_text())
    assert index["sample"]["files"][-2:] == ["instances.npy", "objects.json"]
    url = str(copy / "shards" / "shard-000000.tar")
    key = f"000001_{CAMERAS[0]}"
    for decoded in (wds.WebDataset(url, shardshuffle=False).decode(),
                    wds.WebDataset(url, shardshuffle=False).decode("torchrgb")):
        sample = next(s for s in decoded if s["__key__"] == key)
        assert sample["instances.npy"].dtype == np.uint16
        assert np.array_equal(sample["instances.npy"], ids)
    item = next(i for i in OmniShardDataset(copy, modalities=("instances",))
                if (i["frame"], i["camera"]) == (1, CAMERAS[0]))
    assert torch.equal(item["instances"], torch.from_numpy(ids.astype(np.int64)))
    # a shard of before: instances.png, read all the same
    old = _tar_sample(url, key)
    old["instances.png"] = path.read_bytes()
    del old["instances.npy"]
    back = decode_sample(old, ("instances", "valid"))
    assert torch.equal(back["instances"], item["instances"])
    assert back["valid"].shape == (1,) + SIZE


def test_objects_file_checked_when_read(root, tmp_path):
    """A hand-edited ``objects.json`` with x1 < x0, a negative count or values of the wrong
    type: a ValueError naming the file, the object and what is wrong."""
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    path = copy / CAMERAS[0] / "objects" / "000000.json"
    objects = json.loads(path.read_text())
    assert objects, "the frame has objects"
    good = dict(objects[0])
    x0, y0, x1, y1 = good["box"]
    for edit, message in ((dict(box=[x1, y0, x0, y1]), "x0 < x1"),
                          (dict(pixels=-3), "pixels: expected an integer >= 1"),
                          (dict(box=[str(x0), y0, x1, y1]), "box: expected"),
                          (dict(label="10"), "label: expected"),
                          (dict(instance_id=True), "instance_id: expected"),
                          (dict(box=[x0, y0, x1]), "box: expected")):
        path.write_text(json.dumps([good, dict(good, **edit)]))
        with pytest.raises(ValueError) as err:
            read_frame(copy, CAMERAS[0], 0, ("objects",))
        text = str(err.value)
        assert str(path) in text and "object 1" in text and message in text, text
    path.write_text('{"box": [0, 0, 1, 1]}')
    with pytest.raises(ValueError, match="expected a JSON list"):
        read_frame(copy, CAMERAS[0], 0, ("objects",))


def test_read_frame_errors(root):
    with pytest.raises(ValueError, match="modalities"):
        read_frame(root, CAMERAS[0], 0, ("normals",))
    with pytest.raises(FileNotFoundError, match="000007"):
        read_frame(root, CAMERAS[0], 7)
    with pytest.raises(ValueError, match="frame"):
        read_frame(root, CAMERAS[0], -1)


def test_reader_equals_a_rerender(root):
    """The reader's labels and depth are what the public layer renders from the written
    intrinsics and extrinsics (bit-exact; float32 depth)."""
    from omniscape_torch.scenes.town import Town
    town = Town(0)
    dyn = read_dynamics(root)
    weather = read_manifest(root)["weather_per_frame"]
    cam = "catadioptric_right"
    camera = read_camera(root, cam)
    assert camera.image_size == SIZE
    extr = read_extrinsics(root, cam)
    for k in range(FRAMES):
        pose = extr["T_world_camera"][k]
        rot, centre = pose[:3, :3].float(), pose[:3, 3].float()
        # the faces written: those rendered, a superset of those the layer reads
        faces = torch.tensor([f in extr["faces"][k] for f in FACES])
        read = ot.visible_faces(camera, rot, face_size=extr["face_size"])
        assert not (read & ~faces).any()
        cube = town.render_cubemap(centre, None, extr["face_size"], faces=faces,
                                   t=dyn[k]["timestamp"], weather=weather[k])
        res = ot.OmniProjection(camera, extr["face_size"], fused_grid=False).render(
            depth=cube["depth"], labels=cube["labels"], rotation=rot)
        item = read_frame(root, cam, k)
        assert torch.equal(item["depth"], res["depth"][0, 0].float())
        assert torch.equal(item["labels"], res["labels"][0])
        assert torch.equal(item["valid"], res["valid"][0].bool())


def test_camera_extrinsics_dynamics(root):
    extr = read_extrinsics(root, "fisheye_left")
    t = extr["T_rig_camera"]
    assert t.dtype == torch.float64
    assert torch.allclose(t[:3, 3], torch.tensor([-0.4, -0.8, 0.6], dtype=torch.float64))
    assert set(extr["T_world_camera"]) == set(range(FRAMES))
    for pose in extr["T_world_camera"].values():
        r = pose[:3, :3]
        assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    dyn = read_dynamics(root)
    assert sorted(dyn) == list(range(FRAMES))
    assert dyn[1]["timestamp"] == pytest.approx(0.5)
    raw = json.loads((root / "dynamics.json").read_text())
    assert dyn[0] == raw[0]


def test_omni_dataset_items(root):
    ds = OmniDataset(root)
    assert len(ds) == FRAMES * len(CAMERAS)
    assert ds.items == [(k, c) for k in range(FRAMES) for c in CAMERAS]
    item = ds[3]
    assert item["frame"] == 1 and item["camera"] == CAMERAS[1]
    direct = read_frame(root, CAMERAS[1], 1)
    for m in ("rgb", "depth", "labels", "valid"):
        assert torch.equal(item[m], direct[m])
    camera = ds.camera(CAMERAS[1])
    assert item["model"] == camera.model.name
    assert torch.equal(item["intrinsics"], camera.params)
    assert item["image_size"].tolist() == list(SIZE)
    assert torch.equal(item["T_world_camera"],
                       read_extrinsics(root, CAMERAS[1])["T_world_camera"][1])
    assert item["dynamics"] == read_dynamics(root)[1]
    assert item["weather"] == read_manifest(root)["weather_per_frame"][1]
    sub = OmniDataset(root, cameras=["fisheye_left"], modalities=("labels",), frames=[1])
    assert len(sub) == 1 and set(sub[0]) >= {"labels"} and "rgb" not in sub[0]
    with pytest.raises(ValueError, match="cameras"):
        OmniDataset(root, cameras=["fisheye_right"])
    with pytest.raises(ValueError, match="frames"):
        OmniDataset(root, frames=[5])
    with pytest.raises(IndexError):
        ds[len(ds)]


def _same(a, b):
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def test_omni_dataset_dataloader_workers(root):
    ds = OmniDataset(root, modalities=("rgb", "depth", "labels", "labels_color", "valid"))
    pickle.loads(pickle.dumps(ds))
    serial = [ds[i] for i in range(len(ds))]
    loader = DataLoader(ds, batch_size=None, num_workers=2, shuffle=False)
    parallel = list(loader)
    assert len(parallel) == len(serial)
    for a, b in zip(serial, parallel):
        assert _same(a, b)
    batches = list(DataLoader(ds, batch_size=2, num_workers=2, collate_fn=collate))
    assert len(batches) == FRAMES
    assert batches[0]["rgb"].shape == (2, 3) + SIZE
    assert isinstance(batches[0]["intrinsics"], list)      # 4 and 9 parameters: not stacked
    assert _same(batches[1]["intrinsics"], [serial[2]["intrinsics"], serial[3]["intrinsics"]])
    one = OmniDataset(root, cameras=["fisheye_left"])       # one model: the default collate
    batch = next(iter(DataLoader(one, batch_size=2, num_workers=2)))
    assert batch["intrinsics"].shape == (2, 4) and batch["frame"].tolist() == [0, 1]
    assert batches[0]["camera"] == list(CAMERAS)
    assert batches[0]["T_world_camera"].shape == (2, 4, 4)
    assert batches[0]["dynamics"]["location"]["x"].shape == (2,)


# ---------------------------------------------------------------------------- captures

F = 8


def _write_capture(folder, seed):
    """A CARLA-like capture written without the library's encoders: rgb, depth (24-bit code
    in R, G, B), tags of the 13-class set in the red channel."""
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (6, F, F, 3), dtype=np.uint8)
    code = rng.integers(1, 256 ** 3, (6, F, F), dtype=np.int64)
    tags = rng.integers(0, 13, (6, F, F), dtype=np.int64)
    folder.mkdir(parents=True)
    for i, face in enumerate(FACES):
        cv2.imwrite(str(folder / f"{face}_rgb.png"), rgb[i][..., ::-1])
        packed = np.stack([code[i] % 256, (code[i] // 256) % 256, code[i] // 65536], -1)
        cv2.imwrite(str(folder / f"{face}_depth.png"), packed.astype(np.uint8)[..., ::-1])
        lab = np.zeros((F, F, 3), np.uint8)
        lab[..., 0] = tags[i]
        cv2.imwrite(str(folder / f"{face}_labels.png"), lab[..., ::-1])
    depth = (code * (1000.0 / (256 ** 3 - 1))).astype(np.float32)
    return rgb, depth, tags


def test_cubemap_capture_dataset(tmp_path):
    root = tmp_path / "cubemaps"
    truth = {name: _write_capture(root / name, i) for i, name in enumerate(("000001", "000002"))}
    ds = CubemapCaptureDataset(root, label_set="13")
    pickle.loads(pickle.dumps(ds))
    assert len(ds) == 2
    items = [ds[i] for i in range(len(ds))]
    for item in items:
        rgb, depth, tags = truth[item["capture"]]
        assert item["face_size"] == F
        assert item["rgb"].shape == (6, 3, F, F) and item["rgb"].dtype == torch.float32
        assert torch.equal(item["rgb"], torch.from_numpy(rgb).permute(0, 3, 1, 2).float() / 255)
        assert item["depth"].shape == (6, F, F) and item["depth"].dtype == torch.float32
        np.testing.assert_allclose(item["depth"].numpy(), depth, rtol=1e-6)
        assert item["labels"].dtype == torch.int64
        assert torch.equal(item["labels"], torch.from_numpy(tags))   # set "13": identity
    loaded = list(DataLoader(ds, batch_size=None, num_workers=2))
    for a, b in zip(items, loaded):
        assert _same(a, b)
    with pytest.raises(ValueError, match="label_set"):
        CubemapCaptureDataset(root, label_set="99")


# ---------------------------------------------------------------------------- contact sheet

def test_contact_sheet(root):
    import cv2

    from omniscape_torch.data.generate import SHEET_CELL, SHEET_COLUMNS
    path = root / "contact_sheet.png"
    assert path.is_file()
    image = ot.io.read_image(path).numpy()
    weathers = {}
    for k, w in enumerate(read_manifest(root)["weather_per_frame"]):
        weathers.setdefault(w, k)
    extra = 0 if len(weathers) < 2 else -(-len(weathers) // len(SHEET_COLUMNS))
    assert image.shape[:2] == ((len(CAMERAS) + extra) * SHEET_CELL,
                               len(SHEET_COLUMNS) * SHEET_CELL)
    assert image.std() > 10          # not blank
    assert "contact_sheet.png" in read_manifest(root)["layout"]

    # with more than one weather, a row of the first camera's RGB at the given frame of each
    # (below the title band), in order; missing cells black
    from omniscape_torch.data.generate import contact_sheet
    sheet = cv2.imdecode(np.frombuffer(contact_sheet(root, CAMERAS, 0, {"a": 1, "b": 0}),
                                       np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    assert sheet.shape[:2] == ((len(CAMERAS) + 1) * SHEET_CELL, len(SHEET_COLUMNS) * SHEET_CELL)
    row = sheet[len(CAMERAS) * SHEET_CELL:]
    for i, k in enumerate((1, 0)):
        rgb = ot.io.read_image(root / CAMERAS[0] / "rgb" / f"{k:06d}.png").numpy()
        want = cv2.resize(rgb, (SHEET_CELL, SHEET_CELL), interpolation=cv2.INTER_NEAREST)
        cell = row[:, i * SHEET_CELL:(i + 1) * SHEET_CELL]
        assert np.abs(cell[20:].astype(int) - want[20:].astype(int)).max() <= 1, k
    assert row[:, 2 * SHEET_CELL:].max() == 0


# ---------------------------------------------------------------------------- objects

def test_objects_of_an_instance_map_and_bad_input():
    """Boxes against a hand-made map (XYXY corners: columns u0..u1 -> x0 = u0, x1 = u1 + 1),
    the class the most pixels have (the smaller on a tie), and the errors."""
    from omniscape_torch.data.objects import (decode_objects, encode_objects, instance_image,
                                              instance_objects)

    ids = torch.zeros(6, 7, dtype=torch.int64)
    ids[1:3, 2:6] = 9            # rows 1..2, columns 2..5
    ids[5, 0] = 70000            # one pixel in the corner, an id past 16 bits
    labels = torch.full((6, 7), 10)
    labels[1, 2:4] = 4           # 2 of instance 9's 8 pixels are Pedestrian
    labels[5, 0] = 5
    objects = instance_objects(ids, labels)
    assert objects == [
        {"instance_id": 9, "label": 10, "class": "Vehicle", "box": [2, 1, 6, 3], "pixels": 8},
        {"instance_id": 70000, "label": 5, "class": "Pole", "box": [0, 5, 1, 6], "pixels": 1}]
    labels[2, 2:6] = 4           # now 4 and 4: the smaller label
    assert instance_objects(ids, labels)[0]["label"] == 4
    assert instance_objects(torch.zeros(3, 3, dtype=torch.int32), labels[:3, :3]) == []
    back = decode_objects(encode_objects(objects))
    assert back["boxes"].tolist() == [[2, 1, 6, 3], [0, 5, 1, 6]]
    assert back["box_labels"].tolist() == [10, 5]
    assert back["box_instance_ids"].tolist() == [9, 70000]
    assert decode_objects("[]\n")["boxes"].shape == (0, 4)
    with pytest.raises(ValueError, match="0..65535"):
        instance_image(ids)
    with pytest.raises(TypeError, match="instances"):
        instance_objects(ids.float(), labels)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        instance_objects(ids, labels[:2])
    with pytest.raises(ValueError, match=">= 0"):
        instance_objects(-ids, labels)
    with pytest.raises(ValueError, match="x.json: object 0: no instance_id, label"):
        decode_objects('[{"box": [1, 2]}]', "x.json")
    from omniscape_torch.data.objects import pack_instances, unpack_instances
    packed = pack_instances(torch.tensor([[3, 255]]), torch.tensor([[70000, 0]]))
    assert [t.tolist() for t in unpack_instances(packed)] == [[[3, 255]], [[70000, 0]]]
    with pytest.raises(ValueError, match="labels"):
        pack_instances(torch.tensor([256]), torch.tensor([1]))
