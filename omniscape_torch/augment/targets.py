"""The detection targets and declared label maps of the modules' dicts, and the helpers both
modules share to walk a batch in parts."""

from __future__ import annotations

import warnings
from typing import Mapping, NamedTuple

import torch
from torch import Tensor

from ..cameras import Camera
from ..cameras._checks import not_a_camera
from ..render.kernels.image import CameraGrid

#: The detection keys of the modules' dicts (beside rgb, labels, depth and the declared label
#: keys); a cubemap takes no boxes nor polygons (its boxes come from its instance ids).
_TARGET_KEYS = ("instances", "boxes", "box_instance_ids", "keypoints", "polygons",
                "polygon_box")
_BUILT_IN_KEYS = ("rgb", "labels", "depth", "valid", "params", "intrinsics", "source_camera",
                  "keypoints_valid", "box_index", "box_visible", "polygon_index",
                  *_TARGET_KEYS)


def _check_label_keys(label_keys: object) -> dict[str, int]:
    """``label_keys``: ``{key: ignore value}`` of the label-like keys a user declares."""
    if label_keys is None:
        return {}
    if not isinstance(label_keys, Mapping):
        raise TypeError(f"label_keys: expected a mapping {{key: ignore value}}, got "
                        f"{type(label_keys).__name__}")
    out = {}
    for key, ignore in label_keys.items():
        if not isinstance(key, str) or key in _BUILT_IN_KEYS:
            raise ValueError(f"label_keys: {key!r} is not a free key name (built in: "
                             f"{', '.join(_BUILT_IN_KEYS)})")
        if isinstance(ignore, bool) or not isinstance(ignore, int):
            raise TypeError(f"label_keys[{key!r}]: expected an int ignore value, got "
                            f"{ignore!r}")
        out[key] = int(ignore)
    return out


def _target_keys(label_keys: Mapping[str, int]) -> set[str]:
    return set(_TARGET_KEYS) | set(label_keys)


def _targets(inputs: object, label_keys: Mapping[str, int], cube: bool) -> dict:
    """The detection keys and declared label keys of a forward's dict, as ``render``'s
    arguments (``label_maps``: the declared keys' maps)."""
    if not isinstance(inputs, dict):
        return {}
    for key in ("boxes", "polygons", "polygon_box"):
        if cube and key in inputs:
            raise ValueError(f"{key}: a cubemap has no 2D boxes or polygons; pass instances "
                             f"(B, 6, F, F) and box_instance_ids: the boxes come from the "
                             f"output's instance ids")
    out = {key: inputs[key] for key in _TARGET_KEYS if key in inputs}
    maps = {key: inputs[key] for key in label_keys if key in inputs}
    if maps:
        out["label_maps"] = maps
    return out


def _unpack(inputs: dict, name: str, keys: tuple[str, ...], label_keys: Mapping[str, int],
            defaults: tuple, cube: bool) -> tuple:
    """The values of a forward's dict for ``keys`` (each else its default), refusing the keys
    neither those, the detection keys nor the declared label keys (listing the ones taken)."""
    accepted = set(keys) | _target_keys(label_keys)
    unknown = set(inputs) - accepted
    if unknown:
        taken = sorted(accepted - {"boxes"} if cube else accepted)
        raise ValueError(f"{name}: unknown keys {sorted(unknown)}; the keys taken are {taken} "
                         f"(declare more label maps with label_keys)")
    return tuple(inputs.get(key, default) for key, default in zip(keys, defaults))


def _reference(given: tuple, targets: dict, name: str) -> Tensor:
    """The first input of a forward (its batch and size), a ValueError where there is none."""
    maps = targets.get("label_maps", {}).values()
    ref = next((t for t in (*given, *maps, targets.get("instances")) if t is not None), None)
    if ref is None:
        raise ValueError(f"forward: pass at least one of {name}, labels, depth, instances")
    return ref


def _label_maps(label_keys: Mapping[str, int], instances: Tensor | None,
                label_maps: Mapping[str, Tensor] | None, cube: bool,
                size: tuple[int, int] | None = None) -> dict[str, tuple[Tensor, int]]:
    """``{key: (ids, ignore value)}`` of ``instances`` (ignore 0) and the declared label keys'
    maps, checked: integer ids ``(B, H, W)`` (a cube ``(B, 6, F, F)``), a channel of 1
    dropped, ``bool`` masks as ``uint8``; each of the images' ``size (H, W)`` (the first map's
    where None: the others must match it); instance ids ``>= 0``."""
    given = {} if label_maps is None else dict(label_maps)
    unknown = set(given) - set(label_keys)
    if unknown:
        raise ValueError(f"label_maps: keys {sorted(unknown)} are not declared (label_keys="
                         f"{dict(label_keys)})")
    maps = {}
    reference = "the cube's faces" if cube else "the images'"
    items = [("instances", instances, 0)] + [(k, given[k], label_keys[k]) for k in given]
    layout = "(B, 6, F, F)" if cube else "(B, H, W)"
    for key, ids, ignore in items:
        if ids is None:
            continue
        if not isinstance(ids, Tensor):
            raise TypeError(f"{key}: expected an integer tensor {layout}, got "
                            f"{type(ids).__name__}")
        ids = _plain(ids)
        if ids.dim() == len(layout.split(",")) + 1 and ids.shape[-3] == 1:
            ids = ids.squeeze(-3)
        if ids.is_floating_point() or ids.is_complex():
            raise ValueError(f"{key}: expected integer ids {layout}, got {ids.dtype}")
        if ids.dim() != len(layout.split(",")):
            stacked = " (B, N, 6, F, F)" if cube else " (B, N, H, W)"
            raise ValueError(f"{key}: expected integer ids {layout}, got {tuple(ids.shape)}; "
                             f"stacked masks{stacked} are not taken: merge them into one id "
                             f"map, e.g. (masks * torch.arange(1, N + 1).view(N, 1, 1)).amax(-3)"
                             f" (where masks overlap the larger id wins)")
        found = tuple(ids.shape[-2:])
        if size is None:   # no image: the first map sets the size
            size, reference = found, f"{key}'s"
        elif found != tuple(size):
            raise ValueError(f"{key}: {found[0]} x {found[1]} pixels per sample, expected "
                             f"{size[0]} x {size[1]} ({reference}, every sample); a label map "
                             f"is carried pixel for pixel with the image")
        if key == "instances" and ids.numel() and bool((ids < 0).any()):
            sample = int((ids < 0).flatten(1).any(-1).nonzero()[0, 0])
            raise ValueError(f"instances: negative ids (sample {sample}, min "
                             f"{int(ids[sample].min())}); instance ids are >= 0 (0: none)")
        maps[key] = (ids.to(torch.uint8) if ids.dtype == torch.bool else ids, ignore)
    return maps


def _check_batches(params: dict, **given: object) -> int:
    """The batch of the drawn ``params``; raises naming the first given detection input of
    another (``rgb``, ``labels`` and ``depth`` are checked where they are rendered)."""
    batch = len(params["model"])
    for key, value in given.items():
        if value is None:
            continue
        n = len(value) if not isinstance(value, Tensor) or value.dim() > 0 else 0
        if n != batch:
            raise ValueError(f"{key}: {n} samples, the batch (params) has {batch}")
    return batch


def _render_label_maps(result: dict, maps: dict[str, tuple[Tensor, int]], render_one) -> None:
    """Each label map through ``render_one(ids) -> dict`` (one labels pass: nearest, exact ids
    of any range) into ``result[key]``, its own ignore value outside the valid area; ``valid``
    and ``params`` from the first pass where ``result`` has none."""
    for key, (ids, ignore) in maps.items():
        out = render_one(ids)
        result[key] = out["labels"].masked_fill_(~out["valid"][:, 0], ignore)
        result.setdefault("valid", out["valid"])
        result.setdefault("params", out["params"])


def _source_size(image: Tensor | None, labels: Tensor | None, depth: Tensor | None,
                 channels_last: bool) -> tuple[int, int] | None:
    """``(Hs, Ws)`` of a perspective batch: its image's, labels' or depth's (the maps must
    match it: `_label_maps`), None without any of them."""
    if image is not None and isinstance(image, Tensor) and image.dim() >= 3:
        return tuple(image.shape[1:3] if channels_last else image.shape[-2:])
    for t in (labels, depth):
        if isinstance(t, Tensor) and t.dim() >= 2:
            return tuple(t.shape[-2:])
    return None


def _warn_if_normalised(boxes: list[Tensor], size: tuple[int, int] | None) -> None:
    """One warning where every box of the batch lies within [0, 1] on images of more than a
    few pixels: boxes normalised to the image (YOLO's, albumentations' "albumentations"
    format), which this package reads as pixel corners (a box 0.2 pixels wide)."""
    if size is None or min(size) <= 4:
        return
    flat = torch.cat(boxes) if boxes else torch.zeros(0, 4)
    if len(flat) and bool((flat >= 0).all()) and bool((flat <= 1).all()):
        warnings.warn(f"boxes: every box lies within [0, 1] on images of {size[1]} x {size[0]} "
                      f"pixels: normalised boxes? The boxes are XYXY pixel corner coordinates; "
                      f"multiply by (W, H, W, H) first", UserWarning, stacklevel=4)


def _float(dtype: torch.dtype) -> torch.dtype:
    return dtype if dtype.is_floating_point else torch.float32




def _camera_record(camera: Camera) -> dict:
    """A source camera ``(B,)`` as ``params["source_camera"]`` records it: plain values that a
    ``DataLoader``'s ``default_collate`` stacks (``model``, ``params (B, P)`` float64 on the
    CPU, and ``fov`` / ``blind_fov`` in radians where the camera has them)."""
    record = {"model": camera.model.name,
              "params": camera.params.detach().to("cpu", torch.float64)}
    for name in ("fov", "blind_fov"):
        if getattr(camera, name) is not None:
            record[name] = float(getattr(camera, name))
    return record


def _recorded_camera(record: dict, size: tuple[int, int]) -> Camera:
    """The camera of `_camera_record`'s ``record`` for images of ``size``, also after
    ``default_collate`` of per-sample records (the names listed, the rows stacked)."""
    def one(name: str):
        value = record.get(name)
        if isinstance(value, (list, tuple, Tensor)) and len(value) > 0:
            values = value.tolist() if isinstance(value, Tensor) else list(value)
            if any(v != values[0] for v in values):
                raise ValueError(f'params["source_camera"]["{name}"]: the samples differ '
                                 f"({values}); one call per source model")
            return values[0]
        return value
    try:
        params = torch.as_tensor(record["params"], dtype=torch.float64)
        model = one("model")
    except KeyError:
        raise ValueError(f'params["source_camera"]: expected a record with "model" and '
                         f'"params", got the keys {sorted(record)}') from None
    return Camera(model, params.reshape(-1, params.shape[-1]), size, fov=one("fov"),
                  blind_fov=one("blind_fov"))


def _check_source_camera(camera: object) -> None:
    """Refuse what is not one `Camera` (a batch of one model) naming ``source_camera``."""
    pair = isinstance(camera, tuple) and len(camera) == 2 and isinstance(camera[1], Tensor)
    if isinstance(camera, (list, tuple)) and not pair:   # a pair: not_a_camera's hint
        raise TypeError("source_camera: expected one ot.Camera (shared, or a batch (B,) of one "
                        "model), got a sequence; samples of different source models: one call "
                        "per model (split the batch)")
    if not isinstance(camera, Camera):
        raise not_a_camera("source_camera", camera)
    if len(camera.batch_shape) > 1:
        raise ValueError(f"source_camera: expected one camera or a batch (B,), got a batch "
                         f"{tuple(camera.batch_shape)}")


def _rows(camera: Camera, index: Tensor) -> Camera:
    """The cameras ``index`` of a batch ``(B,)``."""
    return Camera(camera.model, camera.params[index], camera.image_size, fov=camera.fov,
                  blind_fov=camera.blind_fov)


#: Angles of a lens's radius at focal 1 in `RandomReproject._unit_lens` (linear between



class _Part(NamedTuple):
    """A chunk of the samples of one model: ``params (n, P)``, their sample indices
    ``index (n,)``, ``rotation (n, 3, 3)``, ``fov (n,)``, and the source images' pinhole
    ``intrinsics (n, 4)`` and ``(H, W)``, or their ``source`` camera ``(n,)`` of another model
    (then ``intrinsics`` is None)."""

    params: Tensor
    index: Tensor
    rotation: Tensor
    fov: Tensor
    intrinsics: Tensor | None
    source_size: tuple[int, int]
    source: Camera | None = None


def _grid_rows(grid: CameraGrid | tuple[Tensor, Tensor], start: int, stop: int
               ) -> CameraGrid | tuple[Tensor, Tensor]:
    """The samples ``start:stop`` of a grid of ``kernels.camera_grid`` (views)."""
    if isinstance(grid, CameraGrid):
        return grid.rows(start, stop)
    return grid[0][start:stop], grid[1][start:stop]


def _slices(index: Tensor) -> list[tuple[slice, tuple[int, int]]]:
    """The runs of consecutive sample indices of ``index``: ``(slice of the batch, (start,
    stop) into index)`` each."""
    return [(slice(first, first + b - a), (a, b)) for a, b, first in _runs(index.tolist())]


def _plain(t: object) -> object:
    """A tensor subclass (torchvision's ``tv_tensors.Image``, ``Mask``) as the plain tensor it
    holds (no copy); anything else as it is."""
    return t.as_subclass(Tensor) if isinstance(t, Tensor) and type(t) is not Tensor else t


def _on_batch(out: dict, n: int, batch_size: int) -> dict:
    """Drawn parameters of ``n`` samples for ``batch_size`` (``same_on_batch``: one draw
    repeated)."""
    if n == batch_size:
        return out
    return {key: (value * batch_size if key == "model"
                  else value.expand(batch_size, *value.shape[1:]).clone())
            for key, value in out.items()}


def _runs(indices: list[int]) -> list[tuple[int, int, int]]:
    """The runs of consecutive values of ``indices``: ``(start, stop, first value)`` of each,
    positions into ``indices``."""
    runs, start = [], 0
    for k in range(1, len(indices) + 1):
        if k == len(indices) or indices[k] != indices[k - 1] + 1:
            runs.append((start, k, indices[start]))
            start = k
    return runs

