"""Statistics of a generated dataset (``omniscape-torch stats``): the paper's Table I (vehicle
attitude) and the per-class pixel share of the fisheye and catadioptric images, over the
finished frames."""

from __future__ import annotations

import io as _io
import json
from pathlib import Path

import numpy as np
import torch

from ..io import CLASSES, atomic_write_bytes, atomic_write_text, read_image
from ..scenes import ride as _ride
from . import format as fmt
from .integrity import damaged_files
from .readers import has_modality, list_cameras, read_dynamics

__all__ = ["PLOT_INSTALL", "SKY_NOTE", "format_stats", "plot_available", "stats"]

#: What installs the chart's library (matplotlib, optional: the ``plot`` extra).
PLOT_INSTALL = 'pip install "omniscape_torch[plot]"'


def plot_available() -> bool:
    """Whether ``stats.png`` can be drawn: matplotlib is importable (an optional dependency)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def stats(root: str | Path, *, plot: bool = True) -> dict:
    """Table I (yaw, pitch, roll over the ride) and the per-class pixel share (valid pixels)
    of the fisheye and catadioptric images of the dataset in ``root``, over its finished
    frames (``.done`` marker and every camera's files; an interrupted run's dataset has fewer
    than planned); writes ``root/stats.json`` and (``plot``) the bar chart ``root/stats.png``
    (``plot`` needs matplotlib, an optional dependency: `plot_available`).

    Returns:
        ``{"table_one": {angle: {mean, std, min, median, max}}, "class_share": {kind:
        {class: share}}, "pixels": {kind: valid pixel count}, "frames": finished frames,
        "frames_planned": N, "skipped": {"NNNNNN": [the files it lacks, relative paths]},
        "damaged": {"NNNNNN": {file: what is wrong}}}``: a frame without its ``.done`` marker
        is not finished; one with it but without a file lost that file; one with a damaged
        file (cut short, or not decoding: `integrity.damaged_files`) is left out and named
        (``generate`` renders it again). Where the dataset has ``objects`` (written since
        ``generate`` writes them), also ``"objects": {kind: {"images": N, "per_image": mean
        number of objects in an image, "classes": {class: objects}}}`` over the same frames.

    Raises:
        FileNotFoundError: ``root`` holds no dataset.
        ValueError: no frame is finished (and whole) yet.
        ImportError: ``plot`` without matplotlib (``stats.json`` is written first).
    """
    root = Path(root)
    if not (root / fmt.MANIFEST).is_file():
        raise FileNotFoundError(f"{root}: no {fmt.MANIFEST} (not a dataset written by "
                                f"'omniscape-torch generate')")
    cameras = list_cameras(root)
    recs = read_dynamics(root)
    done = set(fmt.finished_frames(root, cameras))
    # each frame left out, and the file it lacks (the marker: not finished; else a file lost)
    skipped = {k: fmt.missing_files(root, cameras, k) for k in sorted(recs) if k not in done}
    modalities = [m for m in fmt.MODALITIES
                  if m in fmt.CORE_MODALITIES or has_modality(root, m, cameras)]
    # a finished frame with a damaged file (cut short by a copy, say) is named and left out
    damaged = {}
    counts = {name.split("_")[0]: np.zeros(len(CLASSES), dtype=np.int64) for name in cameras}
    finished = []
    for k in sorted(recs):
        if k not in done:
            continue
        bad = damaged_files(root, [fmt.frame_file(c, m, k) for c in cameras for m in modalities])
        frame_counts = {} if bad else _class_counts(root, cameras, k, bad)
        if bad:   # cut short, or (found by _class_counts) not decoding
            damaged[k] = bad
            continue
        for name, v in frame_counts.items():
            counts[name.split("_")[0]] += v
        finished.append(recs[k])
    if not finished:
        if damaged:
            k, bad = next(iter(damaged.items()))
            raise ValueError(f"{root}: each of its finished frames has a damaged file (frame "
                             f"{fmt.frame_name(k)}: {_damage(bad)}); run 'omniscape-torch "
                             f"generate' with the same options to render them again")
        raise ValueError(f"{root}: none of its {len(recs)} frames is finished yet; run "
                         f"'omniscape-torch generate' with the same options to finish them")
    rotation = torch.tensor([[r["rotation"]["roll"], r["rotation"]["pitch"],
                              r["rotation"]["yaw"]] for r in finished], dtype=torch.float64)
    table = _ride.table_one(rotation)
    share = {kind: {c: (float(v[i]) / float(v.sum()) if v.sum() else 0.0)
                    for i, c in enumerate(CLASSES)} for kind, v in counts.items()}
    result = {"frames": len(finished), "frames_planned": len(recs), "table_one": table,
              "class_share": share, "pixels": {kind: int(v.sum()) for kind, v in counts.items()},
              "skipped": {fmt.frame_name(k): files for k, files in skipped.items()},
              "damaged": {fmt.frame_name(k): bad for k, bad in damaged.items()}}
    if "objects" in modalities:
        result["objects"] = _objects(root, cameras, [r["frame"] for r in finished])
    atomic_write_text(root / fmt.STATS, json.dumps(result, indent=2) + "\n")
    if plot:
        _plot(result, root / fmt.STATS_PLOT)
    return result


def _class_counts(root: Path, cameras: list[str], k: int, bad: dict) -> dict:
    """Per camera, the valid pixels of each class at frame ``k``; a file that does not decode
    (damaged inside, past what `damaged_files` looks at) is added to ``bad`` with the reason,
    and nothing is returned for the frame."""
    out = {}
    for name in cameras:
        images = {}
        for m in ("labels", "valid"):
            file = fmt.frame_file(name, m, k)
            try:
                images[m] = read_image(root / file).numpy()
            except (ValueError, OSError):
                bad[file] = "cannot be decoded"
                return {}
        labels, valid = images["labels"], images["valid"] > 0
        ids = labels[valid & (labels < len(CLASSES))]
        out[name] = np.bincount(ids.astype(np.int64), minlength=len(CLASSES))
    return out


def _objects(root: Path, cameras: list[str], frames: list[int]) -> dict:
    """Per kind of camera: the mean number of objects an image holds, and the objects of
    each class (the classes with any), over ``frames``."""
    out: dict[str, dict] = {}
    for name in cameras:
        entry = out.setdefault(name.split("_")[0], {"images": 0, "classes": {}})
        for k in frames:
            objects = json.loads((root / fmt.frame_file(name, "objects", k)).read_text(
                encoding="utf-8"))
            entry["images"] += 1
            for o in objects:
                entry["classes"][o["class"]] = entry["classes"].get(o["class"], 0) + 1
    return {kind: {"images": e["images"],
                   "per_image": sum(e["classes"].values()) / max(1, e["images"]),
                   "classes": dict(sorted(e["classes"].items()))} for kind, e in out.items()}


def _plot(result: dict, path: Path) -> None:
    try:
        import matplotlib
    except ImportError:
        raise ImportError(f"{path.name} needs matplotlib: {PLOT_INSTALL}") from None
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.5), layout="constrained")
    ax0, ax1 = fig.subplots(1, 2, width_ratios=(3, 1))
    kinds = list(result["class_share"])
    x = np.arange(len(CLASSES))
    width = 0.8 / max(1, len(kinds))
    for i, kind in enumerate(kinds):
        values = [100 * result["class_share"][kind][c] for c in CLASSES]
        ax0.bar(x + (i - (len(kinds) - 1) / 2) * width, values, width, label=kind)
    ax0.set_xticks(x, CLASSES, rotation=60, ha="right")
    ax0.set_ylabel("share of valid pixels (%)")
    ax0.set_title("class share")
    if kinds:
        ax0.legend()
    names = ("yaw", "pitch", "roll")
    table = result["table_one"]
    ax1.bar(names, [table[n]["mean"] for n in names],
            yerr=[table[n]["std"] for n in names], capsize=4, color="grey")
    ax1.scatter(names, [table[n]["min"] for n in names], marker="v", color="k", label="min")
    ax1.scatter(names, [table[n]["max"] for n in names], marker="^", color="k", label="max")
    ax1.set_ylabel("degrees")
    ax1.set_title("attitude (mean, std)")
    ax1.legend()
    buf = _io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    atomic_write_bytes(path, buf.getvalue())


#: Under the class shares: what ``Unlabeled`` counts.
SKY_NOTE = ("Unlabeled (class 0) is the sky: the 13 CARLA classes the dataset uses (as the "
            "OmniScape dataset does) have no sky class; nothing else in the built-in town is "
            "unlabeled")

#: Skipped frames named one a line before the tables (the others counted).
SHOWN_SKIPPED = 5


def _damage(bad: dict[str, str]) -> str:
    """A damaged frame's first damaged file and what is wrong with it, in words."""
    file, why = next(iter(bad.items()))
    return f"{file} is damaged: {why}" + (f" (and {len(bad) - 1} more file(s))"
                                          if len(bad) > 1 else "")


def _lacks(files: list[str]) -> str:
    """What a skipped frame lacks, in words."""
    if files and files[0].startswith(fmt.DONE + "/"):
        return (f"not finished (no {files[0]}"
                + (f"; missing {files[1]}" + (f" and {len(files) - 2} more file(s)"
                                              if len(files) > 2 else "") if len(files) > 1
                   else "") + ")")
    return (f"missing {files[0]}" + (f" and {len(files) - 1} more file(s)" if len(files) > 1
                                     else "") + " (its marker is there: the file was lost; "
            "run generate again to render the frame anew)") if files else "unreadable"


def format_stats(result: dict) -> str:
    """The text ``omniscape-torch stats`` prints."""
    done, planned = result["frames"], result.get("frames_planned", result["frames"])
    over = f"{done} frames" if done == planned else (
        f"the {done} finished of {planned} frames; run generate again to finish the others")
    lines = []
    reasons = {name: _lacks(files) for name, files in (result.get("skipped") or {}).items()}
    reasons.update({name: f"{_damage(bad)}; run generate again to render the frame anew"
                    for name, bad in (result.get("damaged") or {}).items()})
    for i, name in enumerate(sorted(reasons)):
        if i == SHOWN_SKIPPED:
            lines.append(f"skipped {len(reasons) - i} more unfinished or damaged frame(s) "
                         f"(stats.json lists them)")
            break
        lines.append(f"skipped frame {name}: {reasons[name]}")
    lines += [f"Table I: vehicle attitude over {over} (degrees)",
             f"{'':8}{'mean':>10}{'std':>10}{'min':>10}{'median':>10}{'max':>10}"]
    for name in ("yaw", "pitch", "roll"):
        row = result["table_one"][name]
        lines.append(f"{name:8}" + "".join(f"{row[k]:10.3f}" for k in
                                           ("mean", "std", "min", "median", "max")))
    kinds = list(result["class_share"])
    lines.append("")
    lines.append("class share of valid pixels (%)")
    lines.append(f"{'class':14}" + "".join(f"{k:>14}" for k in kinds))
    for c in CLASSES:
        lines.append(f"{c:14}" + "".join(f"{100 * result['class_share'][k][c]:14.2f}"
                                         for k in kinds))
    lines.append(f"{'valid pixels':14}" + "".join(f"{result['pixels'][k]:14d}" for k in kinds))
    lines.append(SKY_NOTE)
    objects = result.get("objects")
    if objects:
        kinds = list(objects)
        lines += ["", "objects (instances) per image",
                  f"{'class':14}" + "".join(f"{k:>14}" for k in kinds)]
        for c in sorted({c for k in kinds for c in objects[k]["classes"]}):
            lines.append(f"{c:14}" + "".join(
                f"{objects[k]['classes'].get(c, 0) / max(1, objects[k]['images']):14.2f}"
                for k in kinds))
        lines.append(f"{'all':14}" + "".join(f"{objects[k]['per_image']:14.2f}" for k in kinds))
    return "\n".join(lines)
