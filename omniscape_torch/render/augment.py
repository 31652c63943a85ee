"""Random omnidirectional cameras and vehicle attitudes: cubemap batch -> augmented omni batch.

``RandomOmniCamera`` draws, per sample of a cubemap batch, a camera (a fisheye of a chosen model,
or a catadioptric camera; field of view, focal, distortion and centre in configurable ranges)
and an attitude (roll, pitch, yaw), renders RGB, labels, depth and the valid mask through
:class:`~omniscape_torch.OmniProjection`, and returns them with the drawn parameters, so that a
run can be replayed and geometry-aware losses can use the cameras.

Conventions follow kornia's augmentations: ``forward(input, params=None)`` draws parameters
with ``forward_parameters`` (or reuses the given ones) and applies them with ``render``; ``p``
and ``same_on_batch`` have kornia's meaning (see the class docstring for what ``p`` gates here).

Randomness comes only from a ``torch.Generator``: the one passed to a call, else the module's
own, seeded from ``seed`` and, inside a ``DataLoader`` worker, from PyTorch's per-worker seed
(class docstring of ``RandomOmniCamera``). Parameters are drawn in float64 on the CPU, so a seed
gives the same cameras on any device.

Attitude (rig convention of :mod:`omniscape_torch.cameras.presets`): ``R = R_att @ R_mount`` with
``R_att = yaw_pitch_roll_to_matrix(yaw, pitch, roll)`` the vehicle's attitude relative to the
cube frame and ``R_mount`` the camera's mount on the vehicle (identity for a forward fisheye,
the "down" or "up" face's rotation for a catadioptric camera), ``ray_cube = R @ ray_cam``.
"""

from __future__ import annotations

import math
import os
from typing import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ..cameras import Camera
from ..cameras.registry import get_model
from ..cubemap.faces import FACES, face_rotations
from ..cubemap.rotation import check_rotation
from .fast import CameraGrid
from .kernels import camera_grid
from ..cameras.presets import yaw_pitch_roll_to_matrix
from . import layer as projection
from .layer import OmniProjection
from .reference import check_out_dtype

__all__ = ["ApplyToKey", "RandomOmniCamera"]

FISHEYE_MODELS = ("equidistant", "equisolid", "stereographic", "kannala_brandt")
MODES = ("fisheye", "catadioptric", "mixed")
_DEG = math.pi / 180
#: Largest parameter count of the models drawn here (unified: fx, fy, cx, cy, xi, k1, k2, p1, p2):
#: the width of ``camera_params``, whatever the models drawn.
_MAX_P = 9
#: Kannala-Brandt coefficients are halved (at most this many times, then zeroed) until the
#: polynomial stays monotonic past the drawn half field of view.
_KB_SHRINK_STEPS = 8
#: Margin (radians) kept between the drawn half field of view and a model's ``max_angle``.
_ANGLE_MARGIN = 1e-3


def _context_key() -> tuple[int, int] | None:
    """Where the module's generator is valid: None in a process that is no ``DataLoader``
    worker; inside a worker ``(process id, torch.initial_seed())``, which changes with every new
    worker process (PyTorch seeds a worker with ``base_seed + worker_id``, ``base_seed`` drawn
    per iterator) and stays for a persistent worker's life."""
    if torch.utils.data.get_worker_info() is None:
        return None
    return os.getpid(), torch.initial_seed()


def _worker_seed(seed: int | None, initial_seed: int) -> int:
    """The 64-bit seed of the module's generator in a ``DataLoader`` worker whose torch seed is
    ``initial_seed``: NumPy's ``SeedSequence`` hash of both (stable across processes, Python
    versions and platforms, unlike ``hash``), so neighbouring worker seeds give unrelated
    streams, and none repeats the worker's global torch stream (kornia draws from that).
    The 0/1 word keeps ``seed=None`` apart from every int seed (``SeedSequence`` pads the
    entropy with zeros, so ``[a]`` and ``[a, 0]`` would collide)."""
    entropy = [initial_seed, 0] if seed is None else [initial_seed, 1, seed % 2 ** 64]
    high, low = np.random.SeedSequence(entropy).generate_state(2, dtype=np.uint32)
    return (int(high) << 32) | int(low)


def _check_seed(seed: object) -> None:
    """The seeds ``torch.Generator.manual_seed`` takes (``-2**63 <= seed < 2**64``)."""
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"seed: expected an int or None, got {seed!r}")
    if not -2 ** 63 <= seed < 2 ** 64:
        raise ValueError(f"seed: expected -2**63 <= seed < 2**64, got {seed}")


def _check_range(value, name: str, low: float = -math.inf, high: float = math.inf
                 ) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a (min, max) pair of numbers, got {value!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)) or a > b or a < low or b > high:
        raise ValueError(f"{name}: expected finite min <= max within [{low}, {high}], got "
                         f"{(a, b)}")
    return a, b


def _uniform(n: int, bounds: tuple[float, float], generator: torch.Generator) -> Tensor:
    """``(n,)`` float64 uniform draws in ``[lo, hi]`` (exactly ``lo`` when ``lo == hi``)."""
    lo, hi = bounds
    u = torch.rand(n, generator=generator, dtype=torch.float64)
    return lo + (hi - lo) * u


def _unit_radius(model: str, extra: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    """Image radius at focal 1 of rays ``theta (n,)`` from the axis, and its validity, for the
    model's parameters after (fx, fy, cx, cy) ``extra (n, E)`` (float64)."""
    n = theta.shape[0]
    head = torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64).expand(n, 4)
    params = torch.cat((head, extra), dim=-1)
    points = torch.stack((torch.sin(theta), torch.zeros_like(theta), torch.cos(theta)), -1)
    pixels, valid = get_model(model).project(points, params)
    radius = torch.linalg.vector_norm(pixels, dim=-1)
    return radius, valid & (radius > 0) & torch.isfinite(radius)


class RandomOmniCamera(nn.Module):
    """Per sample, a random omnidirectional camera and attitude; renders the cubemap through it.

    Cameras: the image circle of the drawn field of view ``fov`` is inscribed in the image (as in
    :func:`~omniscape_torch.cameras.presets.fisheye` and :func:`~omniscape_torch.cameras.presets.catadioptric`):
    ``f = s (min(H, W) / 2 - 0.5) / r1(fov / 2)`` with ``r1`` the model's radius at focal 1 and
    ``s`` drawn in ``focal_scale_range`` (``s > 1`` zooms in and crops the circle); the centre is
    the image centre plus a uniform jitter of at most ``center_jitter`` pixels on each axis.

    * ``mode="fisheye"``: a model drawn uniformly among ``fisheye_models`` (``equidistant``,
      ``equisolid``, ``stereographic``, ``kannala_brandt``). Kannala-Brandt draws
      ``k1..k4`` uniformly in ``[-kb_distortion, kb_distortion]`` and halves them until the
      model stays monotonic past ``fov / 2`` (its ``max_angle``; zero, i.e. equidistant, at
      worst), so the distortion is always within the model's valid range.
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
    (:attr:`generator`), which follows PyTorch's own seeding of ``DataLoader`` workers (each
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
    * :meth:`reseed` (e.g. in a ``worker_init_fn``) pins the stream to a seed in the process
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
        cata_fov_range: ``(min, max)`` full catadioptric field of view, radians (default 200-230
            deg; must stay below ``2 acos(-xi)`` for every xi in ``xi_range``).
        xi_range: ``(min, max)`` mirror parameter of the unified model (default 0.7-1.0).
        blind_fov: full angle of the catadioptric blind cone, radians, or None.
        looking: catadioptric mount, ``"down"`` (under its mirror, roof mount) or ``"up"``.
        catadioptric_prob: probability of a catadioptric camera in ``"mixed"`` mode.
        focal_scale_range: ``(min, max)`` focal multiplier.
        center_jitter: maximum centre offset in pixels, on each axis.
        roll_range, pitch_range, yaw_range: ``(min, max)`` radians.
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

    Shapes:
        cubemap ``(B, 6, C, F, F)`` (``channels_last``: ``(B, 6, F, F, C)``) floating or
        ``uint8``, labels ``(B, 6, F, F)``, depth ``(B, 6, F, F)`` planar -> ``rgb (B, C, H, W)``
        (``channels_last``: ``(B, H, W, C)``) in ``out_dtype``, ``labels (B, H, W)`` int64,
        ``depth (B, 1, H, W)``, ``valid (B, 1, H, W)`` bool. The drawn parameters do not depend
        on the cubemap's dtype or layout: a seed gives the same cameras for all of them.

    Example:
        >>> aug = RandomOmniCamera((32, 32), 16, seed=0)
        >>> out = aug(torch.rand(2, 6, 3, 16, 16))
        >>> out["rgb"].shape, out["params"]["camera_params"].shape
        (torch.Size([2, 3, 32, 32]), torch.Size([2, 9]))
    """

    def __init__(self, image_size: tuple[int, int], face_size: int, *, mode: str = "fisheye",
                 fisheye_models: Sequence[str] = ("equidistant",),
                 fov_range: tuple[float, float] = (160 * _DEG, 200 * _DEG),
                 kb_distortion: float = 0.02,
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
                 channels_last: bool = False, out_dtype: torch.dtype | None = None) -> None:
        super().__init__()
        try:
            h, w = (int(v) for v in image_size)
        except (TypeError, ValueError):
            raise ValueError(f"image_size: expected (H, W), got {image_size!r}") from None
        if min(h, w) < 2:
            raise ValueError(f"image_size: needs at least 2 x 2 pixels, got {(h, w)}")
        if isinstance(face_size, bool) or not isinstance(face_size, int) or face_size < 1:
            raise ValueError(f"face_size: expected a positive int, got {face_size!r}")
        if mode not in MODES:
            raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
        if isinstance(fisheye_models, str):
            fisheye_models = (fisheye_models,)
        fisheye_models = tuple(fisheye_models)
        if not fisheye_models or any(m not in FISHEYE_MODELS for m in fisheye_models):
            raise ValueError(f"fisheye_models: expected names among {FISHEYE_MODELS}, got "
                             f"{fisheye_models!r}")
        if looking not in ("down", "up"):
            raise ValueError(f"looking: expected 'down' or 'up', got {looking!r}")
        for name, value in (("p", p), ("catadioptric_prob", catadioptric_prob)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not 0 <= value <= 1:
                raise ValueError(f"{name}: expected a probability in [0, 1], got {value!r}")
        if not (isinstance(kb_distortion, (int, float)) and 0 <= kb_distortion < 1):
            raise ValueError(f"kb_distortion: expected a number in [0, 1), got {kb_distortion!r}")
        if not (isinstance(center_jitter, (int, float)) and 0 <= center_jitter < min(h, w) / 2):
            raise ValueError(f"center_jitter: expected pixels in [0, min(H, W) / 2), got "
                             f"{center_jitter!r}")
        if seed is not None:
            _check_seed(seed)
        if not isinstance(channels_last, bool):
            raise TypeError(f"channels_last: expected a bool, got {channels_last!r}")
        if out_dtype is not None and not (isinstance(out_dtype, torch.dtype) and (
                out_dtype.is_floating_point or out_dtype == torch.uint8)):
            raise TypeError(f"out_dtype: expected None, torch.uint8 or a floating dtype, got "
                            f"{out_dtype!r}")
        self.image_size = (h, w)
        self.face_size = face_size
        self.mode = mode
        self.fisheye_models = fisheye_models
        self.fov_range = _check_range(fov_range, "fov_range", 0.0, 2 * math.pi)
        self.kb_distortion = float(kb_distortion)
        self.cata_fov_range = _check_range(cata_fov_range, "cata_fov_range", 0.0, 2 * math.pi)
        self.xi_range = _check_range(xi_range, "xi_range", 0.0, 1.0)
        self.blind_fov = None if blind_fov is None else float(blind_fov)
        self.looking = looking
        self.catadioptric_prob = float(catadioptric_prob)
        self.focal_scale_range = _check_range(focal_scale_range, "focal_scale_range", 1e-3)
        self.center_jitter = float(center_jitter)
        self.roll_range = _check_range(roll_range, "roll_range")
        self.pitch_range = _check_range(pitch_range, "pitch_range")
        self.yaw_range = _check_range(yaw_range, "yaw_range")
        self.p = float(p)
        self.same_on_batch = bool(same_on_batch)
        self.interpolation = interpolation
        self.depth_output = depth_output
        self.ignore_index = int(ignore_index)
        self.seed = seed
        self.channels_last = channels_last
        self.out_dtype = out_dtype
        self._generator: torch.Generator | None = None
        self._generator_key: tuple[int, int] | None = None   # _context_key() it was made in
        self._check_ranges()

    def _check_ranges(self) -> None:
        """Fail at construction, not mid-training, if a range leaves a model's domain."""
        if self.mode != "catadioptric":
            half = torch.tensor([0.5 * self.fov_range[1]], dtype=torch.float64)
            for name in self.fisheye_models:
                extra = torch.zeros(1, 4 if name == "kannala_brandt" else 0, dtype=torch.float64)
                _, ok = _unit_radius(name, extra, half)
                limit = float(get_model(name).max_angle(
                    torch.cat((torch.ones(1, 4, dtype=torch.float64), extra), -1)))
                if not bool(ok) or half.item() > limit - _ANGLE_MARGIN:
                    raise ValueError(f"fov_range: the {name} model sees at most "
                                     f"{2 * limit / _DEG:.1f} deg, fov_range reaches "
                                     f"{2 * half.item() / _DEG:.1f} deg")
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
    # Randomness
    # ---------------------------------------------------------------------------------------
    @property
    def generator(self) -> torch.Generator:
        """The module's CPU generator for the current process and ``DataLoader`` worker, made on
        first use there (class docstring): from ``seed`` (or ``torch.initial_seed()``) outside
        workers, from a hash of ``seed`` and ``torch.initial_seed()`` inside one."""
        key = _context_key()
        if self._generator is None or self._generator_key != key:
            if key is None:
                seed = torch.initial_seed() if self.seed is None else self.seed
            else:
                seed = _worker_seed(self.seed, key[1])
            self._generator = torch.Generator().manual_seed(seed)
            self._generator_key = key
        return self._generator

    def reseed(self, seed: int) -> None:
        """Restart the module's generator from ``seed`` exactly, for the current process and
        ``DataLoader`` worker (e.g. in a ``worker_init_fn``, where a seed made from
        ``torch.initial_seed()`` keeps epochs and workers apart; a constant one repeats them).
        ``seed`` also becomes the module's ``seed`` for the workers it is later copied into."""
        _check_seed(seed)
        self.seed = int(seed)
        self._generator = torch.Generator().manual_seed(self.seed)
        self._generator_key = _context_key()

    def __getstate__(self) -> dict:
        # The generator travels as the bytes of its state. Not as a tensor (nor as the
        # torch.Generator itself, which pickles a state tensor): a DataLoader pickles the
        # dataset for spawned workers with torch's ForkingPickler, which moves tensors to
        # shared memory, and a temporary one is freed before the worker maps it (the worker
        # dies with "unable to resize file").
        # (a copy: object.__getstate__ returns the live __dict__; Python 3.10 has none)
        base = getattr(super(), "__getstate__", None)
        state = dict(base() if base is not None else self.__dict__)
        if state.get("_generator") is not None:
            state["_generator"] = state["_generator"].get_state().numpy().tobytes()
        return state

    def __setstate__(self, state: dict) -> None:
        state = dict(state)
        saved = state.get("_generator")
        if isinstance(saved, bytes):   # (an older pickle holds the torch.Generator itself)
            state["_generator"] = torch.Generator()
            state["_generator"].set_state(torch.frombuffer(bytearray(saved), dtype=torch.uint8))
        # pickled before these existed: their defaults
        for key, default in (("_generator_key", None), ("channels_last", False),
                             ("out_dtype", None)):
            state.setdefault(key, default)
        super().__setstate__(state)

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
        g = self.generator if generator is None else generator
        n = 1 if self.same_on_batch else batch_size
        f64 = dict(dtype=torch.float64)
        # Every draw below happens for every sample whatever its model, so the stream (and hence
        # a seed's batch) does not depend on which branch a sample takes.
        u_model = torch.rand(n, generator=g, **f64)
        fish_fov = _uniform(n, self.fov_range, g)
        cata_fov = _uniform(n, self.cata_fov_range, g)
        xi = _uniform(n, self.xi_range, g)
        k = (2 * torch.rand(n, 4, generator=g, **f64) - 1) * self.kb_distortion
        scale = _uniform(n, self.focal_scale_range, g)
        jitter = (2 * torch.rand(n, 2, generator=g, **f64) - 1) * self.center_jitter
        yaw = _uniform(n, self.yaw_range, g)
        pitch = _uniform(n, self.pitch_range, g)
        roll = _uniform(n, self.roll_range, g)
        applied = torch.rand(n, generator=g, **f64) < self.p

        if self.mode == "fisheye":
            cata = torch.zeros(n, dtype=torch.bool)
        elif self.mode == "catadioptric":
            cata = torch.ones(n, dtype=torch.bool)
        else:
            cata = u_model < self.catadioptric_prob
        n_fish = len(self.fisheye_models)
        # the same uniform picks the fisheye model, rescaled to [0, 1) on the fisheye branch
        u_fish = u_model if self.mode == "fisheye" else (
            (u_model - self.catadioptric_prob) / max(1 - self.catadioptric_prob, 1e-12))
        fish_index = (u_fish.clamp(0, 1 - 1e-12) * n_fish).long()
        models = tuple("unified" if c else self.fisheye_models[i]
                       for c, i in zip(cata.tolist(), fish_index.tolist()))

        h, w = self.image_size
        rim = min(h, w) / 2 - 0.5
        fov = torch.where(cata, cata_fov, fish_fov)
        blind = torch.where(cata, torch.full_like(fov, self.blind_fov or 0.0),
                            torch.zeros_like(fov))
        params = torch.zeros(n, _MAX_P, **f64)
        num_params = torch.zeros(n, dtype=torch.long)
        for name in sorted(set(models)):
            idx = torch.tensor([i for i, m in enumerate(models) if m == name])
            half = 0.5 * fov[idx]
            if name == "unified":
                extra = torch.cat((xi[idx, None], torch.zeros(len(idx), 4, **f64)), -1)
            elif name == "kannala_brandt":
                extra = self._monotonic_kb(k[idx], half)
            else:
                extra = torch.zeros(len(idx), 0, **f64)
            radius, ok = _unit_radius(name, extra, half)
            if not bool(ok.all()):   # guarded by _check_ranges; a bug if it fires
                raise RuntimeError(f"{name}: drawn field of view outside the model's domain")
            focal = scale[idx] * rim / radius
            cx = (w - 1) / 2 + jitter[idx, 0]
            cy = (h - 1) / 2 + jitter[idx, 1]
            row = torch.cat((torch.stack((focal, focal, cx, cy), -1), extra), -1)
            params[idx, :row.shape[-1]] = row
            num_params[idx] = row.shape[-1]

        zero = torch.zeros_like(yaw)
        yaw, pitch, roll = (torch.where(applied, a, zero) for a in (yaw, pitch, roll))
        mount = torch.eye(3, **f64).expand(n, 3, 3).clone()
        mount[cata] = face_rotations(torch.float64)[FACES.index(self.looking)]
        rotation = yaw_pitch_roll_to_matrix(yaw, pitch, roll) @ mount

        out = dict(model=models, camera_params=params, num_params=num_params, fov=fov,
                   blind_fov=blind, yaw=yaw, pitch=pitch, roll=roll, applied=applied,
                   rotation=rotation)
        if n != batch_size:   # same_on_batch
            out = {key: (value * batch_size if key == "model"
                         else value.expand(batch_size, *value.shape[1:]).clone())
                   for key, value in out.items()}
        return out

    def _monotonic_kb(self, k: Tensor, half: Tensor) -> Tensor:
        """``(n, 4)`` coefficients halved until ``max_angle > half + margin`` (zero at worst):
        every halving judged in one call of ``max_angle`` (a polynomial root per row), the
        first good one kept."""
        n, steps = k.shape[0], _KB_SHRINK_STEPS + 1
        scales = 0.5 ** torch.arange(steps, dtype=k.dtype)
        candidates = k[:, None, :] * scales[None, :, None]                   # (n, steps, 4)
        params = torch.cat((torch.ones(n, steps, 4, dtype=k.dtype), candidates), -1)
        good = get_model("kannala_brandt").max_angle(params) > (half + _ANGLE_MARGIN)[:, None]
        first = torch.where(good.any(-1), good.int().argmax(-1), steps)      # (n,)
        chosen = candidates.gather(1, first.clamp_max(steps - 1)[:, None, None].expand(n, 1, 4))
        return torch.where((first < steps)[:, None], chosen[:, 0], torch.zeros_like(k))

    # ---------------------------------------------------------------------------------------
    # Rendering
    # ---------------------------------------------------------------------------------------
    def cameras(self, params: dict, dtype: torch.dtype = torch.float32,
                device: torch.device | str | None = None) -> dict[str, tuple[Tensor, Camera]]:
        """One batched :class:`~omniscape_torch.Camera` per model in ``params``:
        ``{model: (sample indices (n,), camera with params (n, P))}``, without ``fov`` (the
        per-sample cones are applied by ``render``)."""
        out = {}
        models = params["model"]
        for name in sorted(set(models)):
            idx = torch.tensor([i for i, m in enumerate(models) if m == name], dtype=torch.long)
            p = int(params["num_params"][idx[0]])
            cam_params = params["camera_params"][idx, :p].to(dtype=dtype, device=device)
            out[name] = (idx, Camera(name, cam_params, self.image_size))
        return out

    def render(self, cubemap: Tensor | None, params: dict, *, labels: Tensor | None = None,
               depth: Tensor | None = None) -> dict:
        """Render the modalities through the cameras and rotations of ``params``.

        Args:
            cubemap: ``(B, 6, C, F, F)`` (``channels_last``: ``(B, 6, F, F, C)``), floating or
                ``uint8``, or None.
            params: parameters from ``forward_parameters``.
            labels, depth: as for ``forward``.

        Returns:
            dict ``valid`` and, for each given input, ``rgb``, ``labels``, ``depth`` (class
            docstring), plus ``params``.
        """
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
            for start in range(0, len(idx), chunk):
                part = slice(start, start + chunk)
                cam = Camera(name, camera.params[part], self.image_size)
                sel = idx[part]
                proj = OmniProjection(cam, self.face_size, interpolation=self.interpolation,
                                      ignore_index=self.ignore_index)
                # the grid of every pixel, with the sample's rotation and field-of-view cones
                # (on the CPU the sampling pass computes it from the cameras' tables)
                grid = camera_grid(
                    name, cam.params, self.image_size, self.face_size, proj.pad,
                    rotation=params["rotation"][sel].to(dtype=dtype, device=device),
                    fov=params["fov"][sel].to(dtype=dtype, device=device),
                    blind_fov=params["blind_fov"][sel].to(dtype=dtype, device=device),
                    lazy=True)
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
                        interpolation=self.interpolation, ignore_index=self.ignore_index)
                    rows = grid.rows(a, b) if isinstance(grid, CameraGrid) else (
                        grid[0][a:b], grid[1][a:b])
                    layer.render(**inputs, depth_output=self.depth_output, grid=rows,
                                 **rgb_options,
                                 out={key: value[at] for key, value in result.items()})
        result["params"] = params
        return result

    def _check_cubemap(self, cubemap: object) -> torch.dtype | None:
        """The dtype of the ``rgb`` image of ``cubemap`` (None without one). Raises for a cube
        not laid out as ``channels_last`` says (naming the flag that fits), or of a dtype the
        layer refuses."""
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
        if cubemap.dim() != 5 or cubemap.shape[1] != 6 or \
                tuple(cubemap.shape[d] for d in face_dims) != (f, f):
            other = (3, 4) if self.channels_last else (2, 3)   # the other layout's face dims
            hint = ""
            if cubemap.dim() == 5 and cubemap.shape[1] == 6 and \
                    tuple(cubemap.shape[d] for d in other) == (f, f):
                hint = (f"; it looks {'channels-first' if self.channels_last else 'channels-last'}"
                        f": construct with channels_last={not self.channels_last}")
            raise ValueError(f"cubemap: expected shape {layout} with F = face_size = {f} "
                             f"(channels_last={self.channels_last}), got "
                             f"{tuple(cubemap.shape)}{hint}")
        return check_out_dtype(cubemap.dtype, self.out_dtype)

    def forward(self, cubemap: Tensor | dict | None, labels: Tensor | None = None,
                depth: Tensor | None = None, *, params: dict | None = None,
                generator: torch.Generator | None = None) -> dict:
        """Draw (or reuse ``params``, kornia style) and render.

        Args:
            cubemap: ``(B, 6, C, F, F)`` (``channels_last``: ``(B, 6, F, F, C)``) floating or
                ``uint8``, or a dict with keys ``rgb`` and optionally ``labels`` and ``depth``
                (so the module can start an ``nn.Sequential``).
            labels: ``(B, 6, F, F)`` integer class ids.
            depth: ``(B, 6, F, F)`` planar depth, metres.
            params: parameters from ``forward_parameters`` or a previous output, to replay.
            generator: the generator of this call (else the module's).

        Returns:
            dict ``rgb``, ``labels``, ``depth`` (those given), ``valid`` and ``params``.
        """
        if isinstance(cubemap, dict):
            unknown = set(cubemap) - {"rgb", "labels", "depth"}
            if unknown:
                raise ValueError(f"cubemap: unknown keys {sorted(unknown)}")
            labels = cubemap.get("labels", labels)
            depth = cubemap.get("depth", depth)
            cubemap = cubemap.get("rgb")
        ref = next((t for t in (cubemap, labels, depth) if t is not None), None)
        if ref is None:
            raise ValueError("forward: pass at least one of cubemap, labels, depth")
        if params is None:
            params = self.forward_parameters(ref.shape[0], generator=generator)
        return self.render(cubemap, params, labels=labels, depth=depth)


def _runs(indices: list[int]) -> list[tuple[int, int, int]]:
    """The runs of consecutive values of ``indices``: ``(start, stop, first value)`` of each,
    positions into ``indices``."""
    runs, start = [], 0
    for k in range(1, len(indices) + 1):
        if k == len(indices) or indices[k] != indices[k - 1] + 1:
            runs.append((start, k, indices[start]))
            start = k
    return runs


def _check_pixelwise(module: nn.Module) -> None:
    """Refuse a kornia augmentation that moves pixels (see :class:`ApplyToKey`)."""
    from kornia.augmentation import GeometricAugmentationBase2D
    moving = [m for m in module.modules() if isinstance(m, GeometricAugmentationBase2D)]
    if moving:
        raise TypeError(f"module: {type(moving[0]).__name__} moves pixels: applied to one key it "
                        "would move the rgb and not the labels, depth and valid mask. Apply it "
                        "to the cubes before RandomOmniCamera, or to every key with kornia's "
                        "AugmentationSequential(data_keys=[...])")


class ApplyToKey(nn.Module):
    """Apply an image augmentation (e.g. kornia's ``ColorJitter``) to one entry of the dict that
    :class:`RandomOmniCamera` returns, so both compose in an ``nn.Sequential``::

        nn.Sequential(RandomOmniCamera(...), ApplyToKey(kornia.augmentation.ColorJitter(...)))

    The invalid pixels are zeroed again afterwards (``mask_invalid``), in the value's dtype
    (``uint8`` included). Note that kornia's own augmentations draw from torch's global RNG,
    not from this package's generators, and take ``(B, C, H, W)`` floating images.

    Only augmentations that leave every pixel where it is (colour, noise, blur): a geometric
    one (kornia's ``GeometricAugmentationBase2D``: flips, crops, affine warps) would move the
    RGB and not the labels, depth and valid mask, so it is refused with a ``TypeError``. Apply
    those to the cubes before :class:`RandomOmniCamera` (a new attitude is the geometric
    augmentation here), or to every key at once with kornia's ``AugmentationSequential``
    (``data_keys=["input", "mask", ...]``).

    Args:
        module: applied to ``batch[key]``.
        key: the entry it applies to.
        mask_invalid: zero the pixels where ``batch["valid"] (B, 1, H, W)`` is False.
        channels_last: the layout of the module's output: ``(B, H, W, C)`` (True) or
            ``(B, C, H, W)`` (False); None (default) tells them apart by where ``(H, W)`` of
            the valid mask lies, and raises where that is ambiguous (``C = H = W``).
            ``(B, H, W)`` (labels) and ``(B, 1, H, W)`` need no flag.
    """

    def __init__(self, module: nn.Module, key: str = "rgb", mask_invalid: bool = True,
                 channels_last: bool | None = None) -> None:
        super().__init__()
        if channels_last is not None and not isinstance(channels_last, bool):
            raise TypeError(f"channels_last: expected a bool or None, got {channels_last!r}")
        _check_pixelwise(module)
        self.module = module
        self.key = key
        self.mask_invalid = bool(mask_invalid)
        self.channels_last = channels_last

    def forward(self, batch: dict) -> dict:
        out = dict(batch)
        value = self.module(batch[self.key])
        if self.mask_invalid and "valid" in batch:
            mask = _mask_for(batch["valid"], value, self.channels_last, self.key)
            value = torch.where(mask, value, torch.zeros_like(value))
        out[self.key] = value
        return out


def _mask_for(valid: Tensor, value: Tensor, channels_last: bool | None, key: str) -> Tensor:
    """``valid (B, 1, H, W)`` shaped to broadcast over ``value``: ``(B, C, H, W)``,
    ``(B, H, W, C)`` (``valid[:, 0, ..., None]``) or ``(B, H, W)``."""
    hw = tuple(valid.shape[-2:])
    shape = tuple(value.shape)
    if value.dim() == 3 and shape[1:] == hw:
        return valid[:, 0]
    first = value.dim() == 4 and shape[2:] == hw
    last = value.dim() == 4 and shape[1:3] == hw
    if channels_last is None:
        if first and last and shape[1] != 1:
            raise ValueError(f"{key}: shape {shape} reads as (B, C, H, W) and (B, H, W, C) "
                             f"with valid {tuple(valid.shape)}: pass channels_last")
        channels_last = last and not first
    if channels_last and last:
        return valid[:, 0, ..., None]
    if not channels_last and first:
        return valid
    raise ValueError(f"{key}: shape {shape} does not match valid {tuple(valid.shape)} as "
                     f"{'(B, H, W, C)' if channels_last else '(B, C, H, W)'}")
