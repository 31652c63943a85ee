"""The containers the augmentation modules meet, read at the entry of ``forward`` and written
back at its exit, so that the modules themselves see plain batched tensors:

- torchvision's ``tv_tensors`` (``Image``, ``Mask``, ``BoundingBoxes``, ``KeyPoints``; any
  tensor subclass): read as the tensors they hold, their outputs returned in their classes
  (``BoundingBoxes`` in their format, with the output size as ``canvas_size``), and ``valid``
  as a ``Mask`` (the class of the label-like input, else ``tv_tensors.Mask``), so that
  ``transforms.v2``'s geometric transforms after the module move it with the rest (outputs
  given as plain tensors beside ``tv_tensors`` come back as ``tv_tensors`` too);
- unbatched samples (what a ``Dataset`` holds): ``(C, H, W)`` rgb, ``(H, W)`` labels, one
  ``(N, 4)`` box tensor, ``(K, 2)`` keypoints, read as a batch of one and returned without the
  batch dimension, ``params`` included (per-sample values that ``default_collate`` stacks into
  the parameters of the batch, so a collated batch replays);
- kornia's ``AugmentationSequential``, which calls a module it does not know with the image
  alone and leaves masks untransformed: refused with a ``TypeError`` that says how to compose.

torchvision is never imported here: a ``tv_tensors`` class is recognised by its module, and
``torchvision.tv_tensors`` is taken from ``sys.modules`` (imported already, since its tensors
exist).
"""

from __future__ import annotations

import sys
from typing import NamedTuple

import torch
from torch import Tensor

#: Keys that are no per-pixel image: never given a batch dimension (``intrinsics (4,)`` or
#: ``(3, 3)`` and a ``source_camera`` are shared by the batch already).
_SHARED = ("intrinsics", "source_camera")
#: Keys holding one value per sample (a list of B): an unbatched sample's is put in a list.
_PER_SAMPLE = ("boxes", "box_instance_ids", "polygons", "polygon_box")
#: Label-like keys: the class of the first given as a tensor subclass is ``valid``'s.
_MASKS = ("labels", "instances")
#: Box formats of torchvision's ``BoundingBoxFormat`` read and written here.
BOX_FORMATS = ("XYXY", "XYWH", "CXCYWH")
#: How many frames above ``forward`` are searched for kornia's containers.
_KORNIA_DEPTH = 8


class Wrapping(NamedTuple):
    """What `enter` read, for `leave`: whether the sample was unbatched, the
    tensor-subclass input of each key (``boxes``: one per sample, or None), and the class of
    ``valid`` (None: a plain tensor)."""

    unbatched: bool
    likes: dict
    mask_class: type | None


def enter(image: object, labels: object, depth: object, params: dict | None, *,
          batch_dims: dict[str, int], owner: object) -> tuple:
    """The inputs of an augmentation module's ``forward`` as plain batched tensors.

    Args:
        image: ``forward``'s first argument: a tensor or a dict of the module's keys.
        labels: ``forward``'s ``labels``. depth: ``forward``'s ``depth``.
        params: ``forward``'s ``params`` (one sample's, as an unbatched call returns them, are
            made those of a batch of one).
        batch_dims: the dimension count of each batched image key (``rgb``, label-like keys,
            ``depth``); a value with one less is an unbatched sample.
        owner: the module, named in errors.

    Returns:
        ``(image, labels, depth, params, wrapping)``: the same structure, plain and batched,
        and the `Wrapping` that `leave` needs.
    """
    if isinstance(image, Tensor):
        _refuse_kornia_container(owner)
    values = dict(image) if isinstance(image, dict) else {"rgb": image}
    positional = {"labels": labels, "depth": depth}
    for key, value in positional.items():
        values.setdefault(key, value)
    likes, plain = {}, {}
    for key, value in values.items():
        if key == "boxes":
            value, likes[key] = _plain_boxes(value)
        elif isinstance(value, Tensor) and type(value) is not Tensor:
            likes[key] = value
            value = value.as_subclass(Tensor)
        plain[key] = value
    unbatched = _is_unbatched(plain, batch_dims)
    if unbatched:
        plain = {key: _batched(key, value) for key, value in plain.items()}
    if isinstance(params, dict) and isinstance(params.get("model"), str):   # one sample's
        params = _batched_params(params)
    wrapping = Wrapping(unbatched, likes, _mask_class(likes))
    if isinstance(image, dict):
        return ({key: plain[key] for key in image}, labels if "labels" in image else
                plain["labels"], depth if "depth" in image else plain["depth"], params, wrapping)
    return plain["rgb"], plain["labels"], plain["depth"], params, wrapping


def leave(out: dict, wrapping: Wrapping) -> dict:
    """The outputs of ``forward`` in the containers `enter` read: unbatched again
    (``params`` as per-sample values) and in the inputs' tensor classes, ``valid`` in
    ``wrapping.mask_class``."""
    out = dict(out)
    if wrapping.unbatched:
        out = {key: _first(value) for key, value in out.items()}
    size = tuple(out["valid"].shape[-2:]) if "valid" in out else None
    for key, like in wrapping.likes.items():
        if key not in out or like is None:
            continue
        if key == "boxes":
            out[key] = (_wrap_boxes(out[key], like, size) if wrapping.unbatched else
                        [_wrap_boxes(b, one, size) for b, one in zip(out[key], like)])
        else:
            out[key] = _wrap(out[key], like, size)
    _as_tv(out, wrapping.likes, size, wrapping.unbatched)
    if wrapping.mask_class is not None and "valid" in out:
        out["valid"] = out["valid"].as_subclass(wrapping.mask_class)
    return out


# ---------------------------------------------------------------------------------------------
# kornia
# ---------------------------------------------------------------------------------------------
def _refuse_kornia_container(owner: object) -> None:
    """Raise if ``forward`` was called by one of kornia's containers (``AugmentationSequential``
    calls a module it does not know with the image alone and passes masks, boxes and keypoints
    on untransformed)."""
    frame = sys._getframe(2)
    for _ in range(_KORNIA_DEPTH):
        if frame is None:
            return
        if frame.f_globals.get("__name__", "").startswith("kornia.augmentation.container"):
            name = type(owner).__name__
            raise TypeError(
                f"{name} inside kornia's AugmentationSequential: kornia calls it with the image "
                f"alone and would pass masks, boxes and keypoints on untransformed. Call "
                f"{name} on a dict ({{'rgb': ..., 'labels': ...}}) and compose with "
                f"nn.Sequential: kornia's pixel-wise augmentations after it through "
                f"ot.augment.ApplyToKey, its geometric ones on every key at once "
                f"(AugmentationSequential(..., data_keys=['input', 'mask', 'mask']) on "
                f"out['rgb'], out['labels'][:, None], out['valid']; docs/augmentation.md)")
        frame = frame.f_back


# ---------------------------------------------------------------------------------------------
# Unbatched samples
# ---------------------------------------------------------------------------------------------
def _is_unbatched(values: dict, batch_dims: dict[str, int]) -> bool:
    """Whether the sample is unbatched: judged on its first image key given (``rgb``, then the
    label-like keys, then ``depth``), whose batched dimension count ``batch_dims`` gives. A
    depth-only sample is unbatched only as ``(H, W)`` (``(1, H, W)`` reads as a batch)."""
    for key in ("rgb", *_MASKS, "depth"):
        value = values.get(key)
        if isinstance(value, Tensor) and key in batch_dims:
            return value.dim() == batch_dims[key] - 1
    return False


def _batched(key: str, value: object) -> object:
    """One value of an unbatched sample with a batch dimension of one."""
    if key in _SHARED or value is None:
        return value
    if key in _PER_SAMPLE:
        return [value]
    return value.unsqueeze(0) if isinstance(value, Tensor) else value


def _batched_params(params: dict) -> dict:
    """Per-sample parameters (an unbatched call's) as those of a batch of one."""
    def batch(value):
        if isinstance(value, Tensor):
            return value.unsqueeze(0)
        if isinstance(value, dict):
            return {k: batch(v) for k, v in value.items()}
        return value
    out = {key: batch(value) for key, value in params.items()}
    out["model"] = (params["model"],)
    return out


def _first(value: object) -> object:
    """The first sample of an output value (``params``: of every batched entry, recursively;
    strings and numbers shared by the batch stay)."""
    if isinstance(value, Tensor):
        return value[0]
    if isinstance(value, (list, tuple)):
        return value[0]
    if isinstance(value, dict):
        return {key: _first(v) for key, v in value.items()}
    return value


# ---------------------------------------------------------------------------------------------
# tv_tensors
# ---------------------------------------------------------------------------------------------
def _tv_tensors(value: object):
    """``torchvision.tv_tensors`` if ``value`` is one of its tensors, else None."""
    if type(value).__module__.startswith("torchvision.tv_tensors"):
        return sys.modules["torchvision.tv_tensors"]
    return None


def _tv_of(likes: dict):
    """``torchvision.tv_tensors`` where any input is one of its tensors, else None."""
    for like in likes.values():
        for one in (like if isinstance(like, list) else [like]):
            tv = _tv_tensors(one)
            if tv is not None:
                return tv
    return None


def _mask_class(likes: dict) -> type | None:
    """The class of ``valid``: the first label-like input's, else ``tv_tensors.Mask`` where
    any input is a ``tv_tensors`` tensor, else None (a plain tensor)."""
    for key in _MASKS:
        if likes.get(key) is not None:
            return type(likes[key])
    tv = _tv_of(likes)
    return None if tv is None else tv.Mask


def _as_tv(out: dict, likes: dict, size: tuple[int, int] | None, unbatched: bool) -> None:
    """Among ``tv_tensors`` inputs, the outputs that came as plain tensors (or not at all:
    boxes of a cube's instances) as ``tv_tensors`` too, so that v2's transforms move them
    (v2 passes a plain tensor beside an ``Image`` on untouched): ``rgb`` an ``Image``, the
    other images ``(..., H, W)`` ``Mask``s, ``boxes`` ``BoundingBoxes`` (XYXY) and
    ``keypoints`` ``KeyPoints`` of the output canvas."""
    tv = _tv_of(likes)
    if tv is None or size is None:
        return
    for key, value in out.items():
        if likes.get(key) is None and key != "valid" and isinstance(value, Tensor) and \
                type(value) is Tensor and value.dim() >= 2 and tuple(value.shape[-2:]) == size:
            out[key] = tv.Image(value) if key == "rgb" else tv.Mask(value)
    if likes.get("boxes") is None and "boxes" in out:
        def box(b):
            return tv.BoundingBoxes(b, format="XYXY", canvas_size=size)
        out["boxes"] = box(out["boxes"]) if unbatched else [box(b) for b in out["boxes"]]
    if likes.get("keypoints") is None and "keypoints" in out and hasattr(tv, "KeyPoints"):
        out["keypoints"] = tv.KeyPoints(out["keypoints"], canvas_size=size)


def _wrap(value: Tensor, like: Tensor, size: tuple[int, int] | None) -> Tensor:
    """``value`` in the class of ``like``; a ``tv_tensors`` tensor with a ``canvas_size``
    (``KeyPoints``, ``BoundingBoxes``) gets the output size as its canvas."""
    tv = _tv_tensors(like)
    if tv is not None and hasattr(like, "canvas_size") and size is not None:
        return tv.wrap(value, like=like, canvas_size=size)
    return value.as_subclass(type(like))


def _box_format(boxes: Tensor) -> str:
    """The format name of ``boxes`` (``BoundingBoxes.format``; XYXY for a plain tensor)."""
    fmt = getattr(boxes, "format", None)
    name = "XYXY" if fmt is None else getattr(fmt, "name", str(fmt))
    if name not in BOX_FORMATS:
        raise ValueError(f"boxes: format {name} is not supported (expected one of "
                         f"{BOX_FORMATS}; rotated boxes have no tight box through a lens)")
    return name


def to_xyxy(boxes: Tensor, fmt: str) -> Tensor:
    """``(N, 4)`` boxes of torchvision's format ``fmt`` (``XYXY``, ``XYWH``, ``CXCYWH``) as
    XYXY corners, floating."""
    boxes = boxes if boxes.is_floating_point() else boxes.float()
    a, b = boxes[..., :2], boxes[..., 2:]
    if fmt == "XYWH":
        return torch.cat((a, a + b), -1)
    if fmt == "CXCYWH":
        return torch.cat((a - b / 2, a + b / 2), -1)
    return boxes


def from_xyxy(boxes: Tensor, fmt: str) -> Tensor:
    """The inverse of `to_xyxy`."""
    a, b = boxes[..., :2], boxes[..., 2:]
    if fmt == "XYWH":
        return torch.cat((a, b - a), -1)
    if fmt == "CXCYWH":
        return torch.cat(((a + b) / 2, b - a), -1)
    return boxes


def _plain_boxes(boxes: object) -> tuple[object, object]:
    """Boxes (one tensor, or a list of one per sample; ``BoundingBoxes`` of any supported
    format) as plain XYXY tensors, and what to wrap the output in (None where nothing was a
    tensor subclass)."""
    if isinstance(boxes, Tensor):
        if type(boxes) is Tensor:
            return boxes, None
        return to_xyxy(boxes.as_subclass(Tensor), _box_format(boxes)), boxes
    if isinstance(boxes, (list, tuple)):
        pairs = [_plain_boxes(b) for b in boxes]
        likes = [like for _, like in pairs]
        return [b for b, _ in pairs], (likes if any(like is not None for like in likes)
                                        else None)
    return boxes, None


def _wrap_boxes(boxes: Tensor, like: Tensor | None, size: tuple[int, int] | None) -> Tensor:
    """Output XYXY boxes in the format and class of the input ``like`` (canvas: ``size``)."""
    if like is None:
        return boxes
    return _wrap(from_xyxy(boxes, _box_format(like)), like, size)
