"""`RandomReproject`: a perspective (or any camera's) image through a random fisheye lens and
attitude per sample."""

from __future__ import annotations

import math
from typing import Callable, Mapping, Sequence

import torch
from torch import Tensor

from ..cameras import Camera
from ..cubemap.rotation import check_rotation
from ..render import detection
from ..render import layer as projection
from ..render.kernels import resolve
from ..render.kernels.cube import MODES
from ..render.reference import check_out_dtype, warn_if_label_map
from ..render.reproject import INTERPOLATIONS, intrinsics_from_matrix
from . import containers
from .draw import (
    _DEG,
    _IMAGE_DIMS,
    _LENS_DEFAULTS,
    DEFAULT_COVERAGE,
    _check_range,
    _RandomCameras,
    shared_arguments,
)
from .routes import _Routes
from .targets import (
    _camera_record,
    _check_batches,
    _check_label_keys,
    _check_source_camera,
    _float,
    _label_maps,
    _Part,
    _plain,
    _recorded_camera,
    _reference,
    _render_label_maps,
    _rows,
    _source_size,
    _targets,
    _unpack,
    _warn_if_normalised,
)


class RandomReproject(_Routes, _RandomCameras):
    """Per sample, a perspective (or any camera's) image seen through a random fisheye lens and
    attitude.

    For the segmentation datasets of perspective images (Cityscapes, BDD100K, Mapillary, the
    built-in town's pinhole views): each image, with its pinhole intrinsics, is reprojected
    into a fisheye camera drawn as `RandomOmniCamera` draws its fisheyes (``mode=
    "fisheye"``: a model among ``fisheye_models``, the image circle of a field of view drawn in
    ``fov_range`` inscribed in the image, the lens parameters in their ranges), turned by a
    drawn attitude (``R = yaw_pitch_roll_to_matrix(yaw, pitch, roll)`` maps the fisheye's rays
    into the source camera's frame, ``ray_src = R @ ray``): ``ot.reproject``'s image, its
    labels (nearest, never blended, ``ignore_index`` outside) and depth, from one geometry. The
    fisheye sees more than the perspective image: the pixels whose ray misses the source image
    (or lies behind it) are invalid (``valid``, 0 in ``rgb``, ``ignore_index`` in ``labels``).

    The source camera, passed with the images: ``intrinsics (B, 4)`` (``fx, fy, cx, cy`` in
    pixels, pixel centres at integers) or a camera matrix ``K (B, 3, 3)`` / ``(3, 3)`` (zero
    skew, last row ``[0, 0, 1]``: the same pinhole, bit for bit), or ``source_camera``, any
    camera of the registry (a distorted ``opencv`` camera, an Aria ``fisheye624`` read by
    ``Camera.load``...): one shared by the batch, or a batch ``(B,)`` of one model (samples of
    different source models: one call per model). Else the module's: ``source_camera`` or a
    horizontal field of view ``source_fov`` given at construction (``fx = fy = (W / 2) /
    tan(source_fov / 2)``, the principal point at the image centre). The source camera's
    validity (its model's domain, its image bounds, its ``fov``) makes ``valid`` False where it
    does not see. A source other than a pinhole projects the rays in torch (in the drawn
    cameras' dtype), then the same samplers read the image at those pixels: the C++ op as the
    rays ``(u, v, 1)`` of the unit pinhole (exact), or ``grid_sample``; that projection costs
    about 20 to 45 ms more per 512 x 512 output on one CPU thread (``opencv``, ``fisheye624``),
    3 to 8 times a pinhole source's call. Its planar depth is 0 where a source ray lies at or
    beyond 90 degrees from its axis.

    Attitude defaults: roll +-25 deg (the OmniScape paper's Table I), pitch and yaw +-10 deg
    (a perspective image holds a narrow cone: a larger turn leaves the fisheye mostly empty).
    ``p``, ``same_on_batch``, ``seed``, `reseed` and the randomness across epochs and
    ``DataLoader`` workers: as `RandomOmniCamera`'s.

    On the CPU without gradients (the fast path, as ``OmniProjection``'s), every pixel's ray
    comes from a table per camera (``kernels.radial_table``) and the image is sampled by the C++
    op ``sample_image`` straight from the image's memory: ``uint8`` in and out (rounded half
    up, or scaled to [0, 1] by a floating ``out_dtype``), channels-last images read without a
    copy (``channels_last``), labels written as int64 in the same pass. Elsewhere (another
    device, a gradient asked for, ``bicubic``) the exact chain: ``Camera.ray_grid`` and
    `sample_camera` (``grid_sample``).

    Args:
        image_size: ``(H, W)`` of the output.
        source_fov: the horizontal field of view of the perspective images (radians), used
            where no ``intrinsics`` are passed; None: they must be passed.
        source_camera: one `Camera` (any model, ``image_size`` the
            images') used where neither ``intrinsics`` nor ``source_camera`` are passed; not
            with ``source_fov``.
        fisheye_models: the lens, as for `RandomOmniCamera` (``mode="fisheye"``).
        fov_range: the lens, as for `RandomOmniCamera` (``mode="fisheye"``).
        kb_distortion: the lens, as for `RandomOmniCamera` (``mode="fisheye"``).
        unified_xi_range: the lens, as for `RandomOmniCamera` (``mode="fisheye"``).
        eucm_alpha_range: the lens, as for `RandomOmniCamera` (``mode="fisheye"``).
        eucm_beta_range: the lens, as for `RandomOmniCamera` (``mode="fisheye"``).
        ds_xi_range: the lens, as for `RandomOmniCamera` (``mode="fisheye"``).
        ds_alpha_range: the lens, as for `RandomOmniCamera` (``mode="fisheye"``).
        focal_scale_range: the focal as a multiple of the one that inscribes the drawn image
            circle (as for `RandomOmniCamera`); not with ``coverage_range``. Given
            alone, it replaces the default framing (the behaviour before it).
        coverage_range: ``(min, max)`` share of the output's pixels the source fills (valid),
            drawn per sample; the focal is solved for it from the source pinhole, the drawn
            lens and attitude (`framing`; ``params["coverage"]``).
            Default, when neither it nor ``focal_scale_range`` is given: ``(0.5, 0.9)``
            (``DEFAULT_COVERAGE``). Sources other than a pinhole, and
            ``forward_parameters`` without ``source_size``, use ``focal_scale_range``.
        center_jitter: the lens, as for `RandomOmniCamera` (``mode="fisheye"``).
        roll_range: ``(min, max)`` radians.
        pitch_range: ``(min, max)`` radians.
        yaw_range: ``(min, max)`` radians.
        p: probability of a random attitude per sample (else roll = pitch = yaw = 0).
        same_on_batch: one draw for the whole batch.
        interpolation: ``"bilinear"`` (default), ``"nearest"`` or ``"bicubic"`` (exact chain).
        depth_output: ``"range"`` (distance along the ray) or ``"z"`` (along the fisheye's
            optical axis); the input depth is planar, along the source camera's axis.
        ignore_index: label of invalid pixels.
        seed: seed of the module's generator.
        channels_last: the images are ``(B, H, W, C)`` and ``rgb`` comes back so.
        out_dtype: dtype of ``rgb``: None for the image's, or a floating dtype (``uint8``
            scaled to [0, 1]).
        label_keys: ``{key: ignore value}``: more label-like keys the dicts may hold, as for
            `RandomOmniCamera`.
        antialias: prefilter ``rgb`` where the fisheye minifies the source (an output pixel
            covering more than one source pixel): the mean of taps over each pixel's
            footprint through a mip pyramid. On the CPU fast path (``uint8``, float32 and
            float64 images, no gradient) the C++ op `
            mip_image`; elsewhere `antialias` (the same rule,
            differentiable). Pixels that do not minify are as with
            ``antialias=False`` (point samples), bit for bit; ``labels``, ``depth`` and
            ``valid`` are the same either way (nearest texel at the pixel centre, never
            blended). Not for ``interpolation="nearest"``. On by default (as in
            ``ot.reproject``): its cost is in ``docs/augmentation.md`` (Antialiasing).
        backend: the kernels' route (``render.kernels``): ``"auto"`` (the C++ ops on the CPU
            without gradients, else torch), ``"cpp"`` or ``"torch"``.
        camera: a fixed target camera (an ``ot.Camera``, or a calibration file's path that
            ``Camera.load`` reads, e.g. WoodScape's ``front.json``) instead of a drawn lens,
            "make my perspective data look as if taken by this camera": ``image_size`` may
            then be None (the camera's); ``focal_jitter`` and ``center_jitter`` perturb its
            parameters, the attitude ranges its attitude; the lens arguments, ``coverage_range``
            and ``focal_scale_range`` are not used. Without jitter (``roll_range``,
            ``pitch_range``, ``yaw_range`` at ``(0, 0)``) its image is ``ot.reproject``'s into
            that camera, bit for bit.
        focal_jitter: with ``camera``: its focal (``fx, fy``; the pixel polynomial of
            ``woodscape`` and ``scaramuzza``) scaled by a factor drawn in
            ``[1 - focal_jitter, 1 + focal_jitter]``.

    Shapes:
        ``rgb (B, C, Hs, Ws)`` (``channels_last``: ``(B, Hs, Ws, C)``) floating or ``uint8``,
        ``labels (B, Hs, Ws)`` integer, ``depth (B, Hs, Ws)`` or ``(B, 1, Hs, Ws)`` planar ->
        ``rgb (B, C, H, W)`` (``(B, H, W, C)``), ``labels (B, H, W)`` int64,
        ``depth (B, 1, H, W)``, ``valid (B, 1, H, W)`` bool; ``params`` as
        `forward_parameters` returns them, with the ``intrinsics (B, 4)`` of a pinhole
        source, or the record of the ``source_camera`` used (``model``, ``params (B, P)``
        float64 on the CPU: plain values that ``default_collate`` stacks).

    Examples:
        >>> aug = RandomReproject((64, 64), source_fov=math.radians(90), seed=0)
        >>> out = aug({"rgb": torch.rand(2, 3, 48, 64), "labels": torch.zeros(2, 48, 64).long()})
        >>> out["rgb"].shape, out["labels"].shape, out["valid"].shape
        (torch.Size([2, 3, 64, 64]), torch.Size([2, 64, 64]), torch.Size([2, 1, 64, 64]))
    """

    def __init__(self, image_size: tuple[int, int] | None, *, source_fov: float | None = None,
                 source_camera: Camera | None = None,
                 fisheye_models: Sequence[str] = ("equidistant",),
                 fov_range: tuple[float, float] = (160 * _DEG, 200 * _DEG),
                 kb_distortion: float = 0.02,
                 unified_xi_range: tuple[float, float] = _LENS_DEFAULTS["unified_xi_range"],
                 eucm_alpha_range: tuple[float, float] = _LENS_DEFAULTS["eucm_alpha_range"],
                 eucm_beta_range: tuple[float, float] = _LENS_DEFAULTS["eucm_beta_range"],
                 ds_xi_range: tuple[float, float] = _LENS_DEFAULTS["ds_xi_range"],
                 ds_alpha_range: tuple[float, float] = _LENS_DEFAULTS["ds_alpha_range"],
                 focal_scale_range: tuple[float, float] | None = None,
                 coverage_range: tuple[float, float] | None = None,
                 center_jitter: float = 0.0,
                 roll_range: tuple[float, float] = (-25 * _DEG, 25 * _DEG),
                 pitch_range: tuple[float, float] = (-10 * _DEG, 10 * _DEG),
                 yaw_range: tuple[float, float] = (-10 * _DEG, 10 * _DEG),
                 p: float = 1.0, same_on_batch: bool = False,
                 interpolation: str = "bilinear", depth_output: str = "range",
                 ignore_index: int = 255, seed: int | None = None,
                 channels_last: bool = False, out_dtype: torch.dtype | None = None,
                 label_keys: Mapping[str, int] | None = None,
                 antialias: bool = True, backend: str = "auto", camera: object = None,
                 focal_jitter: float = 0.0) -> None:
        if focal_scale_range is not None and coverage_range is not None:
            raise ValueError("coverage_range: pass coverage_range or focal_scale_range, not both")
        if focal_scale_range is None and coverage_range is None:
            coverage_range = DEFAULT_COVERAGE
        if coverage_range is not None:
            coverage_range = _check_range(coverage_range, "coverage_range", 1e-3, 1.0)
        if not isinstance(antialias, bool):
            raise TypeError(f"antialias: expected a bool, got {antialias!r}")
        focal_scale_range = (1.0, 1.0) if focal_scale_range is None else focal_scale_range
        super().__init__(image_size, **shared_arguments(locals()))
        if source_fov is not None and not (isinstance(source_fov, (int, float)) and not
                                           isinstance(source_fov, bool) and
                                           0 < source_fov < math.pi):
            raise ValueError(f"source_fov: expected a horizontal field of view in (0, pi) "
                             f"radians, or None, got {source_fov!r}")
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, got "
                             f"{interpolation!r}")
        if depth_output not in ("range", "z"):
            raise ValueError(f"depth_output: expected 'range' or 'z', got {depth_output!r}")
        if source_camera is not None:
            _check_source_camera(source_camera)
            if len(source_camera.batch_shape) != 0:
                raise ValueError(f"source_camera: at construction one camera shared by every "
                                 f"sample, got a batch {tuple(source_camera.batch_shape)}; pass "
                                 f"a batch per call (forward(..., source_camera=))")
            if source_fov is not None:
                raise ValueError("source_camera: pass source_fov or source_camera, not both")
        self.source_fov = None if source_fov is None else float(source_fov)
        self.source_camera = source_camera
        self.label_keys = _check_label_keys(label_keys)
        self.coverage_range = coverage_range
        self.antialias = antialias
        if self.camera is None:
            self._check_fisheye_ranges()

    def __setstate__(self, state: dict) -> None:
        state = dict(state)
        # pickled before framing and antialiasing existed: as they rendered then
        state.setdefault("coverage_range", None)
        state.setdefault("antialias", False)
        super().__setstate__(state)
        if "source_camera" not in self._modules:   # pickled before it existed
            self.source_camera = None

    def extra_repr(self) -> str:
        source = ("" if self.source_camera is None else
                  f"source_camera={self.source_camera.model.name} "
                  f"{self.source_camera.image_size}, ")
        return (f"image_size={self.image_size}, source_fov={self.source_fov}, {source}"
                f"fisheye_models={self.fisheye_models}, p={self.p}, "
                f"same_on_batch={self.same_on_batch}, seed={self.seed}, "
                f"channels_last={self.channels_last}, out_dtype={self.out_dtype}, "
                f"coverage_range={self.coverage_range}, antialias={self.antialias}")

    @torch.no_grad()
    def forward_parameters(self, batch_size: int, *, generator: torch.Generator | None = None,
                           intrinsics: Tensor | None = None,
                           source_size: tuple[int, int] | None = None) -> dict:
        """Draw fisheye cameras and attitudes for ``batch_size`` samples.

        Args:
            batch_size: ``B``.
            generator: the generator of this call (else the module's).
            intrinsics: the source pinhole ``(B, 4)`` or ``(4,)`` ``fx, fy, cx, cy`` (or a
                camera matrix), which ``coverage_range`` frames (else ``source_fov``'s);
                ignored without ``coverage_range``.
            source_size: ``(Hs, Ws)`` of the source images: with ``coverage_range``, the
                focal is solved for the drawn coverage of this source (as ``forward`` draws);
                None: from ``focal_scale_range`` (the image circle inscribed), unframed.

        Returns:
            dict, tensors float64 on the CPU: ``model`` (tuple of ``B`` model names),
            ``camera_params (B, 9)`` (zero-padded), ``num_params (B,)``, ``fov (B,)`` and
            ``blind_fov (B,)`` (radians; 0), ``yaw``, ``pitch``, ``roll (B,)``, ``applied (B,)``,
            ``rotation (B, 3, 3)`` fisheye -> source camera frame, and with ``coverage_range``
            and a pinhole source ``coverage (B,)``: the share of the output drawn (the focal
            solved for it, `framing`).

        Raises:
            ValueError: ``source_size`` with ``coverage_range`` but neither ``intrinsics`` nor
                ``source_fov``.
        """
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size: expected a positive int, got {batch_size!r}")
        source = None
        if self.coverage_range is not None and source_size is not None:
            source_size = (int(source_size[0]), int(source_size[1]))
            source = self._intrinsics(intrinsics, source_size, batch_size)
        return self._draw_params(batch_size, generator, source, source_size)

    def source_intrinsics(self, image_size: tuple[int, int], batch: int) -> Tensor:
        """``(batch, 4)`` float64 pinhole intrinsics of images of ``image_size`` from
        ``source_fov``: ``fx = fy = (W / 2) / tan(source_fov / 2)``, ``cx = (W - 1) / 2``,
        ``cy = (H - 1) / 2``."""
        if self.source_fov is None:
            raise ValueError("intrinsics: pass the images' pinhole intrinsics (B, 4) fx, fy, cx, "
                             "cy, or construct RandomReproject with source_fov")
        key = ("source", tuple(image_size))
        row = self._cached.get(key)
        if row is None:   # one row per image size, repeated (a new tensor) per call
            h, w = image_size
            f = (w / 2) / math.tan(self.source_fov / 2)
            row = self._cached[key] = torch.tensor([[f, f, (w - 1) / 2, (h - 1) / 2]],
                                                   dtype=torch.float64)
        return torch.empty(batch, 4, dtype=torch.float64).copy_(row)   # (repeat: 4x slower)

    def render(self, image: Tensor | None, params: dict, *, labels: Tensor | None = None,
               depth: Tensor | None = None, intrinsics: Tensor | None = None,
               source_camera: Camera | None = None, instances: Tensor | None = None,
               boxes: Sequence[Tensor] | None = None,
               box_instance_ids: Sequence[Tensor] | None = None,
               keypoints: Tensor | None = None, label_maps: Mapping[str, Tensor] | None = None,
               polygons: Sequence[Sequence[Tensor]] | None = None,
               polygon_box: Sequence[Tensor] | None = None) -> dict:
        """Reproject the modalities and the detection targets through the cameras and
        rotations of ``params``.

        Args:
            image: ``(B, C, Hs, Ws)`` (``channels_last``: ``(B, Hs, Ws, C)``), or None.
            params: parameters from ``forward_parameters``.
            labels: as for ``forward``.
            depth: as for ``forward``.
            intrinsics: as for ``forward``.
            source_camera: as for ``forward``.
            instances: ``(B, Hs, Ws)`` integer instance ids (0: none), any range.
            boxes: per sample ``(N_i, 4)`` XYXY corner coordinates.
            box_instance_ids: per sample ``(N_i,)`` the instance id of each box (with
                ``instances``: the exact mode).
            keypoints: ``(B, K, 2)`` corner coordinates (NaN: missing).
            label_maps: the declared label keys' maps (``label_keys``), by key.
            polygons: per sample a list of rings ``(N_k, 2)`` corner coordinates (or COCO's
                flat lists).
            polygon_box: per sample ``(R_i,)`` the box of each ring (default: ring k, box k).

        Returns:
            the dict of ``forward``: ``params`` with the ``intrinsics (B, 4)`` of a pinhole
            source, else ``source_camera``, the source used, as ``{"model", "params" (B, P)
            float64 on the CPU[, "fov", "blind_fov"]}``, which ``default_collate`` stacks and a
            replay reads back.
        """
        return self._render(image, params, None, labels=labels, depth=depth,
                            intrinsics=intrinsics, source_camera=source_camera,
                            instances=instances, boxes=boxes, box_instance_ids=box_instance_ids,
                            keypoints=keypoints, label_maps=label_maps, polygons=polygons,
                            polygon_box=polygon_box)

    def _render(self, image: Tensor | None, params: dict, drawn: tuple | None, *,
                labels: Tensor | None = None, depth: Tensor | None = None,
                intrinsics: Tensor | None = None, source_camera: Camera | None = None,
                instances: Tensor | None = None, boxes: Sequence[Tensor] | None = None,
                box_instance_ids: Sequence[Tensor] | None = None,
                keypoints: Tensor | None = None, label_maps: Mapping[str, Tensor] | None = None,
                polygons: Sequence[Sequence[Tensor]] | None = None,
                polygon_box: Sequence[Tensor] | None = None) -> dict:
        """`render`; ``drawn``: where ``forward`` drew ``params`` itself in this call,
        the source ``(k, camera)`` of `_source` (checked) for images of ``(Hs, Ws)``
        that it drew them for, else None. Drawn params are not checked again (their rotations,
        cameras and batch are the module's own) nor is their source made again (for inputs of
        that size)."""
        size = _source_size(image, labels, depth, self.channels_last)
        maps = _label_maps(self.label_keys, instances, label_maps, cube=False, size=size)
        if size is None and maps:   # label maps alone: the first one's size
            size = tuple(next(iter(maps.values()))[0].shape[-2:])
        batch = _check_batches(params, **dict(
            (key, t) for key, (t, _) in maps.items()), box_instance_ids=box_instance_ids,
            keypoints=keypoints, boxes=boxes, polygons=polygons)
        kp_dtype = torch.float32
        if keypoints is not None:
            kp_dtype = _float(torch.as_tensor(keypoints).dtype)
            keypoints = detection.check_keypoints(keypoints, batch)
        box_dtype = torch.float32
        if boxes is not None:
            box_dtype = next((_float(torch.as_tensor(b).dtype) for b in boxes), box_dtype)
            boxes = detection.check_boxes(boxes, batch)
            _warn_if_normalised(boxes, size)
        ids = None
        if box_instance_ids is not None:
            if instances is None:
                raise ValueError("box_instance_ids: needs instances (the exact mode boxes the "
                                 "output pixels of each box's instance id)")
            ids = detection.check_box_ids(box_instance_ids, boxes, batch)
        ring_dtype = torch.float32
        if polygons is not None:
            ring_dtype = next((_float(r.dtype) for p in polygons for r in p
                               if isinstance(r, Tensor)), ring_dtype)
            polygons, polygon_box = detection.check_polygons(polygons, batch, boxes, polygon_box)
        elif polygon_box is not None:
            raise ValueError("polygon_box: needs polygons (the box of each ring)")
        sources = dict(intrinsics=intrinsics, source_camera=source_camera)
        targets = None
        if keypoints is not None or polygons is not None or (boxes is not None and ids is None):
            # mapped before the maps are rendered: the boxes that the valid area cuts read
            # their pixels from the rays the maps are sampled along (Targets.scan)
            k, camera = (drawn[:2] if drawn is not None and drawn[2] == size else
                         self._source(intrinsics, source_camera, size, batch))
            source = (detection.Side("pinhole", k, size) if k is not None
                      else detection.Side.of(camera, batch))
            targets = detection.Targets(
                self._changes(params, source), batch, keypoints=keypoints,
                boxes=None if ids is not None else boxes, source_size=size,
                polygons=polygons, polygon_box=polygon_box)
        result = {}
        if any(t is not None for t in (image, labels, depth)):
            result = self._render_maps(image, params, labels=labels, depth=depth,
                                       scan=None if targets is None else targets.scan,
                                       drawn=drawn, **sources)
        _render_label_maps(result, maps, lambda ids: self._render_maps(
            None, params, labels=ids, drawn=drawn, **sources))
        if ids is not None:
            result.update(detection.boxes_of_instances(result["instances"], ids,
                                                       _plain(instances), box_dtype))
        if targets is not None:
            valid = result["valid"][:, 0] if "valid" in result else None
            result.update(targets.result(kp_dtype, box_dtype, valid, ring_dtype))
        return result

    def _render_maps(self, image: Tensor | None, params: dict, *, labels: Tensor | None = None,
                     depth: Tensor | None = None, intrinsics: Tensor | None = None,
                     source_camera: Camera | None = None, scan: Callable | None = None,
                     drawn: tuple | None = None) -> dict:
        """`render` of the modalities alone (``valid``, ``rgb``, ``labels``, ``depth``,
        ``params`` with the source camera's record); ``scan``: called on the fast path with
        each chunk's samples and the rays they are sampled along (``detection.Targets.scan``);
        ``drawn``: as for `_render`."""
        image, labels, depth, size = self._check_inputs(image, labels, depth)
        batch = next(t for t in (image, labels, depth) if t is not None).shape[0]
        if drawn is None or drawn[2] != size:
            if len(params["model"]) != batch:
                raise ValueError(f"params: drawn for {len(params['model'])} samples, the batch "
                                 f"has {batch}")
            check_rotation(params["rotation"], 'params["rotation"]')
            k, source = self._source(intrinsics, source_camera, size, batch)
        else:
            k, source = drawn[:2]
        ref = next(t for t in (image, labels, depth) if t is not None)
        device = ref.device
        dtype = torch.float64 if ref.dtype == torch.float64 else torch.float32
        rgb_dtype = None if image is None else check_out_dtype(image.dtype, self.out_dtype)
        h, w = self.image_size
        result = {"valid": torch.empty(batch, 1, h, w, dtype=torch.bool, device=device)}
        if image is not None:
            chans = image.shape[1]
            result["rgb"] = (torch.empty(batch, h, w, chans, dtype=rgb_dtype, device=device)
                             .permute(0, 3, 1, 2) if self.channels_last
                             else torch.empty(batch, chans, h, w, dtype=rgb_dtype,
                                              device=device))
        if labels is not None:
            result["labels"] = torch.empty(batch, h, w, dtype=torch.int64, device=device)
        if depth is not None:
            result["depth"] = torch.empty(batch, 1, h, w, dtype=depth.dtype, device=device)
        # the C++ ops for the whole call where they run (kernels.resolve), and samplable
        fast_path = (self.interpolation in MODES and resolve(
            self.backend, image, labels, depth, k, what="RandomReproject") == "cpp")
        given = source
        if source is not None:   # projected in the drawn cameras' dtype, as a pinhole's rays
            source = Camera(source.model, source.params.to(device, dtype), source.image_size,
                            fov=source.fov, blind_fov=source.blind_fov)
        # on the CPU a few samples at a time (projection.CHUNK_PIXELS): the rays of a chunk
        chunk = batch if device.type != "cpu" else max(1, projection.CHUNK_PIXELS // (h * w))
        groups = self._camera_params(params, dtype, device,
                                     checked=drawn is not None and drawn[2] == size)
        rotations = params["rotation"].to(dtype=dtype, device=device)
        fovs = params["fov"].to(dtype=dtype, device=device)
        for name, (idx, cam_params) in groups.items():
            for start in range(0, len(idx), chunk):
                sel = idx[start:start + chunk]
                at = slice(start, start + chunk) if len(groups) == 1 else sel   # (views)
                part = _Part(cam_params[start:start + chunk], sel, rotations[at], fovs[at],
                             None if k is None else k[at].to(device), size,
                             None if source is None else _rows(source, sel.to(device)))
                if fast_path:
                    self._render_fast(name, part, image, labels, depth, result, scan)
                else:
                    self._render_exact(name, part, image, labels, depth, result)
        if image is not None and self.channels_last:
            result["rgb"] = result["rgb"].permute(0, 2, 3, 1)
        if k is not None:
            result["params"] = dict(params, intrinsics=k.to("cpu", torch.float64))
            result["params"].pop("source_camera", None)
        else:
            result["params"] = dict(params, source_camera=_camera_record(given))
            result["params"].pop("intrinsics", None)
        return result

    def _draw(self, ref: Tensor, ids: bool, intrinsics: object, source_camera: object,
              generator: torch.Generator | None) -> tuple[dict, tuple]:
        """``forward_parameters`` for the inputs of ``forward`` (``ref``: the first given; ``ids``:
        it is labels or depth, never channels-last), framed to their source where it is a
        pinhole (``coverage_range``), and that source as `_render` takes it: ``(k,
        camera, (Hs, Ws))``."""
        if isinstance(ref, bool) or not isinstance(ref, Tensor) or ref.dim() < 3:
            raise ValueError(f"image: expected (B, C, H, W) (labels, depth: (B, H, W)), got "
                             f"{tuple(getattr(ref, 'shape', ())) or type(ref).__name__}")
        batch = ref.shape[0]
        size = tuple(ref.shape[1:3] if self.channels_last and not ids else ref.shape[-2:])
        k, camera = self._source(intrinsics, source_camera, size, batch)
        framed = self.coverage_range is not None and k is not None
        return (self._draw_params(batch, generator, k if framed else None,
                                  size if framed else None), (k, camera, size))

    def _check_inputs(self, image, labels, depth):
        """The inputs as ``(B, C, Hs, Ws)`` image, ``(B, Hs, Ws)`` labels and ``(B, 1, Hs, Ws)``
        depth (views), and the source size ``(Hs, Ws)``; raises naming what is wrong."""
        if image is not None:
            if not isinstance(image, Tensor):
                raise TypeError(f"image: expected a tensor, got {type(image).__name__}")
            image = _plain(image)
            if image.dim() != 4:
                layout = "(B, H, W, C)" if self.channels_last else "(B, C, H, W)"
                raise ValueError(f"image: expected {layout} (channels_last="
                                 f"{self.channels_last}), got {tuple(image.shape)}")
            if not (image.is_floating_point() or image.dtype == torch.uint8):
                raise TypeError(f"image: expected a floating-point or uint8 image, got "
                                f"{image.dtype}")
            if self.channels_last:
                image = image.permute(0, 3, 1, 2)
            warn_if_label_map(image, 1)
        if labels is not None:
            labels = _plain(labels)
            if labels.dim() == 4 and labels.shape[1] == 1:
                labels = labels[:, 0]
            if labels.dim() != 3 or labels.is_floating_point() or labels.is_complex():
                raise ValueError(f"labels: expected integer class ids (B, H, W), got "
                                 f"{labels.dtype} {tuple(labels.shape)}")
        if depth is not None:
            depth = _plain(depth)
            if depth.dim() == 3:
                depth = depth.unsqueeze(1)
            if depth.dim() != 4 or depth.shape[1] != 1 or not depth.is_floating_point():
                raise ValueError(f"depth: expected floating planar depth (B, H, W) or "
                                 f"(B, 1, H, W), got {depth.dtype} {tuple(depth.shape)}")
        given = [(name, t) for name, t in (("image", image), ("labels", labels),
                                           ("depth", depth)) if t is not None]
        if not given:
            raise ValueError("render: pass at least one of image, labels, depth")
        ref_name, ref = given[0]
        for name, t in given[1:]:
            if t.shape[0] != ref.shape[0] or t.shape[-2:] != ref.shape[-2:] or \
                    t.device != ref.device:
                raise ValueError(f"{name}: shape {tuple(t.shape)} on {t.device} does not match "
                                 f"{ref_name} {tuple(ref.shape)} on {ref.device} (batch and "
                                 f"image size)")
        return image, labels, depth, tuple(ref.shape[-2:])

    def _source(self, intrinsics: Tensor | None, source_camera: Camera | None,
                size: tuple[int, int], batch: int) -> tuple[Tensor | None, Camera | None]:
        """The source camera of ``batch`` images of ``size``: ``(intrinsics (batch, 4) float64,
        None)`` for a pinhole (the C++ op's own projection), else ``(None, camera (batch,))``
        (its params detached, on the CPU, in their dtype)."""
        if intrinsics is not None and source_camera is not None:
            raise ValueError("source_camera: pass intrinsics or source_camera, not both")
        if intrinsics is None and source_camera is None:
            source_camera = self.source_camera
        if source_camera is None:
            return self._intrinsics(intrinsics, size, batch), None
        if isinstance(source_camera, dict):   # a replay: the record of a render's params
            source_camera = _recorded_camera(source_camera, size)
        _check_source_camera(source_camera)
        if source_camera.image_size != tuple(size):
            raise ValueError(f"source_camera: image_size {source_camera.image_size} does not "
                             f"match the images' {tuple(size)} (scale the camera with the "
                             f"images: fx, fy times s, cx + 0.5 and cy + 0.5 times s)")
        shape = tuple(source_camera.batch_shape)
        if shape not in ((), (batch,)):
            raise ValueError(f"source_camera: expected one camera or a batch of {batch} (the "
                             f"images' batch), got a batch {shape}")
        params = source_camera.params.detach().cpu()
        params = params.expand(batch, params.shape[-1])
        if source_camera.model.name == "pinhole" and source_camera.fov is None and \
                source_camera.blind_fov is None:   # the fast op's own pinhole
            return self._intrinsics(params, size, batch), None
        return None, Camera(source_camera.model, params, size, fov=source_camera.fov,
                            blind_fov=source_camera.blind_fov)

    def _intrinsics(self, intrinsics: Tensor | None, size: tuple[int, int], batch: int
                    ) -> Tensor:
        """``(batch, 4)`` float64 source intrinsics, checked (or from ``source_fov``); a camera
        matrix ``K (batch, 3, 3)`` or ``(3, 3)`` is read as its ``fx, fy, cx, cy``."""
        if intrinsics is None:
            return self.source_intrinsics(size, batch)
        if isinstance(intrinsics, Camera):
            raise TypeError("intrinsics: got an ot.Camera; pass it as source_camera")
        k = torch.as_tensor(intrinsics, dtype=torch.float64).cpu()
        if k.dim() in (2, 3) and k.shape[-2:] == (3, 3):
            if k.dim() == 3 and k.shape[0] != batch:
                raise ValueError(f"intrinsics: a batch of {k.shape[0]} camera matrices K for "
                                 f"{batch} images")
            k = intrinsics_from_matrix(k, "intrinsics")
        if k.dim() == 1:
            k = k.expand(batch, -1)
        if k.shape != (batch, 4) or not bool(torch.isfinite(k).all()) or \
                bool((k[:, :2] <= 0).any()):
            raise ValueError(f"intrinsics: expected finite (B={batch}, 4) or (4,) fx, fy, cx, "
                             f"cy with fx, fy > 0, or K (B={batch}, 3, 3) or (3, 3), got "
                             f"{tuple(k.shape)}")
        return k

    def forward(self, image: Tensor | dict | None, labels: Tensor | None = None,
                depth: Tensor | None = None, *, intrinsics: Tensor | None = None,
                source_camera: Camera | None = None, params: dict | None = None,
                generator: torch.Generator | None = None) -> dict:
        """Draw (or reuse ``params``) and reproject.

        Args:
            image: ``(B, C, H, W)`` (``channels_last``: ``(B, H, W, C)``) floating or ``uint8``
                perspective images, or a dict with the keys ``rgb`` and optionally ``labels``,
                ``depth``, ``intrinsics`` and ``source_camera``, the detection keys
                ``instances`` ``(B, H, W)``, ``boxes`` (per sample ``(N_i, 4)`` XYXY corner
                coordinates), ``box_instance_ids`` (per sample ``(N_i,)``: the exact mode),
                ``keypoints`` ``(B, K, 2)``, ``polygons`` (per sample a list of rings
                ``(N_k, 2)`` corner coordinates or COCO's flat lists) with ``polygon_box``
                (per sample ``(R_i,)``: the box of each ring), and the keys of ``label_keys``
                (``docs/detection.md``); ``tv_tensors.Image`` /
                ``tv_tensors.Mask``
                are taken as the tensors they hold, and their outputs come back in their
                classes (``valid`` as a ``Mask``); an unbatched sample ``(C, H, W)``,
                ``(H, W)`` comes back unbatched, ``params`` per sample
                (`containers`).
            labels: ``(B, H, W)`` integer class ids.
            depth: planar depth ``(B, H, W)``.
            intrinsics: ``(B, 4)`` or ``(4,)`` pinhole ``fx, fy, cx, cy`` of the images, or a
                camera matrix ``K (B, 3, 3)`` or ``(3, 3)`` (zero skew; else ``source_camera``,
                the module's ``source_camera`` or ``source_fov``).
            source_camera: the images' camera, any model of the registry: one
                `Camera` shared by the batch, or a batch ``(B,)`` of one
                model (e.g. ``Camera.load`` of an Aria calibration, or an ``opencv`` camera
                with its distortion).
            params: parameters from ``forward_parameters`` or a previous output, to replay.
            generator: the generator of this call (else the module's).

        Returns:
            dict ``rgb``, ``labels``, ``depth``, ``instances`` and the declared label keys
            (those given), ``valid`` and ``params``; with ``boxes``: ``boxes`` (the same
            structure, each the tight box of its object in the output, clipped to the valid
            area), ``box_index`` (per sample ``(M_i,)`` int64: the input box of each) and
            ``box_visible`` (per sample ``(M_i,)`` bool: False where an outline box's object
            may be out of view); with ``keypoints``: ``keypoints (B, K, 2)`` (NaN where
            invalid) and ``keypoints_valid (B, K)``; with ``polygons``: ``polygons`` (per
            sample a list of rings ``(M_j, 2)``, clipped to the valid area) and
            ``polygon_index`` (per sample ``(M,)`` int64: the input ring of each).
        """
        image, labels, depth, params, wrapping = containers.enter(
            image, labels, depth, params, batch_dims=_IMAGE_DIMS, owner=self)
        targets = _targets(image, self.label_keys, cube=False)
        if isinstance(image, dict):
            image, labels, depth, intrinsics, source_camera = _unpack(
                image, "image", ("rgb", "labels", "depth", "intrinsics", "source_camera"),
                self.label_keys, (None, labels, depth, intrinsics, source_camera), cube=False)
        ref = _reference((image, labels, depth), targets, "image")
        drawn = None
        if params is None:
            params, drawn = self._draw(ref, image is None or ref is not image, intrinsics,
                                       source_camera, generator)
        elif intrinsics is None and source_camera is None:   # a replay: its source camera
            intrinsics = params.get("intrinsics")
            source_camera = params.get("source_camera")
        out = self._render(image, params, drawn, labels=labels, depth=depth,
                           intrinsics=intrinsics, source_camera=source_camera, **targets)
        return containers.leave(out, wrapping)

