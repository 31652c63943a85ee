"""What a ``generate`` run finds in its folder, checked before it renders: a dataset of the
same settings (completed), of the same settings and fewer frames (extended: frame k depends
on the settings and k only, so the frames there are kept), or of other settings (refused,
naming each setting that differs); and finished frames with a damaged file (rendered again).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from . import format as fmt
from . import shards
from .integrity import damaged_files

__all__ = ["config_changes", "extend_shards", "folder_frames", "render_damaged_again"]


def _setting(key: str, value) -> str:
    """A configuration value as the command line writes it."""
    if value is None:
        return "the default"
    if isinstance(value, bool):
        return "on" if value else "off"
    if key == "image_size" and isinstance(value, (list, tuple)) and len(value) == 2:
        return str(value[0]) if value[0] == value[1] else f"{value[0]}x{value[1]}"
    if isinstance(value, (list, tuple)):
        return ",".join(map(str, value))
    return str(value)


def config_changes(old: object, new: dict) -> str:
    """``": --image-size: the folder has 512, this run 256; ..."``: each setting of ``new`` (a
    `DatasetConfig.to_dict`) that differs from a folder's ``old`` one, by its option
    name, with both values; ``""`` when ``old`` is not a configuration (unreadable)."""
    if not isinstance(old, dict):
        return ""
    changes = [f"--{key.replace('_', '-')}: the folder has "
               f"{_setting(key, old[key]) if key in old else 'none'}, this run "
               f"{_setting(key, new[key]) if key in new else 'none'}"
               for key in dict.fromkeys([*new, *old]) if old.get(key) != new.get(key)]
    return ": " + "; ".join(changes) if changes else ""


def folder_frames(out: Path, config) -> int | None:
    """The frames of the dataset in ``out`` (None: no dataset there yet), once checked that
    this run completes it (the same settings) or extends it (the same settings but more
    frames).

    Raises:
        ValueError: ``out`` holds a dataset of other settings, or of more frames; the
            message names each setting that differs, with both values.
    """
    manifest = out / fmt.MANIFEST
    if not manifest.is_file():
        return None
    try:
        old = json.loads(manifest.read_text(encoding="utf-8")).get("config")
    except (ValueError, AttributeError):
        old = None
    new = config.to_dict()
    if isinstance(old, dict):
        old.setdefault("antialias", 1)   # written before antialias existed: one ray a texel
        old.setdefault("min_object_pixels", 1)   # before it existed: every object listed
        old.setdefault("rig", "omniscape")   # before WoodScape's: the motorcycle's
        frames = old.get("frames")
        if isinstance(frames, int) and 0 < frames <= config.frames and \
                {**old, "frames": config.frames} == new:
            return frames
    more = (" (a larger --frames extends it)" if isinstance(old, dict)
            and old.get("frames") != new["frames"] else "")
    raise ValueError(f"{out} holds a dataset of another configuration ({manifest}"
                     f"{config_changes(old, new)}); rerun with the folder's settings{more} to "
                     f"complete it, or use another --out folder or remove it")


def extend_shards(out: Path, config) -> None:
    """A dataset grows to ``config.frames`` frames: its WebDataset shards whose frames change
    (the last one, when it was short) are removed, to be packed again with the new frames,
    and the shard index names the new shards (``pack`` and ``--format webdataset`` then
    write them)."""
    try:
        index = json.loads((out / fmt.SHARD_INDEX).read_text(encoding="utf-8"))
        size = shards.check_frames_per_shard(index["frames_per_shard"])
        listed = [entry["frames"] for entry in index["shards"]]
    except (OSError, ValueError, KeyError, TypeError):
        return   # no shards (or no index of them to keep)
    groups = shards.shard_groups(config.frames, size)
    for i, frames in enumerate(listed):
        if i >= len(groups) or frames != [groups[i][0], groups[i][-1]]:
            (out / fmt.shard_file(i)).unlink(missing_ok=True)
    (out / fmt.SHARD_INDEX).unlink()   # the index of fewer frames: rewritten
    shards.write_index(out, config.frames, config.cameras, size)


def render_damaged_again(plan, out: Path, frames: list[int],
                         log: Callable[[str], None]) -> None:
    """Check the files of the finished frames among ``frames`` (`damaged_files`:
    their structure, a few milliseconds a frame); a frame with a damaged file is named and
    made unfinished (its marker removed, and the WebDataset shard that holds it), so that the
    run renders it again."""
    size = (shards.resolve_frames_per_shard(out, None)
            if (out / fmt.SHARD_INDEX).is_file() else None)
    for k in frames:
        if not plan.finished(out, k):
            continue
        damaged = damaged_files(out, plan.files(k))
        if not damaged:
            continue
        file, why = next(iter(damaged.items()))
        more = f" (and {len(damaged) - 1} more file(s))" if len(damaged) > 1 else ""
        log(f"frame {fmt.frame_name(k)}: {file} is damaged: {why}{more}; rendering the frame "
            f"again")
        (out / fmt.marker(k)).unlink(missing_ok=True)
        if size is not None:
            (out / fmt.shard_file(k // size)).unlink(missing_ok=True)
