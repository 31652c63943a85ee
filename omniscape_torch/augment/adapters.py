"""Adapters that put the augmentation modules into other libraries' pipelines.

`to_albumentations` makes a `omniscape_torch.augment.RandomReproject` an
albumentations transform (``A.Compose([...])``), with its image, mask, masks, bboxes and
keypoints targets in albumentations' conventions. albumentations is an optional dependency,
imported only when an adapter is made: the adapter's class derives from the
``albumentations.DualTransform`` installed then, so the same code serves albumentations (MIT,
2.x) and its successor AlbumentationsX (AGPL, the same ``albumentations`` package and API),
and depends on neither.
"""

from __future__ import annotations

import sys

import numpy as np
import torch
from torch import Tensor, nn

__all__ = ["BOXES_FROM", "to_albumentations"]

#: The albumentations targets the adapter moves (additional targets of these types too).
_TARGETS = ("image", "mask", "masks", "bboxes", "keypoints")
#: Those of albumentations' spatial targets it refuses with a TypeError.
_REFUSED = ("images", "volume", "volumes", "mask3d", "masks3d")


#: The adapter's ``boxes_from`` values: where its boxes come from besides outlines and polygons.
BOXES_FROM = ("masks", "mask")


def to_albumentations(module: nn.Module, *, intrinsics: Tensor | None = None, p: float = 1.0,
                      boxes_from: str | None = None, instance_field: str | None = None):
    """An albumentations transform that runs ``module`` on each sample, for ``A.Compose``.

    The transform draws the sample's camera and attitude from its albumentations generator
    (``A.Compose(..., seed=...)`` reproduces a run) and renders every target of the sample
    through them in one call of ``module``:

    - ``image``: ``(H, W, C)`` or ``(H, W)``, ``uint8`` or floating -> ``(h, w, C)`` (or
      ``(h, w)``) of the same dtype, ``h, w = module.image_size``; 0 outside the valid area;
    - ``mask`` ``(H, W)`` / ``(H, W, C)`` and ``masks`` ``(N, H, W)``: integer class ids, never
      blended, ``module.ignore_index`` outside the valid area (in the mask's dtype where it
      fits, else int64);
    - ``bboxes`` in the Compose's ``bbox_params`` format (``pascal_voc``, ``coco``, ``yolo``,
      ``albumentations``) with their ``label_fields``: each box becomes the tight box of its
      object in the output, and a box left without area is dropped with its labels;
    - ``keypoints`` (``keypoint_params``): each mapped through the camera; one outside the
      image or the valid area comes back as NaN, which albumentations drops when
      ``remove_invisible=True`` (its default). Angle and scale are passed on unchanged.
    - ``polygons`` (not an albumentations target: a key of the call that albumentations passes
      on, and that no other transform of the Compose moves): per object a list of rings, each
      ``(N, 2)`` pixel corner coordinates or COCO's flat ``[x0, y0, x1, y1, ...]`` list, with
      ``polygon_box`` (the bbox of each ring; default: ring k, bbox k) -> ``polygons`` (float64
      ``(M, 2)`` arrays, clipped to the valid area) and ``polygon_index`` (the input ring of
      each); with ``bboxes``, a bbox with rings becomes the tight box of its mapped rings.

    The boxes of ``bboxes`` come from their outlines (loose on objects that are not boxes:
    ``docs/detection.md``), from ``polygons`` where given, or (``boxes_from``) exactly from the
    output pixels of each box's object: ``"masks"``, bbox j is the box of ``masks[j]``'s
    non-zero pixels (one mask per bbox, in their order); ``"mask"``, ``mask`` holds instance
    ids and the bbox label field ``instance_field`` each bbox's id (exact up to 2**24: the
    label columns are float32). A bbox whose object leaves the view is dropped with its labels.
    Other targets (``images``, volumes) raise a ``TypeError``. ``A.to_dict`` serialisation is
    not supported (a torch module is no JSON); the transform pickles, for ``DataLoader``
    workers.

    Args:
        module: a `omniscape_torch.augment.RandomReproject` whose source camera is set
            (``source_fov`` or ``source_camera``), or given here as ``intrinsics``.
        intrinsics: the images' pinhole ``fx, fy, cx, cy`` ``(4,)`` or ``K (3, 3)``, shared by
            every sample (None: the module's source camera).
        p: probability of applying the transform (albumentations' ``p``).
        boxes_from: None, ``"masks"`` or ``"mask"``: the exact boxes (above).
        instance_field: with ``boxes_from="mask"``, the name of the bbox label field (of the
            Compose's ``bbox_params.label_fields``) that holds each bbox's instance id.

    Returns:
        An instance of a subclass of the installed ``albumentations.DualTransform``.

    Raises:
        ImportError: albumentations (or AlbumentationsX) is not installed.
        TypeError: ``module`` is not an ``nn.Module``.
        ValueError: ``boxes_from`` is none of ``BOXES_FROM``, or ``"mask"`` without
            ``instance_field``.
    """
    if not isinstance(module, nn.Module):
        raise TypeError(f"module: expected an omniscape augmentation module, got "
                        f"{type(module).__name__}")
    if boxes_from is not None and boxes_from not in BOXES_FROM:
        raise ValueError(f"boxes_from: expected None or one of {BOXES_FROM}, got "
                         f"{boxes_from!r}")
    if (boxes_from == "mask") != (instance_field is not None):
        raise ValueError("instance_field: the bbox label field of each box's instance id in "
                         "`mask`, given with boxes_from='mask' (and only then)")
    try:
        import albumentations as A
    except ImportError as err:
        raise ImportError("to_albumentations needs albumentations (or AlbumentationsX): see "
                          "docs/getting-started.md for installing it beside OpenCV's contrib "
                          f"build ({err})") from None
    return _adapter_class(A.DualTransform)(module, intrinsics=intrinsics, p=p,
                                           boxes_from=boxes_from, instance_field=instance_field)


def _adapter_class(base: type) -> type:
    """The adapter's class on albumentations' ``DualTransform`` ``base`` (made per call of
    `to_albumentations`; an instance pickles as that call). The draw is albumentations
    2's ``get_params`` or AlbumentationsX's ``sample_parameters``, whichever ``base`` has
    (AlbumentationsX refuses a subclass that defines the former)."""

    def draw(self, rng: np.random.Generator) -> dict:
        generator = torch.Generator().manual_seed(int(rng.integers(0, 2 ** 63 - 1)))
        return {"omniscape": self.module.forward_parameters(1, generator=generator)}

    def __init__(self, module: nn.Module, intrinsics: Tensor | None = None,
                 p: float = 1.0, boxes_from: str | None = None,
                 instance_field: str | None = None) -> None:
        base.__init__(self, p=p)
        self.module = module
        self.intrinsics = intrinsics
        self.boxes_from, self.instance_field = boxes_from, instance_field

    namespace = {
        "__doc__": "``module`` as an albumentations transform (`to_albumentations`).",
        "__init__": __init__,
        "__reduce__": lambda self: (_rebuild, (self.module, self.intrinsics, self.p,
                                               self.boxes_from, self.instance_field)),
        "targets": property(lambda self: {key: self.apply for key in _TARGETS}),
        "apply_with_params": _apply_with_params,
        "get_transform_init_args_names": lambda self: ("module", "intrinsics", "boxes_from",
                                                       "instance_field"),
    }
    if hasattr(base, "sample_parameters"):   # AlbumentationsX
        sampled = vars(sys.modules[base.__module__])["SampledParams"]
        namespace["sample_parameters"] = lambda self, params, data, targets, sampling: sampled(
            params=draw(self, sampling.random_generator))
    else:   # albumentations 2
        namespace["get_params"] = lambda self: draw(self, self.random_generator)
    return type("OmniscapeTransform", (base,), namespace)


def _apply_with_params(self, params, *args, **data) -> dict:
    """Every target of one sample through the drawn camera, in one pass per image (the
    adapter's ``apply_with_params``; ``params``: a dict, or AlbumentationsX's
    ``SampledParams`` holding one)."""
    drawn = getattr(params, "params", params)["omniscape"]
    kinds = {key: self._additional_targets.get(key, key) for key, value in data.items()
             if value is not None}
    refused = sorted(key for key, kind in kinds.items() if kind in _REFUSED)
    if refused:
        raise TypeError(f"{type(self.module).__name__} in albumentations: the targets "
                        f"{refused} are not supported (only {_TARGETS})")
    out = dict(data)
    images = [key for key, kind in kinds.items() if kind == "image"]
    carried = [k for k in ("bboxes", "keypoints", "polygons") if k in kinds]
    if not images and carried:
        raise TypeError(f"{', '.join(carried)}: pass the image too (its size is their "
                        f"source's)")
    exact = self.boxes_from is not None and "bboxes" in kinds
    for n, key in enumerate(images):
        # the first image carries the boxes, keypoints and polygons (their source size is its)
        extra = {} if n else {k: data[k] for k in (*carried, "polygon_box")
                              if k in data and not (exact and k == "bboxes")}
        out.update(_render(self.module, drawn, self.intrinsics, key, data[key], extra))
    valid = {}
    for key, kind in kinds.items():
        if kind == "mask":
            out[key], valid[key] = _mask(self.module, drawn, self.intrinsics, data[key])
        elif kind == "masks" and len(data[key]):
            moved = [_mask(self.module, drawn, self.intrinsics, m) for m in data[key]]
            out[key] = np.stack([m for m, _ in moved])
            valid[key] = moved[0][1]
    if exact:
        out["bboxes"] = _exact_boxes(self, data, out, valid, kinds)
    return out


def _exact_boxes(self, data: dict, out: dict, valid: dict, kinds: dict) -> np.ndarray:
    """``bboxes`` (normalised, label columns kept) as the tight boxes of their objects' output
    pixels: ``masks[j]`` (``boxes_from="masks"``) or the pixels of ``mask`` holding the bbox's
    instance id (``"mask"``, the id in the label field ``instance_field``)."""
    boxes = data["bboxes"]
    key = next((k for k, kind in kinds.items() if kind == self.boxes_from), None)
    if key is None:
        raise TypeError(f"bboxes: boxes_from={self.boxes_from!r} needs the `{self.boxes_from}` "
                        f"target beside them")
    if self.boxes_from == "masks":
        source = np.asarray(data[key])
        if len(source) != len(boxes):
            raise ValueError(f"bboxes: boxes_from='masks' boxes bboxes[j] by masks[j], got "
                             f"{len(boxes)} bboxes and {len(source)} masks")
        moved = np.asarray(out[key]) if len(source) else np.zeros((0, 1, 1))
        objects = [(moved[j] != 0) & valid.get(key, True) for j in range(len(boxes))]
        present = [bool(np.any(source[j] != 0)) for j in range(len(boxes))]
    else:
        processor = self.get_processor("bboxes") if hasattr(self, "get_processor") else None
        fields = list(getattr(getattr(processor, "params", None), "label_fields", None) or [])
        if self.instance_field not in fields:
            raise ValueError(f"instance_field: {self.instance_field!r} is not a label field of "
                             f"the Compose's bbox_params (label_fields={fields})")
        ids = boxes[:, 4 + fields.index(self.instance_field)].astype(np.int64)
        source, moved = np.asarray(data[key]), np.asarray(out[key])
        objects = [(moved == i) & valid[key] for i in ids.tolist()]
        present = [bool(np.any(source == i)) for i in ids.tolist()]
    for j, ok in enumerate(present):
        if not ok:
            raise ValueError(f"bboxes[{j}]: its object has no pixel in the source "
                             f"`{key}` (boxes_from={self.boxes_from!r})")
    h, w = out[key].shape[-2:] if self.boxes_from == "masks" else out[key].shape[:2]
    rows, kept = [], []
    for j, mask in enumerate(objects):
        r, c = np.nonzero(mask)
        if len(r):
            rows.append([c.min() / w, r.min() / h, (c.max() + 1) / w, (r.max() + 1) / h])
            kept.append(j)
    moved_boxes = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
    return np.concatenate((moved_boxes, boxes[kept, 4:]), 1).astype(boxes.dtype)


def _rebuild(module: nn.Module, intrinsics: Tensor | None, p: float,
             boxes_from: str | None = None, instance_field: str | None = None):
    """An unpickled adapter: `to_albumentations` again, on the albumentations there."""
    return to_albumentations(module, intrinsics=intrinsics, p=p, boxes_from=boxes_from,
                             instance_field=instance_field)


def _call(module: nn.Module, drawn: dict, intrinsics: Tensor | None, sample: dict) -> dict:
    """``module`` on one unbatched sample with the drawn parameters, without gradients."""
    extra = {} if intrinsics is None else {"intrinsics": intrinsics}
    with torch.no_grad():
        return module(sample, params=drawn, **extra)


def _render(module: nn.Module, drawn: dict, intrinsics: Tensor | None, key: str,
            image: np.ndarray, extra: dict) -> dict:
    """The image ``key`` (``(H, W[, C])``) and, with it, ``bboxes`` and ``keypoints``."""
    height, width = image.shape[:2]
    gray = image.ndim == 2
    hwc = torch.from_numpy(np.ascontiguousarray(image[..., None] if gray else image))
    rgb = hwc if getattr(module, "channels_last", False) else hwc.permute(2, 0, 1)
    sample = {"rgb": rgb}
    if "bboxes" in extra:   # normalised XYXY (+ label columns) -> pixel corners
        scale = np.array([width, height, width, height], dtype=np.float64)
        sample["boxes"] = torch.from_numpy(extra["bboxes"][:, :4] * scale)
    if "keypoints" in extra:   # pixel centres at integers -> the corner convention
        sample["keypoints"] = torch.from_numpy(extra["keypoints"][:, :2].astype(np.float64)
                                               + 0.5)
    if "polygons" in extra:    # pixel corner coordinates, as COCO's
        sample["polygons"] = list(extra["polygons"])
        if extra.get("polygon_box") is not None:
            sample["polygon_box"] = torch.as_tensor(np.asarray(extra["polygon_box"]))
    got = _call(module, drawn, intrinsics, sample)
    rgb = got["rgb"].as_subclass(Tensor)
    rgb = rgb if getattr(module, "channels_last", False) else rgb.permute(1, 2, 0)
    rgb = rgb.numpy()
    out = {key: rgb[..., 0] if gray else rgb}
    h, w = rgb.shape[:2]
    if "bboxes" in extra:
        boxes = extra["bboxes"]
        index = got["box_index"].numpy()
        moved = got["boxes"].as_subclass(Tensor).double().numpy() / [w, h, w, h]
        out["bboxes"] = np.concatenate((moved, boxes[index, 4:]), 1).astype(boxes.dtype)
    if "polygons" in extra:
        out["polygons"] = [r.double().numpy() for r in got["polygons"]]
        out["polygon_index"] = got["polygon_index"].numpy()
    if "keypoints" in extra:
        points = extra["keypoints"].copy()
        moved = got["keypoints"].as_subclass(Tensor).double().numpy() - 0.5
        moved[~got["keypoints_valid"].numpy()] = np.nan
        points[:, :2] = moved
        out["keypoints"] = points
    return out


def _mask(module: nn.Module, drawn: dict, intrinsics: Tensor | None,
          mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A mask ``(H, W)`` or ``(H, W, C)`` of integer ids through the drawn camera, and the
    output's valid area ``(h, w)``."""
    if not (np.issubdtype(mask.dtype, np.integer) or mask.dtype == bool):
        raise TypeError(f"mask: expected integer class ids, got {mask.dtype}")
    channels = [mask] if mask.ndim == 2 else [mask[..., c] for c in range(mask.shape[-1])]
    ignore = int(getattr(module, "ignore_index", 255))
    dtype = mask.dtype if mask.dtype != bool and (
        np.iinfo(mask.dtype).min <= ignore <= np.iinfo(mask.dtype).max) else np.int64
    got = [_call(module, drawn, intrinsics, {"labels": torch.from_numpy(
        np.ascontiguousarray(c).astype(np.int64))}) for c in channels]
    out = [g["labels"].numpy().astype(dtype) for g in got]
    valid = got[0]["valid"].as_subclass(Tensor)[0].numpy()
    return (out[0] if mask.ndim == 2 else np.stack(out, -1)), valid
