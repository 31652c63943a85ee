"""`RandomOmniCamera`: a random omnidirectional camera and attitude per sample of a cubemap
batch."""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import torch
from torch import Tensor

from ..cameras import Camera
from ..cubemap.rotation import check_rotation
from ..render import detection
from ..render import layer as projection
from ..render.kernels.camera import camera_grid
from ..render.layer import OmniProjection
from ..render.reference import check_out_dtype
from . import containers
from .draw import (
    _ANGLE_MARGIN,
    _CUBE_DIMS,
    _DEG,
    _LENS_DEFAULTS,
    MODES,
    _check_range,
    _RandomCameras,
    shared_arguments,
)
from .targets import (
    _check_batches,
    _check_label_keys,
    _grid_rows,
    _label_maps,
    _plain,
    _reference,
    _render_label_maps,
    _runs,
    _targets,
    _unpack,
)


class RandomOmniCamera(_RandomCameras):
    """Per sample, a random omnidirectional camera and attitude; renders the cubemap through it.

    Cameras: the image circle of the drawn field of view ``fov`` is inscribed in the image (as in
    `fisheye` and `catadioptric`):
    ``f = s (min(H, W) / 2 - 0.5) / r1(fov / 2)`` with ``r1`` the model's radius at focal 1 and
    ``s`` drawn in ``focal_scale_range`` (``s > 1`` zooms in and crops the circle); the centre is
    the image centre plus a uniform jitter of at most ``center_jitter`` pixels on each axis.

    * ``mode="fisheye"``: a model drawn uniformly among ``fisheye_models``
      (`FISHEYE_MODELS`: ``equidistant``, ``equisolid``, ``stereographic``,
      ``kannala_brandt``, ``unified``, ``eucm``, ``double_sphere``). Kannala-Brandt draws
      ``k1..k4`` uniformly in ``[-kb_distortion, kb_distortion]`` and halves them until the
      model stays monotonic past ``fov / 2`` (its ``max_angle``; zero, i.e. equidistant, at
      worst), so the distortion is always within the model's valid range. The unified
      (Mei: a fisheye lens, no mirror and no mount rotation here), EUCM and double sphere
      lenses draw their parameters uniformly in their ranges (``unified_xi_range``,
      ``eucm_alpha_range``/``eucm_beta_range``, ``ds_xi_range``/``ds_alpha_range``), and a
      drawn ``fov`` beyond the drawn lens's reach is cut to it (the ``fov`` returned is the
      one rendered).
    * ``mode="catadioptric"``: a ``unified`` camera (xi drawn in ``xi_range``, no lens
      distortion) under or over its mirror (``looking``), with a central ``blind_fov`` cone.
    * ``mode="mixed"``: catadioptric with probability ``catadioptric_prob``, else a fisheye.

    Attitude: roll, pitch, yaw drawn uniformly in their ranges (defaults from the OmniScape
    paper's Table I: roll +-25 deg, pitch +-10 deg, any yaw); ``R = R_att @ R_mount`` (module
    docstring).

    ``p``: the probability, per sample, that the attitude is random; otherwise it is the
    nominal one (roll = pitch = yaw = 0). The camera itself is always drawn (the output is a
    different image from the input in any case). ``same_on_batch``: one draw for the batch.

    Randomness: the ``generator`` passed to a call wins; else the module's own CPU generator
    (`generator`), which follows PyTorch's own seeding of ``DataLoader`` workers (each
    worker's ``torch.initial_seed()`` is ``base_seed + worker_id``, ``base_seed`` drawn afresh
    for every iterator, i.e. every epoch, from ``DataLoader(generator=...)`` or else from the
    global RNG):

    * Outside ``DataLoader`` workers (``num_workers=0``, the training loop): one stream, started
      on first use from ``seed`` (``torch.initial_seed()`` when ``seed`` is None) and continued
      across calls and epochs, so epochs differ.
    * Inside a worker: the generator is tied to the worker process and its torch seed. A worker
      that finds none made there (the module is new, was used in the main process before the
      workers started, or comes from an earlier epoch's workers, forked or pickled) starts one
      from a hash of ``seed`` and ``torch.initial_seed()`` (``numpy.random.SeedSequence``). So
      workers draw different streams, each epoch of non-persistent workers draws new ones, and
      persistent workers continue theirs across epochs.
    * `reseed` (e.g. in a ``worker_init_fn``) pins the stream to a seed in the process
      and worker it is called in.

    A run is reproduced by the same ``seed`` and the same
    ``DataLoader(generator=torch.Generator().manual_seed(s))`` (or the same ``torch.manual_seed``
    before the ``DataLoader``'s iterators are made), with the same worker count and order of
    samples; the multiprocessing context (fork, spawn, forkserver) does not change the draws.
    No global RNG is consumed. The module pickles with its generator's state. A process forked
    by other means than a ``DataLoader`` inherits the stream as it was (as NumPy's and torch's
    global generators are): reseed there. On the CPU every pixel's ray comes from a table per
    camera inside the C++ sampling pass (``fast.sample_camera``; nothing compiles at run time),
    so ``DataLoader`` workers render as fast as the main process.

    Args:
        image_size: ``(H, W)`` of the output.
        face_size: ``F``, texels per cube face side of the input.
        mode: ``"fisheye"``, ``"catadioptric"`` or ``"mixed"``.
        fisheye_models: fisheye model names drawn from.
        fov_range: ``(min, max)`` full fisheye field of view, radians (default 160-200 deg).
        kb_distortion: bound of the Kannala-Brandt coefficients.
        unified_xi_range: ``(min, max)`` of the unified (Mei) fisheye lens's xi (defaults
            for this and the next four: typical fisheye lenses; Usenko et al. 2018 fit EUCM
            alpha 0.63, beta 1.04 and double sphere xi -0.2, alpha 0.59 to theirs).
        eucm_alpha_range: ``(min, max)`` of the EUCM fisheye lens's alpha.
        eucm_beta_range: ``(min, max)`` of the EUCM fisheye lens's beta.
        ds_xi_range: ``(min, max)`` of the double sphere fisheye lens's xi.
        ds_alpha_range: ``(min, max)`` of the double sphere fisheye lens's alpha.
        cata_fov_range: ``(min, max)`` full catadioptric field of view, radians (default 200-230
            deg; must stay below ``2 acos(-xi)`` for every xi in ``xi_range``).
        xi_range: ``(min, max)`` mirror parameter of the unified model (default 0.7-1.0).
        blind_fov: full angle of the catadioptric blind cone, radians, or None.
        looking: catadioptric mount, ``"down"`` (under its mirror, roof mount) or ``"up"``.
        catadioptric_prob: probability of a catadioptric camera in ``"mixed"`` mode.
        focal_scale_range: ``(min, max)`` focal multiplier.
        center_jitter: maximum centre offset in pixels, on each axis.
        roll_range: ``(min, max)`` radians.
        pitch_range: ``(min, max)`` radians.
        yaw_range: ``(min, max)`` radians.
        p: probability of a random attitude per sample.
        same_on_batch: draw one camera and attitude for the whole batch.
        interpolation: RGB interpolation of ``OmniProjection``.
        depth_output: ``"range"`` or ``"z"`` (see ``OmniProjection.render``).
        ignore_index: label of invalid pixels.
        seed: seed of the module's generator (see above), ``-2**63 <= seed < 2**64``.
        channels_last: the RGB cubemap is ``(B, 6, F, F, C)`` (channels innermost, as image
            files and simulators give faces) and ``rgb`` comes back ``(B, H, W, C)``; read
            without a copy (``OmniProjection.render``'s ``channels_last``).
        out_dtype: dtype of ``rgb``: None for the cubemap's (a ``uint8`` cube gives a ``uint8``
            image, blended in float32 and rounded to nearest, half up), or a floating dtype (a
            ``uint8`` cube is then scaled to [0, 1] in the same pass). ``torch.uint8`` is
            accepted for ``uint8`` cubes only.
        label_keys: ``{key: ignore value}``: more label-like keys the dicts may hold (e.g.
            ``{"parts": 255}``), each carried as ``labels`` are (nearest, int64 ids of any
            range) with its own value outside the valid area (``docs/detection.md``).
        backend: the kernels' route (``render.kernels``): ``"auto"`` (the C++ ops on the CPU
            without gradients, else torch), ``"cpp"`` or ``"torch"``.
        camera: a fixed target camera (an ``ot.Camera``, or a calibration file's path that
            ``Camera.load`` reads, e.g. WoodScape's ``front.json``) instead of a drawn lens:
            ``image_size`` may then be None (the camera's); ``focal_jitter`` and
            ``center_jitter`` perturb its parameters, the attitude ranges its attitude; the
            lens arguments and ``mode`` are not used. Without jitter (every range 0) its image
            is ``OmniProjection(camera, face_size)``'s, to the float32 rounding of the grid
            (the camera's rays come from its radius table here, within 0.005 texel).
        focal_jitter: with ``camera``: its focal (``fx, fy``; the pixel polynomial of
            ``woodscape`` and ``scaramuzza``) scaled by a factor drawn in
            ``[1 - focal_jitter, 1 + focal_jitter]``.

    Shapes:
        cubemap ``(B, 6, C, F, F)`` (``channels_last``: ``(B, 6, F, F, C)``) floating or
        ``uint8``, labels ``(B, 6, F, F)``, depth ``(B, 6, F, F)`` planar -> ``rgb (B, C, H, W)``
        (``channels_last``: ``(B, H, W, C)``) in ``out_dtype``, ``labels (B, H, W)`` int64,
        ``depth (B, 1, H, W)``, ``valid (B, 1, H, W)`` bool. The drawn parameters do not depend
        on the cubemap's dtype or layout: a seed gives the same cameras for all of them.

    Examples:
        >>> aug = RandomOmniCamera((32, 32), 16, seed=0)
        >>> out = aug(torch.rand(2, 6, 3, 16, 16))
        >>> out["rgb"].shape, out["params"]["camera_params"].shape
        (torch.Size([2, 3, 32, 32]), torch.Size([2, 9]))
    """

    def __init__(self, image_size: tuple[int, int] | None, face_size: int, *,
                 mode: str = "fisheye",
                 fisheye_models: Sequence[str] = ("equidistant",),
                 fov_range: tuple[float, float] = (160 * _DEG, 200 * _DEG),
                 kb_distortion: float = 0.02,
                 unified_xi_range: tuple[float, float] = _LENS_DEFAULTS["unified_xi_range"],
                 eucm_alpha_range: tuple[float, float] = _LENS_DEFAULTS["eucm_alpha_range"],
                 eucm_beta_range: tuple[float, float] = _LENS_DEFAULTS["eucm_beta_range"],
                 ds_xi_range: tuple[float, float] = _LENS_DEFAULTS["ds_xi_range"],
                 ds_alpha_range: tuple[float, float] = _LENS_DEFAULTS["ds_alpha_range"],
                 cata_fov_range: tuple[float, float] = (200 * _DEG, 230 * _DEG),
                 xi_range: tuple[float, float] = (0.7, 1.0),
                 blind_fov: float | None = 40 * _DEG, looking: str = "down",
                 catadioptric_prob: float = 0.5,
                 focal_scale_range: tuple[float, float] = (1.0, 1.0),
                 center_jitter: float = 0.0,
                 roll_range: tuple[float, float] = (-25 * _DEG, 25 * _DEG),
                 pitch_range: tuple[float, float] = (-10 * _DEG, 10 * _DEG),
                 yaw_range: tuple[float, float] = (-math.pi, math.pi),
                 p: float = 1.0, same_on_batch: bool = False,
                 interpolation: str = "bilinear", depth_output: str = "range",
                 ignore_index: int = 255, seed: int | None = None,
                 channels_last: bool = False, out_dtype: torch.dtype | None = None,
                 label_keys: Mapping[str, int] | None = None, backend: str = "auto",
                 camera: object = None, focal_jitter: float = 0.0) -> None:
        super().__init__(image_size, **shared_arguments(locals()))
        if isinstance(face_size, bool) or not isinstance(face_size, int) or face_size < 1:
            raise ValueError(f"face_size: expected a positive int, got {face_size!r}")
        if mode not in MODES:
            raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
        if looking not in ("down", "up"):
            raise ValueError(f"looking: expected 'down' or 'up', got {looking!r}")
        if isinstance(catadioptric_prob, bool) or not isinstance(
                catadioptric_prob, (int, float)) or not 0 <= catadioptric_prob <= 1:
            raise ValueError(f"catadioptric_prob: expected a probability in [0, 1], got "
                             f"{catadioptric_prob!r}")
        self.face_size = face_size
        self.mode = mode
        self.cata_fov_range = _check_range(cata_fov_range, "cata_fov_range", 0.0, 2 * math.pi)
        self.xi_range = _check_range(xi_range, "xi_range", 0.0, 1.0)
        self.blind_fov = None if blind_fov is None else float(blind_fov)
        self.looking = looking
        self.catadioptric_prob = float(catadioptric_prob)
        self.label_keys = _check_label_keys(label_keys)
        self._check_ranges()

    def _check_ranges(self) -> None:
        """Fail at construction, not mid-training, if a range leaves a model's domain."""
        if self.camera is not None:   # a fixed camera: no lens drawn
            return
        if self.mode != "catadioptric":
            self._check_fisheye_ranges()
        if self.mode != "fisheye":
            xi = self.xi_range[0]   # the smallest xi sees the least far
            limit = math.acos(-xi)
            if 0.5 * self.cata_fov_range[1] > limit - _ANGLE_MARGIN:
                raise ValueError(f"cata_fov_range: a unified camera with xi = {xi} sees at most "
                                 f"{2 * limit / _DEG:.1f} deg, the range reaches "
                                 f"{self.cata_fov_range[1] / _DEG:.1f} deg")
            if self.blind_fov is not None and not 0 < self.blind_fov < self.cata_fov_range[0]:
                raise ValueError(f"blind_fov: expected in (0, min cata fov), got {self.blind_fov}")

    def extra_repr(self) -> str:
        return (f"image_size={self.image_size}, face_size={self.face_size}, mode={self.mode!r}, "
                f"p={self.p}, same_on_batch={self.same_on_batch}, seed={self.seed}, "
                f"channels_last={self.channels_last}, out_dtype={self.out_dtype}")

    # ---------------------------------------------------------------------------------------
    # Parameters
    # ---------------------------------------------------------------------------------------
    @torch.no_grad()
    def forward_parameters(self, batch_size: int, *, generator: torch.Generator | None = None
                           ) -> dict:
        """Draw cameras and attitudes for ``batch_size`` samples (kornia's name for it).

        Returns:
            dict, tensors float64 on the CPU: ``model`` (tuple of ``B`` model names),
            ``camera_params (B, 9)`` (zero-padded to the largest model's parameter count, so
            the default ``collate_fn`` stacks per-sample draws of different models),
            ``num_params (B,)``, ``fov (B,)`` and ``blind_fov (B,)`` (radians, 0 for none),
            ``yaw``, ``pitch``, ``roll (B,)``, ``applied (B,)`` bool (random attitude),
            ``rotation (B, 3, 3)`` camera -> cube frame.
        """
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size: expected a positive int, got {batch_size!r}")
        return self._draw_params(batch_size, generator)

    # ---------------------------------------------------------------------------------------
    # Rendering
    # ---------------------------------------------------------------------------------------
    def render(self, cubemap: Tensor | None, params: dict, *, labels: Tensor | None = None,
               depth: Tensor | None = None, instances: Tensor | None = None,
               box_instance_ids: Sequence[Tensor] | None = None,
               keypoints: Tensor | None = None, label_maps: Mapping[str, Tensor] | None = None
               ) -> dict:
        """Render the modalities and the detection targets through the cameras and rotations
        of ``params``.

        Args:
            cubemap: ``(B, 6, C, F, F)`` (``channels_last``: ``(B, 6, F, F, C)``), floating or
                ``uint8``, or None.
            params: parameters from ``forward_parameters``.
            labels: as for ``forward``.
            depth: as for ``forward``.
            instances: ``(B, 6, F, F)`` integer instance ids (0: none), any range.
            box_instance_ids: per sample the ``(N_i,)`` instance ids to box (needs
                ``instances``).
            keypoints: ``(B, K, 3)`` rows ``(face, x, y)``: a face index (``FACES`` order) and
                corner coordinates on it.
            label_maps: the declared label keys' cubemaps (``label_keys``), by key.

        Returns:
            the dict of ``forward``.
        """
        maps = _label_maps(self.label_keys, instances, label_maps, cube=True,
                           size=(self.face_size, self.face_size))
        _check_batches(params, **dict(
            (key, t) for key, (t, _) in maps.items()), box_instance_ids=box_instance_ids,
            keypoints=keypoints)
        if keypoints is not None:
            keypoints = detection.check_keypoints(keypoints, len(params["model"]), 3)
        ids = None
        if box_instance_ids is not None:
            if instances is None:
                raise ValueError("box_instance_ids: needs instances (a cube has no 2D boxes: "
                                 "boxes come from its instance ids)")
            ids = detection.check_box_ids(box_instance_ids, None, len(params["model"]))
        result = {}
        if any(t is not None for t in (cubemap, labels, depth)):
            result = self._render_maps(cubemap, params, labels=labels, depth=depth)
        _render_label_maps(result, maps, lambda ids: self._render_maps(None, params, labels=ids))
        if ids is not None:
            result.update(detection.boxes_of_instances(result["instances"], ids,
                                                       _plain(instances)))
        if keypoints is not None:
            cube = detection.Side(None, None, None)
            result.update(detection.map_targets(
                self._changes(result["params"], cube), len(params["model"]),
                keypoints=detection.cube_points(keypoints, self.face_size)))
        return result

    def _render_maps(self, cubemap: Tensor | None, params: dict, *,
                     labels: Tensor | None = None, depth: Tensor | None = None) -> dict:
        """`render` of the modalities alone (``valid``, ``rgb``, ``labels``, ``depth``,
        ``params``)."""
        rgb_dtype = self._check_cubemap(cubemap)
        ref = next((t for t in (cubemap, depth, labels) if t is not None), None)
        if ref is None:
            raise ValueError("render: pass at least one of cubemap, labels, depth")
        batch = ref.shape[0]
        if len(params["model"]) != batch:
            raise ValueError(f"params: drawn for {len(params['model'])} samples, the batch has "
                             f"{batch}")
        check_rotation(params["rotation"], 'params["rotation"]')
        dtype = ref.dtype if ref.is_floating_point() and ref.dtype == torch.float64 \
            else torch.float32
        device = ref.device
        # on the CPU a few samples at a time (projection.CHUNK_PIXELS)
        chunk = batch if device.type != "cpu" else max(1, projection.CHUNK_PIXELS // math.prod(
            self.image_size))
        result: dict[str, Tensor] = {}
        # the layer refuses these without rgb: a labels- or depth-only call ignores them
        rgb_options = {} if cubemap is None else dict(out_dtype=rgb_dtype,
                                                      channels_last=self.channels_last)
        cameras = self.cameras(params, dtype, device)
        if len(cameras) > 1 or chunk < batch:   # several parts: outputs allocated once
            h, w = self.image_size   # the outputs of OmniProjection.render
            shapes = {"valid": ((1, h, w), torch.bool)}
            if cubemap is not None:
                shapes["rgb"] = (((h, w, cubemap.shape[4]) if self.channels_last
                                  else (cubemap.shape[2], h, w)), rgb_dtype)
            if labels is not None:
                shapes["labels"] = ((h, w), torch.int64)
            if depth is not None:
                shapes["depth"] = ((1, h, w), depth.dtype)
            result = {key: torch.empty((batch, *shape), dtype=out_dtype, device=device)
                      for key, (shape, out_dtype) in shapes.items()}
        for name, (idx, camera) in cameras.items():
            # the grid of every pixel, with the sample's rotation and field-of-view cones: on
            # the CPU the cameras' tables, made for the model's samples at once, their rays a
            # chunk at a time and the taps in the sampling pass
            whole = camera_grid(
                name, camera.params, self.image_size, self.face_size,
                projection.pad_for(self.interpolation),
                rotation=params["rotation"][idx].to(dtype=dtype, device=device),
                fov=params["fov"][idx].to(dtype=dtype, device=device),
                blind_fov=params["blind_fov"][idx].to(dtype=dtype, device=device), lazy=True,
                backend=self.backend)
            for start in range(0, len(idx), chunk):
                part = slice(start, start + chunk)
                cam = camera if len(idx) <= chunk else Camera(name, camera.params[part],
                                                              self.image_size)
                sel = idx[part]
                proj = OmniProjection(cam, self.face_size, interpolation=self.interpolation,
                                      ignore_index=self.ignore_index, backend=self.backend)
                grid = _grid_rows(whole, start, start + chunk)
                if not result:   # one part, the whole batch: the layer allocates
                    result = proj.render(rgb=cubemap, labels=labels, depth=depth,
                                         depth_output=self.depth_output, grid=grid,
                                         **rgb_options)
                    continue
                # each run of consecutive samples as views of the inputs and of the outputs'
                # rows (mixed models: several runs), so that nothing is copied
                for a, b, first in _runs(sel.tolist()):
                    at = slice(first, first + b - a)
                    inputs = {key: None if t is None else t[at] for key, t in
                              (("rgb", cubemap), ("labels", labels), ("depth", depth))}
                    layer = proj if b - a == len(sel) else OmniProjection(
                        Camera(name, cam.params[a:b], self.image_size), self.face_size,
                        interpolation=self.interpolation, ignore_index=self.ignore_index,
                        backend=self.backend)
                    layer.render(**inputs, depth_output=self.depth_output,
                                 grid=_grid_rows(grid, a, b),
                                 **rgb_options,
                                 out={key: value[at] for key, value in result.items()})
        result["params"] = params
        return result

    def _check_cubemap(self, cubemap: object, unbatched: bool = False) -> torch.dtype | None:
        """The dtype of the ``rgb`` image of ``cubemap`` (None without one). Raises for a cube
        not laid out as ``channels_last`` says (naming the flag that fits), or of a dtype the
        layer refuses. ``unbatched``: ``forward`` was given one sample, batched since: the
        message shows the shape as passed."""
        if cubemap is None:
            return None
        if not isinstance(cubemap, Tensor):
            raise TypeError(f"cubemap: expected a tensor, got {type(cubemap).__name__}")
        if not (cubemap.is_floating_point() or cubemap.dtype == torch.uint8):
            raise TypeError(f"cubemap: expected a floating-point or uint8 cubemap, got "
                            f"{cubemap.dtype}")
        f = self.face_size
        layout = "(B, 6, F, F, C)" if self.channels_last else "(B, 6, C, F, F)"
        face_dims = (2, 3) if self.channels_last else (3, 4)
        shape = tuple(cubemap.shape)
        if (len(shape) != 5 or shape[1] != 6
                or tuple(shape[d] for d in face_dims) != (f, f)):
            other = (3, 4) if self.channels_last else (2, 3)   # the other layout's face dims
            hint = ""
            if len(shape) == 5 and shape[1] == 6 and tuple(shape[d] for d in other) == (f, f):
                hint = (f"; it looks {'channels-first' if self.channels_last else 'channels-last'}"
                        f": construct with channels_last={not self.channels_last}")
            if unbatched:   # the shape as passed: one sample, (6, C, F, F)
                layout, shape = "(6, C, F, F) or " + layout, shape[1:]
            raise ValueError(f"cubemap: expected shape {layout} with F = face_size = {f} "
                             f"(channels_last={self.channels_last}), got {shape}{hint}")
        return check_out_dtype(cubemap.dtype, self.out_dtype)   # the layer checks for ids

    def forward(self, cubemap: Tensor | dict | None, labels: Tensor | None = None,
                depth: Tensor | None = None, *, params: dict | None = None,
                generator: torch.Generator | None = None) -> dict:
        """Draw (or reuse ``params``, kornia style) and render.

        Args:
            cubemap: ``(B, 6, C, F, F)`` (``channels_last``: ``(B, 6, F, F, C)``) floating or
                ``uint8``, or a dict with keys ``rgb`` and optionally ``labels`` and ``depth``
                (so the module can start an ``nn.Sequential``), and the detection keys
                ``instances`` ``(B, 6, F, F)`` (ids, 0: none), ``box_instance_ids`` (per sample
                the ids to box) and ``keypoints`` ``(B, K, 3)`` rows ``(face, x, y)``, and the
                keys of ``label_keys`` (``docs/detection.md``). Tensor subclasses
                (torchvision's ``tv_tensors.Image``, ``Mask``) are read as the tensors they
                hold, and their outputs come back in their classes (``valid`` as a ``Mask``);
                an unbatched sample ``(6, C, F, F)``, ``(6, F, F)`` comes back unbatched
                (`containers`).
            labels: ``(B, 6, F, F)`` integer class ids.
            depth: ``(B, 6, F, F)`` planar depth, metres.
            params: parameters from ``forward_parameters`` or a previous output, to replay.
            generator: the generator of this call (else the module's).

        Returns:
            dict ``rgb``, ``labels``, ``depth``, ``instances`` and the declared label keys
            (those given), ``valid`` and ``params``; with ``box_instance_ids``: ``boxes`` (per
            sample ``(M_i, 4)`` XYXY corner coordinates, the tight box of the id's output
            pixels) and ``box_index`` (per sample ``(M_i,)``: positions in
            ``box_instance_ids``); with ``keypoints``: ``keypoints (B, K, 2)`` corner
            coordinates (NaN where invalid) and ``keypoints_valid (B, K)``.
        """
        cubemap, labels, depth, params, wrapping = containers.enter(
            cubemap, labels, depth, params, batch_dims=_CUBE_DIMS, owner=self)
        targets = _targets(cubemap, self.label_keys, cube=True)
        if isinstance(cubemap, dict):
            cubemap, labels, depth = _unpack(cubemap, "cubemap", ("rgb", "labels", "depth"),
                                             self.label_keys, (None, labels, depth), cube=True)
        ref = _reference((cubemap, labels, depth), targets, "cubemap")
        if wrapping.unbatched:   # checked here, where the shape passed is known
            self._check_cubemap(cubemap, unbatched=True)
        if params is None:
            params = self.forward_parameters(ref.shape[0], generator=generator)
        out = self.render(cubemap, params, labels=labels, depth=depth, **targets)
        return containers.leave(out, wrapping)


