"""WebDataset shards of a generated dataset, to stream into training from anywhere.

``omniscape-torch generate --format webdataset`` (each task packs the shard of the frames it
rendered) and ``omniscape-torch pack DIR`` (a folder written before) write, beside the
folder's files (which stay: the ``.done`` markers are the resume mechanism, and ``stats``
reads them)::

    DIR/shards/index.json          frames per shard S, the frames of each shard, the cameras
    DIR/shards/shard-NNNNNN.tar    frames NNNNNN * S .. (NNNNNN + 1) * S - 1 (fewer in the last)

A shard holds one sample per frame and camera, frame-major, cameras in the dataset's order;
sample ``KEY = NNNNNN_<camera>`` (frame number and camera name) is the files::

    KEY.camera.json     {"frame", "camera", "weather", "intrinsics": <camera>/camera.json,
                         "T_rig_camera": 4 x 4, "T_world_camera": 4 x 4 at this frame}
    KEY.dynamics.json   the frame's record of dynamics.json (CARLA names and units)
    KEY.rgb.png  KEY.depth.exr  KEY.labels.png  KEY.valid.png   the folder's files, byte for byte
    KEY.instances.npy   where the dataset has instances: the ids of instances/NNNNNN.png as
                        a uint16 .npy array, which webdataset's default decode() reads
                        exactly (its image decoders clip a 16-bit PNG to 8 bits); shards
                        packed before hold KEY.instances.png, read all the same
    KEY.objects.json    where the dataset has it, byte for byte

``index.json`` lists the files of a sample (``sample.files``), those of the optional
modalities included where the shards hold them.

A shard is written to a temporary name and renamed (a retried or resumed task never leaves a
partial shard), with fixed tar headers (time 0, owner 0, mode 0644): its bytes depend on the
dataset's files only, so a shard packed by a Ray task equals one packed by ``pack``.
`omniscape_torch.data.datasets.OmniShardDataset` reads shards (with ``webdataset``)
into the items `OmniDataset` reads from the folder.
"""

from __future__ import annotations

import io as _io
import json
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from ..io.atomic import atomic_path, atomic_write_text, folder_lock
from ..io.labels import colorize
from . import format as fmt
from .objects import decode_instances, decode_objects, instance_npy
from .readers import list_frames, read_camera_dict, read_dynamics, read_extrinsics, read_manifest

__all__ = ["FRAMES_PER_SHARD", "OPTIONAL_SAMPLE_MODALITIES", "SAMPLE_MODALITIES",
           "SHARD_FILES", "check_frames_per_shard", "decode_sample", "pack",
           "resolve_frames_per_shard", "sample_modalities", "shard_groups", "shard_urls",
           "write_index", "write_shard"]

#: Frames per shard by default: 64 samples with the rig's four cameras (about 40 MB at
#: 512 x 512), within WebDataset's advice of shards from tens of MB up.
FRAMES_PER_SHARD = 16

#: The images a sample holds, from the folder's files (``labels_color`` is left out: it is
#: the labels in the palette, `decode_sample` draws it when asked).
SAMPLE_MODALITIES = ("rgb", "depth", "labels", "valid")
#: The images a sample holds besides, where the dataset has them (`sample_modalities`):
#: not in a dataset written before ``generate`` wrote instances.
OPTIONAL_SAMPLE_MODALITIES = fmt.OPTIONAL_MODALITIES
#: The extension of each modality's member in a sample, where it is not the folder's:
#: instance ids as a ``.npy`` array (module docstring).
SHARD_FILES = {**fmt.MODALITIES, "instances": "npy"}

INDEX_FORMAT = "omniscape_torch webdataset shards"


def check_frames_per_shard(frames_per_shard) -> int:
    """``frames_per_shard`` as an int >= 1.

    Raises:
        ValueError: anything else, naming ``frames_per_shard``.
    """
    if isinstance(frames_per_shard, bool) or not isinstance(frames_per_shard, int) or \
            frames_per_shard < 1:
        raise ValueError(f"frames_per_shard: expected a positive integer, got "
                         f"{frames_per_shard!r}")
    return frames_per_shard


def resolve_frames_per_shard(root: str | Path, frames_per_shard: int | None) -> int:
    """``frames_per_shard``, or for None the one of the shards in ``root`` (its index), else
    `FRAMES_PER_SHARD`."""
    if frames_per_shard is not None:
        return check_frames_per_shard(frames_per_shard)
    try:
        index = json.loads((Path(root) / fmt.SHARD_INDEX).read_text(encoding="utf-8"))
        return check_frames_per_shard(index["frames_per_shard"])
    except (OSError, ValueError, KeyError, TypeError):
        return FRAMES_PER_SHARD


def shard_groups(frames: int, frames_per_shard: int) -> list[list[int]]:
    """The frames of each shard of a dataset of ``frames`` frames: ``[[0, .., S - 1], [S, ..],
    ...]``, the last one shorter."""
    s = check_frames_per_shard(frames_per_shard)
    return [list(range(i, min(i + s, frames))) for i in range(0, frames, s)]


def sample_modalities(root: str | Path, cameras: Sequence[str]) -> tuple[str, ...]:
    """The modalities a sample of the dataset in ``root`` holds: `SAMPLE_MODALITIES`,
    and each optional one (instances, objects) that the folder has for every camera, or,
    for a camera with no frame written yet (a run about to write them), that the manifest's
    layout lists."""
    root = Path(root)
    try:
        layout = read_manifest(root).get("layout", {})
    except FileNotFoundError:
        layout = {}

    def holds(m: str, camera: str) -> bool:
        if (root / camera / m).is_dir():
            return True
        return not (root / camera / "rgb").is_dir() and \
            f"<camera>/{m}/NNNNNN.{fmt.MODALITIES[m]}" in layout

    return SAMPLE_MODALITIES + tuple(m for m in OPTIONAL_SAMPLE_MODALITIES
                                     if cameras and all(holds(m, c) for c in cameras))


def write_index(root: str | Path, frames: int, cameras: Sequence[str],
                frames_per_shard: int) -> dict:
    """Write ``shards/index.json`` (unless it holds the same already) and return it: frames
    per shard, the cameras, the files of a sample (`sample_modalities`) and each
    shard's frames.

    Raises:
        ValueError: the folder holds shards of another ``frames_per_shard`` (or frames, or
            cameras): their frames would not be those the index names.
    """
    root = Path(root)
    groups = shard_groups(frames, frames_per_shard)
    index = {"format": INDEX_FORMAT, "frames_per_shard": frames_per_shard, "frames": frames,
             "cameras": list(cameras),
             "sample": {"key": "NNNNNN_<camera>",
                        "files": ["camera.json", "dynamics.json"]
                        + [f"{m}.{SHARD_FILES[m]}" for m in sample_modalities(root, cameras)]},
             "shards": [{"file": Path(fmt.shard_file(i)).name, "frames": [g[0], g[-1]],
                         "samples": len(g) * len(cameras)} for i, g in enumerate(groups)]}
    text = json.dumps(index, indent=2) + "\n"
    path = root / fmt.SHARD_INDEX
    try:
        old = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        old = None
    if old == text:
        return index
    if old is not None:
        try:
            was = json.loads(old)
        except ValueError:
            was = {}
        same = all(was.get(k) == index[k] for k in ("frames_per_shard", "frames", "cameras"))
        # only the sample's files differ (shards packed before the index listed instances):
        # the index is rewritten, and the reader reads the shards of both
        if not same and any((root / fmt.SHARDS).glob("shard-*.tar")):
            raise ValueError(
                f"frames_per_shard: {path} holds shards of {was.get('frames_per_shard')} "
                f"frames (of {was.get('frames')} frames, cameras {was.get('cameras')}), not "
                f"{frames_per_shard}; pass that, or remove {root / fmt.SHARDS}")
    atomic_write_text(path, text)
    return index


def _tar_member(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    info.mtime = 0
    info.mode = 0o644
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    tar.addfile(info, _io.BytesIO(data))


def _dumps(obj) -> bytes:
    return (json.dumps(obj) + "\n").encode("utf-8")


def write_shard(root: str | Path, index: int, frames: Sequence[int],
                cameras: Sequence[str]) -> Path:
    """Pack ``frames`` of ``cameras`` of the dataset in ``root`` into ``shards/shard-NNNNNN.tar``
    (``NNNNNN = index``), atomically. Returns the path.

    Raises:
        FileNotFoundError: a file of a frame is missing (names it).
    """
    root = Path(root)
    try:
        weather = read_manifest(root).get("weather_per_frame")
    except FileNotFoundError:
        weather = None
    dynamics = read_dynamics(root)
    intrinsics = {c: read_camera_dict(root, c) for c in cameras}
    extrinsics = {c: read_extrinsics(root, c) for c in cameras}
    modalities = sample_modalities(root, cameras)
    path = root / fmt.shard_file(index)
    with atomic_path(path, suffix=".tar") as tmp:
        with tarfile.open(tmp, "w", format=tarfile.USTAR_FORMAT) as tar:
            for k in frames:
                for c in cameras:
                    key = f"{fmt.frame_name(k)}_{c}"
                    meta = {"frame": k, "camera": c,
                            "weather": weather[k] if weather is not None and k < len(weather)
                            else None,
                            "intrinsics": intrinsics[c],
                            "T_rig_camera": extrinsics[c]["T_rig_camera"].tolist(),
                            "T_world_camera": extrinsics[c]["T_world_camera"][k].tolist()}
                    _tar_member(tar, f"{key}.camera.json", _dumps(meta))
                    _tar_member(tar, f"{key}.dynamics.json", _dumps(dynamics[k]))
                    for m in modalities:
                        file = root / fmt.frame_file(c, m, k)
                        if not file.is_file():
                            raise FileNotFoundError(f"{file}: missing (frame {k} is not "
                                                    "finished)")
                        data = file.read_bytes()
                        if m == "instances":
                            data = instance_npy(decode_instances(data, str(file)))
                        _tar_member(tar, f"{key}.{m}.{SHARD_FILES[m]}", data)
    return path


def pack(root: str | Path, frames_per_shard: int | None = None, *,
         progress: bool | None = None, log: Callable[[str], None] | None = None) -> dict:
    """Pack a dataset folder into WebDataset shards (``omniscape-torch pack DIR``).

    Writes ``shards/index.json`` and every shard whose frames are all finished and which is
    not written yet (a rerun after ``generate`` finished more frames writes the rest).
    ``frames_per_shard``: default, that of the shards there, else `FRAMES_PER_SHARD`.

    Returns:
        ``{"written": [shard files], "skipped": [already there], "incomplete": [shards with
        unfinished frames, not written]}`` (file names).

    Raises:
        FileNotFoundError: not a dataset folder.
        ValueError: ``frames_per_shard`` is not the one of the shards there.
        omniscape_torch.io.atomic.FolderBusyError: a run is writing the folder.
    """
    from tqdm import tqdm

    root = Path(root)
    log = log or (lambda msg: None)
    manifest = read_manifest(root)
    frames, cameras = int(manifest["frames"]), list(manifest["cameras"])
    result: dict[str, list[str]] = {"written": [], "skipped": [], "incomplete": []}
    with folder_lock(root):
        frames_per_shard = resolve_frames_per_shard(root, frames_per_shard)
        write_index(root, frames, cameras, frames_per_shard)
        finished = set(list_frames(root, cameras))
        groups = shard_groups(frames, frames_per_shard)
        if progress is None:
            progress = sys.stderr.isatty()
        for i, group in enumerate(tqdm(groups, disable=not progress, file=sys.stderr,
                                       unit="shard", desc="pack")):
            name = Path(fmt.shard_file(i)).name
            if (root / fmt.shard_file(i)).is_file():
                result["skipped"].append(name)
            elif all(k in finished for k in group):
                write_shard(root, i, group, cameras)
                result["written"].append(name)
            else:
                result["incomplete"].append(name)
    if result["incomplete"]:
        log(f"{len(result['incomplete'])} shard(s) hold unfinished frames and were not written; "
            "run generate again, then pack")
    return result


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

def shard_urls(source: str | Path | Sequence[str | Path]) -> list[str]:
    """The shards to read: a dataset folder (its ``shards/``) or a shard folder (those its
    ``index.json`` lists that exist: a run still writing some is read without them), a list of
    paths or URLs, or one WebDataset URL (braces expanded: ``shard-{000000..000009}.tar``,
    ``pipe:`` commands, ``http(s)://``, ...).

    Raises:
        FileNotFoundError: a folder without shards.
    """
    if isinstance(source, (list, tuple)):
        return [str(s) for s in source]
    path = Path(source)
    if path.is_dir():
        folder = path / fmt.SHARDS if (path / fmt.SHARDS).is_dir() else path
        index = folder / Path(fmt.SHARD_INDEX).name
        if index.is_file():
            names = [s["file"] for s in json.loads(index.read_text(encoding="utf-8"))["shards"]]
        else:
            names = sorted(p.name for p in folder.glob("shard-*.tar"))
        urls = [str(folder / n) for n in names if (folder / n).is_file()]
        if not urls:
            raise FileNotFoundError(f"{path}: no WebDataset shards (write them with "
                                    f"'omniscape-torch pack {path}' or generate --format "
                                    "webdataset)")
        return urls
    import braceexpand
    return list(braceexpand.braceexpand(str(source)))


def _png(data: bytes, name: str) -> Tensor:
    from ..io.images import decode_image

    return torch.from_numpy(decode_image(data, name))


def _exr_depth(data: bytes, name: str) -> Tensor:
    """Channel ``Z`` of an OpenEXR file's bytes, ``(H, W)`` float32."""
    import OpenEXR

    try:
        try:
            exr = OpenEXR.File(_io.BytesIO(data), separate_channels=True)
        except TypeError:   # OpenEXR before 3.4 reads files only
            with tempfile.NamedTemporaryFile(suffix=".exr") as f:
                f.write(data)
                f.flush()
                exr = OpenEXR.File(f.name, separate_channels=True)
        channels = exr.channels()
    except RuntimeError as err:
        raise ValueError(f"{name}: not a readable OpenEXR file ({err})") from None
    if "Z" not in channels:
        raise ValueError(f"{name}: no channel 'Z'; the file has {sorted(channels)}")
    return torch.from_numpy(np.array(channels["Z"].pixels, dtype=np.float32, copy=True))


def decode_sample(sample: dict, modalities: Sequence[str] = SAMPLE_MODALITIES, *,
                  rgb_uint8: bool = False) -> dict:
    """One WebDataset sample (``{"__key__": ..., "camera.json": bytes, ...}``) as the item
    `OmniDataset` gives for that frame and camera: the
    same keys, types and values (``labels_color`` drawn from the labels).

    Raises:
        ValueError: an unknown modality, or one the sample lacks (``instances``, ``objects``
            of shards of a dataset written before them; names the sample).
    """
    key = sample.get("__key__", "?")
    meta = json.loads(sample["camera.json"])
    item: dict = {"frame": int(meta["frame"]), "camera": meta["camera"]}
    labels = None
    for m in modalities:
        if m not in fmt.MODALITIES:
            raise ValueError(f"modalities: expected some of {tuple(fmt.MODALITIES)}, got {m!r}")
        name = f"{key}.{m}.{SHARD_FILES[m]}"
        if m == "labels_color":
            if labels is None:
                labels = _png(sample[f"labels.{fmt.MODALITIES['labels']}"], name).long()
            item[m] = torch.from_numpy(colorize(labels)).permute(2, 0, 1).contiguous()
            continue
        data = sample.get(f"{m}.{SHARD_FILES[m]}")
        if data is None:
            data = sample.get(f"{m}.{fmt.MODALITIES[m]}")   # instances.png: older shards
        if data is None:
            raise ValueError(f"{name}: not in the sample (shards of a dataset written before "
                             f"generate wrote {m}?)")
        if m == "objects":
            item.update(decode_objects(data, name))
        elif m == "depth":
            item[m] = _exr_depth(data, name)
        elif m == "rgb":
            rgb = _png(data, name).permute(2, 0, 1).contiguous()
            item[m] = rgb if rgb_uint8 else rgb.float() / 255.0
        elif m == "labels":
            labels = item[m] = _png(data, name).long()
        elif m == "instances":
            item[m] = decode_instances(data, name)
        else:   # valid: (1, H, W), as the folder's reader
            item[m] = (_png(data, name) > 0).unsqueeze(0)
    intr = meta["intrinsics"]
    item["model"] = intr["model"]
    item["intrinsics"] = torch.tensor(list(intr["params"].values()), dtype=torch.float64)
    item["image_size"] = torch.tensor(intr["image_size"], dtype=torch.int64)
    item["T_world_camera"] = torch.tensor(meta["T_world_camera"], dtype=torch.float64)
    item["T_rig_camera"] = torch.tensor(meta["T_rig_camera"], dtype=torch.float64)
    item["dynamics"] = json.loads(sample["dynamics.json"])
    if meta.get("weather") is not None:
        item["weather"] = meta["weather"]
    return item
