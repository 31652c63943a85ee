"""Exports (``data.export``, ``omniscape-torch export``), each read back by the tool that
reads its format: pycocotools and faster-coco-eval (COCO), mmsegmentation's documented layout,
cityscapesscripts (its label table, file-name parser, JSON loader and ``json2labelImg``
drawing), and the YOLO text format parsed back."""

from __future__ import annotations

import contextlib
import io
import json
import math
import shutil
import sys

import numpy as np
import pytest
import torch
from PIL import Image

import omniscape_torch as ot
from omniscape_torch import cli
from omniscape_torch.data.export import FORMATS, coco_rle, export_dataset, export_samples, \
    split_frames
from omniscape_torch.data.generate import DatasetConfig, generate
from omniscape_torch.io.labels import CLASSES

# pycocotools' decode on numpy 2
pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")

SIZE = (48, 48)
CAMERAS = ("fisheye_left", "catadioptric_right")
FRAMES = 2


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "data"
    config = DatasetConfig(frames=FRAMES, image_size=SIZE, max_face_size=32, cameras=CAMERAS,
                           weather=("clear_noon",), antialias=1, seed=0)
    generate(out, config, workers=1, progress=False)
    return out


def _png(path) -> np.ndarray:
    with Image.open(path) as im:
        return np.array(im)


def _objects(root, camera, frame) -> list[dict]:
    return json.loads((root / camera / "objects" / f"{frame:06d}.json").read_text())


def _quiet(fn, *args):
    with contextlib.redirect_stdout(io.StringIO()):
        return fn(*args)


def _ap(evaluator) -> float:
    """AP at IoU 0.50:0.95 of a COCOeval (pycocotools' or faster-coco-eval's), quietly."""
    with contextlib.redirect_stdout(io.StringIO()):
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    return evaluator.stats[0]


def test_coco_rle_is_pycocotools_encoding():
    """The RLE written without pycocotools equals ``pycocotools.mask.encode`` of the
    Fortran-order uint8 mask (counts decoded), on random masks, full, empty and one-pixel
    ones."""
    mask_api = pytest.importorskip("pycocotools.mask")
    rng = np.random.default_rng(0)
    masks = [rng.random(tuple(rng.integers(1, 40, 2))) < rng.random() for _ in range(100)]
    masks += [np.ones((5, 7), bool), np.zeros((5, 7), bool), np.eye(1, 9, 8, dtype=bool)]
    for mask in masks:
        want = mask_api.encode(np.asfortranarray(mask.astype(np.uint8)))
        got = coco_rle(mask)
        assert got["counts"] == want["counts"].decode("ascii")
        assert got["size"] == list(want["size"])
        assert np.array_equal(mask_api.decode({"size": got["size"],
                                               "counts": got["counts"].encode()}), mask)


def test_coco_scores_ap_1_against_itself_and_masks_decode_to_the_instance_maps(root, tmp_path):
    """``export coco``: pycocotools and faster-coco-eval load it; its ground truth as
    detections scores AP 1.000 (bbox and segm) in both; every mask decodes to its instance's
    pixels in the dataset's map, areas and boxes are ``area``/``toBbox`` of the masks."""
    from faster_coco_eval import COCO as FastCOCO
    from faster_coco_eval import COCOeval_faster
    from pycocotools import mask as mask_api
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    out = tmp_path / "coco"
    result = export_dataset("coco", root, out, val_fraction=0.5, seed=0)
    assert result["images"] == {"train": 2, "val": 2}
    compared = 0
    for split in ("train", "val"):
        path = str(out / "annotations" / f"instances_{split}.json")
        gt = _quiet(COCO, path)
        assert [c["name"] for c in gt.dataset["categories"]] == list(ot.data.format
                                                                     .INSTANCE_CLASSES)
        assert [c["id"] for c in gt.dataset["categories"]] == [
            CLASSES.index(n) for n in ot.data.format.INSTANCE_CLASSES]
        anns = gt.loadAnns(gt.getAnnIds())
        assert anns and all(a["iscrowd"] == 0 and a["id"] >= 1 for a in anns)
        dets = [dict(a, score=1.0) for a in anns]
        for kind in ("bbox", "segm"):
            ev = COCOeval(gt, _quiet(gt.loadRes, [dict(d) for d in dets]), kind)
            assert _ap(ev) == pytest.approx(1.0) and ev.stats[1] == pytest.approx(1.0)
            fgt = _quiet(FastCOCO, path)
            fev = COCOeval_faster(fgt, _quiet(fgt.loadRes, [dict(d) for d in dets]), kind)
            assert _ap(fev) == pytest.approx(1.0)
        for image in gt.dataset["images"]:
            assert (out / split / image["file_name"]).read_bytes() == (
                root / image["camera"] / "rgb" / f"{image['frame']:06d}.png").read_bytes()
            ids = _png(root / image["camera"] / "instances" / f"{image['frame']:06d}.png")
            rebuilt = np.zeros(ids.shape, np.int64)
            for a in gt.loadAnns(gt.getAnnIds(imgIds=[image["id"]])):
                m = mask_api.decode(a["segmentation"]).astype(bool)
                assert not rebuilt[m].any()           # no two masks share a pixel
                rebuilt[m] = a["instance_id"]
                assert int(mask_api.area(a["segmentation"])) == a["area"]
                assert mask_api.toBbox(a["segmentation"]).tolist() == a["bbox"]
                compared += 1
            assert np.array_equal(rebuilt, ids.astype(np.int64))   # every object, exactly
    objects = sum(len(_objects(root, c, k)) for c in CAMERAS for k in range(FRAMES))
    assert compared == objects > 0


def test_mmseg_layout(root, tmp_path):
    """``export mmseg``: mmseg's custom-dataset layout (img_dir/ann_dir by split, .png), each
    annotation an 8-bit one-channel PNG of class indices 0..K-1 (the subset in its order) or
    255, the labels remapped exactly; metainfo's classes and palette."""
    out = tmp_path / "mmseg"
    export_dataset("mmseg", root, out, classes=["Vehicle", "Road", "Building"],
                   val_fraction=0.5)
    meta = json.loads((out / "metainfo.json").read_text())
    assert meta["classes"] == ["Vehicle", "Road", "Building"]
    assert meta["palette"] == [ot.io.PALETTE[CLASSES.index(n)].tolist() for n in meta["classes"]]
    assert meta["ignore_index"] == 255 and meta["reduce_zero_label"] is False
    seen = 0
    for split in ("train", "val"):
        names = sorted(p.name for p in (out / "img_dir" / split).iterdir())
        assert names == sorted(p.name for p in (out / "ann_dir" / split).iterdir()) and names
        for name in names:
            frame, camera = int(name[:6]), name[7:-4]
            with Image.open(out / "ann_dir" / split / name) as im:
                assert im.mode == "L"
                ann = np.array(im)
            assert set(np.unique(ann).tolist()) <= {0, 1, 2, 255}
            labels = _png(root / camera / "labels" / f"{frame:06d}.png")
            want = np.full(labels.shape, 255)
            for i, n in enumerate(meta["classes"]):
                want[labels == CLASSES.index(n)] = i
            assert np.array_equal(ann, want)
            seen += 1
    assert seen == FRAMES * len(CAMERAS)


def test_cityscapes_conventions(root, tmp_path):
    """``export cityscapes`` against cityscapesscripts: file names parse with its
    ``getCsFileInfo``; the label ids, names and colours written are its table's; labelIds are
    the dataset's labels mapped (outside the valid area: out of roi); instanceIds are labelId
    * 1000 + k on each object's pixels (k from 0 per class) and the labelId elsewhere; the
    polygons load with its ``Annotation`` and its ``json2labelImg`` draws them back into the
    labelIds (all but at most 0.1 % of the pixels)."""
    pytest.importorskip("cityscapesscripts")
    from cityscapesscripts.helpers.annotation import Annotation
    from cityscapesscripts.helpers.csHelpers import getCsFileInfo
    from cityscapesscripts.helpers.labels import id2label, name2label
    from cityscapesscripts.preparation.json2labelImg import createLabelImage

    from omniscape_torch.data.export.cityscapes import CITYSCAPES_IDS, CITYSCAPES_LABELS

    for k, (name, colour) in CITYSCAPES_LABELS.items():
        assert id2label[k].name == name and tuple(id2label[k].color) == colour
    assert name2label["car"].id == CITYSCAPES_IDS["Vehicle"] and name2label["car"].hasInstances
    assert name2label["person"].id == CITYSCAPES_IDS["Pedestrian"]
    out = tmp_path / "cityscapes"
    export_dataset("cityscapes", root, out, val_fraction=0.5)
    files = sorted((out / "gtFine").rglob("*_gtFine_labelIds.png"))
    assert len(files) == FRAMES * len(CAMERAS)
    drawn = wrong = 0
    for path in files:
        info = getCsFileInfo(str(path))
        assert (info.type, info.type2, info.ext) == ("gtFine", "labelIds", "png")
        camera, frame = info.city.replace("-", "_"), int(info.frameNb)
        assert camera in CAMERAS and info.sequenceNb == "000000"
        split = path.parent.parent.name
        image = out / "leftImg8bit" / split / info.city / \
            f"{info.city}_{info.sequenceNb}_{info.frameNb}_leftImg8bit.png"
        assert image.read_bytes() == (root / camera / "rgb" / f"{frame:06d}.png").read_bytes()
        ids = _png(path)
        labels = _png(root / camera / "labels" / f"{frame:06d}.png")
        want = np.where(labels == 255, name2label["out of roi"].id, 0)
        for n, cid in CITYSCAPES_IDS.items():
            want[labels == CLASSES.index(n)] = cid
        assert np.array_equal(ids, want)
        inst = _png(str(path).replace("labelIds", "instanceIds"))
        assert inst.dtype == np.uint16
        source = _png(root / camera / "instances" / f"{frame:06d}.png")
        assert np.array_equal(inst[source == 0], ids[source == 0])
        per_class = {}
        for o in _objects(root, camera, frame):
            values = np.unique(inst[source == o["instance_id"]])
            assert values.size == 1 and values[0] // 1000 == want[source == o["instance_id"]][0]
            per_class.setdefault(int(values[0]) // 1000, []).append(int(values[0]) % 1000)
        for ks in per_class.values():
            assert sorted(ks) == list(range(len(ks)))
        colour = _png(str(path).replace("labelIds", "color"))
        assert np.array_equal(colour, np.array([id2label[int(i)].color for i in ids.reshape(-1)],
                                               np.uint8).reshape(*ids.shape, 3))
        annotation = Annotation()
        annotation.fromJsonFile(str(path).replace("labelIds.png", "polygons.json"))
        assert (annotation.imgHeight, annotation.imgWidth) == ids.shape
        back = np.array(createLabelImage(annotation, "ids"))
        drawn += back.size
        wrong += int((back != ids).sum())
    assert wrong <= 0.001 * drawn


def test_yolo_format(root, tmp_path):
    """``export yolo``: data.yaml (path, train, val, nc, names) and one ``class cx cy w h``
    line per object, normalised; parsed back, the boxes are the dataset's within 1e-6 px and
    the classes its classes' positions in ``names``."""
    import yaml

    out = tmp_path / "yolo"
    export_dataset("yolo", root, out, classes=["Vehicle", "Pole"], val_fraction=0.5)
    data = yaml.safe_load((out / "data.yaml").read_text())
    assert data["names"] == {0: "Vehicle", 1: "Pole"} and data["nc"] == 2
    assert (out / data["train"]).is_dir() and (out / data["val"]).is_dir()
    h, w = SIZE
    compared = 0
    for split in ("train", "val"):
        for image in sorted((out / "images" / split).iterdir()):
            frame, camera = int(image.stem[:6]), image.stem[7:]
            lines = (out / "labels" / split / f"{image.stem}.txt").read_text().splitlines()
            rows = [line.split() for line in lines]
            assert all(len(r) == 5 for r in rows)
            got = [(int(r[0]), *map(float, r[1:])) for r in rows]
            want = [o for o in _objects(root, camera, frame) if o["class"] in ("Vehicle", "Pole")]
            assert len(got) == len(want)
            for (c, cx, cy, bw, bh), o in zip(got, want, strict=True):
                assert data["names"][c] == o["class"]
                box = [(cx - bw / 2) * w, (cy - bh / 2) * h, (cx + bw / 2) * w, (cy + bh / 2) * h]
                assert max(abs(a - b) for a, b in zip(box, o["box"])) < 1e-6
                compared += 1
    assert compared > 0


def test_split_by_frame_rerun_and_settings(root, tmp_path):
    """The split is by frame (every camera of a frame in one split), the same for the same
    seed; an interrupted export (files missing, ``finished`` false) is completed by the same
    call into the same bytes; other settings into the folder are refused, naming them."""
    assert split_frames(range(10), 0.3, seed=4) == split_frames(list(range(10))[::-1], 0.3, 4)
    assert len(split_frames(range(10), 0.3, 4)) == 3
    assert len(split_frames(range(2), 0.1)) == 1 and split_frames(range(5), 0.0) == set()
    assert len({frozenset(split_frames(range(20), 0.5, s)) for s in range(4)}) > 1
    with pytest.raises(ValueError, match="val_fraction"):
        split_frames(range(3), 1.0)
    out = tmp_path / "yolo"
    export_dataset("yolo", root, out, val_fraction=0.5, seed=1)
    for split in ("train", "val"):
        frames = {p.stem[:6] for p in (out / "images" / split).iterdir()}
        assert len(frames) == 1 and len(list((out / "images" / split).iterdir())) == 2
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()
              and p.name != ".lock"}
    settings = json.loads((out / "export.json").read_text())
    assert settings["finished"] is True
    # interrupted: some files never written, the settings file not yet finished
    victims = sorted(out.rglob("*.txt"))[:2] + [out / "data.yaml"]
    for v in victims:
        v.unlink()
    settings["finished"] = False
    (out / "export.json").write_text(json.dumps(settings))
    export_dataset("yolo", root, out, val_fraction=0.5, seed=1)
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()
             and p.name != ".lock"}
    assert after == before
    with pytest.raises(ValueError, match=r"seed: the folder has 1, this run 2"):
        export_dataset("yolo", root, out, val_fraction=0.5, seed=2)
    with pytest.raises(ValueError, match="classes: Road: no objects"):
        export_dataset("coco", root, tmp_path / "c", classes=["Road"])
    with pytest.raises(ValueError, match="classes"):
        export_dataset("mmseg", root, tmp_path / "m", classes=["Sky"])
    with pytest.raises(ValueError, match="format"):
        export_dataset("voc", root, tmp_path / "v")
    with pytest.raises(ValueError, match="inside the dataset"):
        export_dataset("yolo", root, root / "yolo")


def test_export_samples_from_the_augmentation(tmp_path):
    """A stream of the augmentation's outputs (batched dicts), exported: COCO's masks decode
    to each output instance map and score AP 1 against themselves; boxes alone (outline mode,
    ``box_labels`` through ``box_index``) give YOLO lines equal to the output boxes;
    keypoints of an object go to its annotation; mmseg needs labels."""
    from pycocotools import mask as mask_api
    from pycocotools.coco import COCO

    aug = ot.augment.RandomReproject((40, 40), source_fov=math.radians(90), seed=0)
    images = torch.rand(2, 3, 30, 40)
    instances = torch.zeros(2, 30, 40, dtype=torch.int64)
    instances[:, 5:20, 5:25] = 300
    instances[:, 18:28, 22:38] = 70
    labels = torch.where(instances == 300, 10, torch.where(instances == 70, 4, 7))
    boxes = [torch.tensor([[5.0, 5.0, 25.0, 20.0], [22.0, 18.0, 38.0, 28.0]])] * 2
    exact = aug({"rgb": images, "labels": labels, "instances": instances,
                 "box_instance_ids": [torch.tensor([300, 70])] * 2})
    stream = [dict(exact, keypoints=torch.tensor([[[10.0, 10.0]], [[math.nan, 0.0]]]).expand(
        2, 2, 1, 2).clone(), box_instance_ids=[torch.tensor([300, 70])] * 2)]
    out = tmp_path / "coco"
    result = export_samples("coco", stream, out, val_fraction=0.0)
    assert result["images"] == {"train": 2, "val": 0}
    gt = _quiet(COCO, str(out / "annotations" / "instances_train.json"))
    for image in gt.dataset["images"]:
        ids = exact["instances"][image["id"] - 1].numpy()
        rebuilt = np.zeros_like(ids)
        for a in gt.loadAnns(gt.getAnnIds(imgIds=[image["id"]])):
            rebuilt[mask_api.decode(a["segmentation"]).astype(bool)] = a["instance_id"]
            assert a["category_id"] == (10 if a["instance_id"] == 300 else 4)
            kp = a.get("keypoints")
            if a["instance_id"] == 300:   # the keypoint given for it, visible
                assert kp[2] == 2 and a["num_keypoints"] == 1
            else:                          # a NaN keypoint: not labelled
                assert kp == [0.0, 0.0, 0] and a["num_keypoints"] == 0
        assert np.array_equal(rebuilt, ids)
    outline = aug({"rgb": images, "boxes": boxes}, params=exact["params"])
    yolo = tmp_path / "yolo"
    export_samples("yolo", [dict(outline, box_labels=[torch.tensor([10, 4])] * 2)], yolo,
                   val_fraction=0.0)
    for b in range(2):
        rows = [list(map(float, line.split())) for line in
                (yolo / "labels" / "train" / f"{b:06d}.txt").read_text().splitlines()]
        kept = outline["box_index"][b].tolist()
        # the instance classes' positions: Pedestrian 0, Pole 1, Vehicle 2, TrafficSign 3
        assert [int(r[0]) for r in rows] == [[2, 0][i] for i in kept]
        for r, box in zip(rows, outline["boxes"][b].tolist(), strict=True):
            got = [(r[1] - r[3] / 2) * 40, (r[2] - r[4] / 2) * 40, (r[1] + r[3] / 2) * 40,
                   (r[2] + r[4] / 2) * 40]
            assert max(abs(x - y) for x, y in zip(got, box)) < 1e-6
    # a batch-wide split (or frame) applies to each of its images
    seg = export_samples("mmseg", [dict(exact, split="val")], tmp_path / "mv")
    assert seg["images"] == {"train": 0, "val": 2}
    with pytest.raises(ValueError, match="labels"):
        export_samples("mmseg", [{"rgb": images[0]}], tmp_path / "m")
    with pytest.raises(ValueError, match="box_labels"):
        export_samples("yolo", [{"rgb": images[0], "boxes": boxes[0]}], tmp_path / "y2")


def test_without_opencv_only_cityscapes_needs_it(root, tmp_path, capsys, monkeypatch):
    """Without OpenCV: ``export cityscapes`` is one line naming the install, exit 1, nothing
    written; the other exports run."""
    monkeypatch.setitem(sys.modules, "cv2", None)
    assert cli.main(["export", "cityscapes", str(root), "--out", str(tmp_path / "cs")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install opencv" in err[0]
    assert not (tmp_path / "cs").exists()
    for f in ("coco", "mmseg", "yolo"):
        assert cli.main(["export", f, str(root), "--out", str(tmp_path / f),
                         "--no-progress"]) == 0


def test_cli_export(root, tmp_path, capsys):
    """``omniscape-torch export``: its formats are the package's; it writes and says what;
    bad input is one line and exit 2."""
    assert cli.EXPORT_FORMATS == FORMATS
    out = tmp_path / "mmseg"
    assert cli.main(["export", "mmseg", str(root), "--out", str(out), "--classes",
                     "Road,Vehicle", "--no-progress"]) == 0
    assert "as mmseg to" in capsys.readouterr().out
    assert json.loads((out / "metainfo.json").read_text())["classes"] == ["Road", "Vehicle"]
    assert cli.main(["export", "coco", str(root), "--out", str(tmp_path / "c"), "--classes",
                     "Sky"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "classes" in err[0]
    copy = tmp_path / "old"
    shutil.copytree(root, copy)
    for c in CAMERAS:
        shutil.rmtree(copy / c / "instances")
    assert cli.main(["export", "yolo", str(copy), "--out", str(tmp_path / "y")]) == 2
    assert "instance maps" in capsys.readouterr().err
