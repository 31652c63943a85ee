"""The fisheye lenses and attitudes both augmentation modules draw: their generator (seeding
across epochs and `DataLoader` workers), their checks, and the draws themselves."""

from __future__ import annotations

import math
import os
from types import MappingProxyType
from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ..cameras import Camera
from ..cameras.presets import rotation_rows
from ..cameras.registry import get_model
from ..render import detection
from ..render.kernels import build as extension
from ..render.kernels import framing
from ..render.kernels.camera import radial_table
from .targets import _on_batch

#: The fisheye lenses drawn (``fisheye_models``): the radially symmetric models of the registry
#: that see past 180 degrees.
FISHEYE_MODELS = ("equidistant", "equisolid", "stereographic", "kannala_brandt", "unified",
                  "eucm", "double_sphere")
MODES = ("fisheye", "catadioptric", "mixed")
#: Fisheye models whose reach is fixed: a ``fov_range`` beyond it is refused at construction.
#: The others are fitted to each drawn field of view (:meth:`_RandomCameras._lens`).
_FIXED_REACH = ("equidistant", "equisolid", "stereographic")
#: The lens parameters drawn per model (beyond fx, fy, cx, cy), by the attribute of their range.
_LENS_RANGES = MappingProxyType({"unified": ("unified_xi_range",),
                                 "eucm": ("eucm_alpha_range", "eucm_beta_range"),
                                 "double_sphere": ("ds_xi_range", "ds_alpha_range")})
#: Their defaults, for modules pickled before they existed: typical fisheye lenses (Usenko et
#: al. 2018 fit EUCM alpha 0.63, beta 1.04 and double sphere xi -0.2, alpha 0.59 to theirs).
_LENS_DEFAULTS = MappingProxyType({"unified_xi_range": (0.5, 1.0),
                                   "eucm_alpha_range": (0.55, 0.7),
                                   "eucm_beta_range": (0.9, 1.2),
                                   "ds_xi_range": (-0.3, 0.0), "ds_alpha_range": (0.5, 0.7)})
#: Dimension count of each batched input (one less: an unbatched sample; ``containers``).
_IMAGE_DIMS = MappingProxyType({"rgb": 4, "labels": 3, "instances": 3, "depth": 3})
_CUBE_DIMS = MappingProxyType({"rgb": 5, "labels": 4, "instances": 4, "depth": 4})
#: The kind of a sample drawn as a catadioptric camera (a unified model under its mirror).
_CATADIOPTRIC = "catadioptric"
#: ``RandomReproject``'s ``coverage_range`` when neither it nor ``focal_scale_range`` is given:
#: a pinhole source fills 50 to 90 % of the output.
DEFAULT_COVERAGE = (0.5, 0.9)
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


class _RandomCameras(nn.Module):
    """What :class:`RandomOmniCamera` and :class:`RandomReproject` share: the module's
    generator (its seeding across epochs and ``DataLoader`` workers), the fisheye lenses and
    attitudes they draw, and their checks. Not a public class: see those two."""

    def __init__(self, image_size: tuple[int, int], *, fisheye_models: Sequence[str],
                 fov_range: tuple[float, float], kb_distortion: float,
                 unified_xi_range: tuple[float, float], eucm_alpha_range: tuple[float, float],
                 eucm_beta_range: tuple[float, float], ds_xi_range: tuple[float, float],
                 ds_alpha_range: tuple[float, float], focal_scale_range: tuple[float, float],
                 center_jitter: float, roll_range: tuple[float, float],
                 pitch_range: tuple[float, float], yaw_range: tuple[float, float], p: float,
                 same_on_batch: bool, interpolation: str, depth_output: str, ignore_index: int,
                 seed: int | None, channels_last: bool, out_dtype: torch.dtype | None) -> None:
        super().__init__()
        try:
            h, w = (int(v) for v in image_size)
        except (TypeError, ValueError):
            raise ValueError(f"image_size: expected (H, W), got {image_size!r}") from None
        if min(h, w) < 2:
            raise ValueError(f"image_size: needs at least 2 x 2 pixels, got {(h, w)}")
        if isinstance(fisheye_models, str):
            fisheye_models = (fisheye_models,)
        fisheye_models = tuple(fisheye_models)
        if not fisheye_models or any(m not in FISHEYE_MODELS for m in fisheye_models):
            raise ValueError(f"fisheye_models: expected names among {FISHEYE_MODELS}, got "
                             f"{fisheye_models!r}")
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 <= p <= 1:
            raise ValueError(f"p: expected a probability in [0, 1], got {p!r}")
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
        self.fisheye_models = fisheye_models
        self.fov_range = _check_range(fov_range, "fov_range", 0.0, 2 * math.pi)
        self.kb_distortion = float(kb_distortion)
        self.unified_xi_range = _check_range(unified_xi_range, "unified_xi_range", 0.0, 1.0)
        self.eucm_alpha_range = _check_range(eucm_alpha_range, "eucm_alpha_range", 0.0, 1.0)
        self.eucm_beta_range = _check_range(eucm_beta_range, "eucm_beta_range", 1e-3)
        self.ds_xi_range = _check_range(ds_xi_range, "ds_xi_range", -1.0, 1.0)
        self.ds_alpha_range = _check_range(ds_alpha_range, "ds_alpha_range", 0.0, 1.0)
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

    def _check_fisheye_ranges(self) -> None:
        """Fail at construction, not mid-training, if ``fov_range`` leaves the domain of a
        model whose reach is fixed (the drawn lenses of the others are fitted to each drawn
        field of view: :meth:`_lens`)."""
        half = torch.tensor([0.5 * self.fov_range[1]], dtype=torch.float64)
        for name in self.fisheye_models:
            if name not in _FIXED_REACH:
                continue
            _, ok = _unit_radius(name, torch.zeros(1, 0, dtype=torch.float64), half)
            limit = float(get_model(name).max_angle(torch.ones(1, 4, dtype=torch.float64)))
            if not bool(ok) or half.item() > limit - _ANGLE_MARGIN:
                raise ValueError(f"fov_range: the {name} model sees at most "
                                 f"{2 * limit / _DEG:.1f} deg, fov_range reaches "
                                 f"{2 * half.item() / _DEG:.1f} deg")

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
        state.pop("_aranges", None)   # (tensors: made again on first use)
        return state

    def __setstate__(self, state: dict) -> None:
        state = dict(state)
        saved = state.get("_generator")
        if isinstance(saved, bytes):   # (an older pickle holds the torch.Generator itself)
            state["_generator"] = torch.Generator()
            state["_generator"].set_state(torch.frombuffer(bytearray(saved), dtype=torch.uint8))
        # pickled before these existed: their defaults
        for key, default in (("_generator_key", None), ("channels_last", False),
                             ("out_dtype", None), ("label_keys", {}),
                             *_LENS_DEFAULTS.items()):
            state.setdefault(key, default)
        super().__setstate__(state)

    # ---------------------------------------------------------------------------------------
    # Lenses
    # ---------------------------------------------------------------------------------------
    @property
    def _draws_lens(self) -> bool:
        """Whether a call draws the parameters of the models in :data:`_LENS_RANGES` (not for
        the other models: their seeds keep the draws they had before those models existed)."""
        return any(m in _LENS_RANGES for m in self.fisheye_models)

    def _lens(self, name: str, half: Tensor, k: Tensor, lens: Tensor) -> tuple[Tensor, Tensor]:
        """The parameters after (fx, fy, cx, cy) ``(n, E)`` of ``n`` fisheye lenses of model
        ``name`` with half fields of view ``half (n,)``, and the half fields of view they see:
        Kannala-Brandt ``k (n, 4)`` halved until monotonic past ``half``; the parameters of the
        unified, EUCM and double sphere models from the uniforms ``lens (n, 2)`` in their
        ranges, ``half`` capped ``_ANGLE_MARGIN`` inside the reach of the drawn lens."""
        n = half.shape[0]
        if name == "kannala_brandt":
            return self._monotonic_kb(k, half), half
        if name not in _LENS_RANGES:
            return torch.zeros(n, 0, dtype=torch.float64), half
        columns = []
        for j, attr in enumerate(_LENS_RANGES[name]):
            lo, hi = getattr(self, attr)
            columns.append(lo + (hi - lo) * lens[:, j])
        extra = torch.stack(columns, -1)
        if name == "unified":   # no lens distortion: k1, k2, p1, p2 = 0
            extra = torch.cat((extra, torch.zeros(n, 4, dtype=torch.float64)), -1)
        reach = get_model(name).max_angle(torch.cat((torch.ones(n, 4, dtype=torch.float64),
                                                     extra), -1))
        return extra, torch.minimum(half, reach - _ANGLE_MARGIN)

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

    def _camera_rows(self, name: str, extra: Tensor, half: Tensor, scale: Tensor,
                     jitter: Tensor, focal: Tensor | None = None) -> Tensor:
        """``(n, P)`` parameters of ``n`` cameras of model ``name``: the image circle of the
        half field of view ``half`` inscribed in the image (times the focal ``scale``; or the
        given ``focal (n,)``), the centre the image's plus ``jitter (n, 2)``, then the lens
        parameters ``extra``."""
        h, w = self.image_size
        if focal is None:
            radius, ok = _unit_radius(name, extra, half)
            if not bool(ok.all()):   # guarded by the range checks and _lens; a bug if it fires
                raise RuntimeError(f"{name}: drawn field of view outside the model's domain")
            focal = scale * (min(h, w) / 2 - 0.5) / radius
        centre = torch.stack(((w - 1) / 2 + jitter[:, 0], (h - 1) / 2 + jitter[:, 1]), -1)
        return torch.cat((focal[:, None], focal[:, None], centre, extra), -1)

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

    def _camera_params(self, params: dict, dtype: torch.dtype, device: torch.device,
                       checked: bool = False) -> dict[str, tuple[Tensor, Tensor]]:
        """What :meth:`cameras` holds, checked as ``Camera`` checks it, without making the
        cameras: ``{model: (sample indices (n,), params (n, P) in dtype on device)}``. The
        lenses without parameters (``fx, fy, cx, cy``: finite, ``fx, fy > 0``) are checked
        in one operation for the batch; ``checked``: the module's own draws of this call,
        not checked again."""
        out = {}
        models = params["model"]
        names = sorted(set(models))
        counts = params["num_params"].tolist()
        for name in names:
            if len(names) == 1:
                idx = self._every(len(models))
                p = counts[0]
                rows = params["camera_params"][:, :p]
            else:
                first = models.index(name)
                idx = torch.tensor([i for i, m in enumerate(models) if m == name],
                                   dtype=torch.long)
                p = counts[first]
                rows = params["camera_params"][idx, :p]
            if checked:
                out[name] = (idx, rows.to(dtype=dtype, device=device))
            elif name in _FIXED_REACH and p == 4:
                values = rows.detach().cpu().numpy()
                if not (np.isfinite(values).all() and (values[:, :2] > 0).all()):
                    raise ValueError(f'params["camera_params"]: expected finite {name} '
                                     f"parameters with fx, fy > 0, got {rows.tolist()}")
                out[name] = (idx, rows.to(dtype=dtype, device=device))
            else:
                rows = rows.to(dtype=dtype, device=device)
                out[name] = (idx, Camera(name, rows, self.image_size).params)
        return out

    def _every(self, n: int) -> Tensor:
        """``torch.arange(n)``, made once per ``n`` (the sample indices of a batch of one
        model; read, never written)."""
        cached = getattr(self, "_aranges", None)
        if cached is None:
            cached = self._aranges = {}
        idx = cached.get(n)
        if idx is None:
            idx = cached[n] = torch.arange(n)
        return idx

    def _changes(self, params: dict, source: "detection.Side"
                 ) -> list[tuple[Tensor, "detection.Change"]]:
        """The camera changes of the drawn ``params`` from ``source``, one per model:
        ``(sample indices, detection.Change)``."""
        changes = []
        f64 = dict(device="cpu", dtype=torch.float64)
        for name, (idx, camera) in self.cameras(params, torch.float64, "cpu").items():
            output = detection.Side(name, camera.params, self.image_size,
                                    params["fov"][idx].to(**f64),
                                    params["blind_fov"][idx].to(**f64))
            changes.append((idx, detection.Change(source.rows(idx), output,
                                                  params["rotation"][idx].to(**f64))))
        return changes




class _FramedDraw:
    """`RandomReproject`'s draw of its fisheyes, framed to a pinhole source (mixed into it)."""

    def _draw_params(self, batch_size: int, generator: torch.Generator | None,
                     source: Tensor | None, source_size: tuple[int, int] | None) -> dict:
        """:meth:`forward_parameters`, framed to the pinhole ``source (B, 4)`` of images of
        ``source_size`` (None: by ``focal_scale_range``).

        The uniforms come from one call of the generator, in the order (and so with the values)
        of one call per family: ``u_model (n)``, ``fov (n)``, ``k (n, 4)``, ``lens (n, 2)``,
        ``scale (n)``, ``jitter (n, 2)``, ``yaw``, ``pitch``, ``roll``, ``applied (n)``, then
        ``coverage (n)`` where framed; every draw for every sample, whatever its model (the
        stream does not branch). The arithmetic runs in float64 NumPy, a few operations per
        family for the whole batch (on a few samples torch's dispatch costs more than it)."""
        g = self.generator if generator is None else generator
        n = 1 if self.same_on_batch else batch_size
        framed = source is not None
        u = torch.rand((15 + framed) * n, generator=g, dtype=torch.float64)
        ops = extension.ops()
        if (framed and len(self.fisheye_models) == 1 and ops is not None and
                self._unit_lens(self.fisheye_models[0]) is not None):
            return _on_batch(self._draw_one_lens(ops, u, n, source[:n], source_size), n,
                             batch_size)
        u = u.numpy()
        u_model, fov, k, lens, scale, jitter, attitude, applied, coverage = (
            u[n * a:n * b].reshape(n, b - a) for a, b in (
                (0, 1), (1, 2), (2, 6), (6, 8), (8, 9), (9, 11), (11, 14), (14, 15),
                (15, 15 + framed)))
        fov = self._scaled(fov[:, 0], self.fov_range)
        k = (2 * k - 1) * self.kb_distortion
        scale = self._scaled(scale[:, 0], self.focal_scale_range)
        jitter = (2 * jitter - 1) * self.center_jitter
        applied = applied[:, 0] < self.p
        # yaw, pitch, roll: the rows of (3, n) uniforms, 0 where no attitude is applied
        bounds = np.array((self.yaw_range, self.pitch_range, self.roll_range))     # (3, 2)
        attitude = np.where(applied, self._scaled(attitude.reshape(3, n), bounds.T[..., None]),
                            0.0)
        yaw, pitch, roll = attitude
        coverage = self._scaled(coverage[:, 0], self.coverage_range) if framed else None
        cos, sin = np.cos(attitude), np.sin(attitude)
        rotation = np.stack([entry for row in rotation_rows(
            cos[0], sin[0], cos[1], sin[1], cos[2], sin[2]) for entry in row],
            -1).reshape(n, 3, 3)
        h, w = self.image_size
        centre = jitter + np.array([(w - 1) / 2, (h - 1) / 2])
        index = (np.clip(u_model[:, 0], 0, 1 - 1e-12) * len(self.fisheye_models)).astype(np.int64)
        models = tuple(self.fisheye_models[i] for i in index.tolist())
        source = None if source is None else source[:n].numpy()   # (same_on_batch: the first)
        params = np.zeros((n, _MAX_P))
        num_params = np.zeros(n, dtype=np.int64)
        for name in sorted(set(models)):
            idx = slice(None) if len(set(models)) == 1 else index == self.fisheye_models.index(
                name)
            half = 0.5 * fov[idx]
            if name in _FIXED_REACH:   # no lens parameters, the drawn half field of view
                extra = np.zeros((len(half), 0))
            else:
                extra, half = (t.numpy() for t in self._lens(
                    name, torch.from_numpy(half), torch.from_numpy(k[idx]),
                    torch.from_numpy(lens[idx])))
            fov[idx] = 2 * half
            if framed:
                focal = self._framed_focal(name, extra, half, rotation[idx], source[idx],
                                           source_size, centre[idx], coverage[idx])
            else:
                radius, ok = _unit_radius(name, torch.from_numpy(extra), torch.from_numpy(half))
                if not bool(ok.all()):   # guarded by the range checks and _lens: a bug if so
                    raise RuntimeError(f"{name}: drawn field of view outside the model's "
                                       f"domain")
                focal = scale[idx] * (min(h, w) / 2 - 0.5) / radius.numpy()
            row = np.concatenate((focal[:, None], focal[:, None], centre[idx], extra), -1)
            params[idx, :row.shape[-1]] = row
            num_params[idx] = row.shape[-1]
        out = {key: torch.from_numpy(value) for key, value in (
            ("camera_params", params), ("num_params", num_params), ("fov", fov),
            ("blind_fov", np.zeros(n)), ("yaw", yaw), ("pitch", pitch), ("roll", roll),
            ("applied", applied), ("rotation", rotation))}
        out["model"] = models
        if framed:
            out["coverage"] = torch.from_numpy(coverage)
        return _on_batch(out, n, batch_size)

    def _draw_one_lens(self, ops, u: Tensor, n: int, source: Tensor,
                       source_size: tuple[int, int]) -> dict:
        """:meth:`_draw_params` of ``n`` samples of the one lens of ``fisheye_models``, which
        has a table (:meth:`_unit_lens`), framed to the pinholes ``source (n, 4)``: the C++ op
        ``frame_lens`` computes from the uniforms ``u (16 n,)`` what the NumPy steps compute
        (attitudes, rotations, reach, radius, focal; within rounding of the cosines: the
        rotations within 1e-15, the focals within 1e-12, relative), without their two dozen
        calls on a few numbers each."""
        name = self.fisheye_models[0]
        unit = self._unit_lens(name)
        h, w = self.image_size
        key = ("spec", self.image_size)
        spec, centre = self._cached.get(key, (None, None))
        if spec is None:   # the ranges and p as the op reads them; the image's centre
            spec = torch.tensor([*self.fov_range, *self.yaw_range, *self.pitch_range,
                                 *self.roll_range, *self.coverage_range, self.p],
                                dtype=torch.float64)
            centre = np.array([[(w - 1) / 2, (h - 1) / 2]])
            self._cached[key] = spec, centre
        if self.center_jitter != 0:   # the jitter's uniforms: (n, 2) from 9 n
            jitter = (2 * u[9 * n:11 * n].numpy().reshape(n, 2) - 1) * self.center_jitter
            centre = jitter + centre
        edges = torch.from_numpy(self._to_edge(centre))
        centre = torch.from_numpy(centre)
        params, fov, attitude, applied, rotation, coverage = (
            torch.zeros(n, _MAX_P, dtype=torch.float64), torch.empty(n, dtype=torch.float64),
            torch.empty(3, n, dtype=torch.float64), torch.empty(n, dtype=torch.bool),
            torch.empty(n, 3, 3, dtype=torch.float64), torch.empty(n, dtype=torch.float64))
        ops.frame_lens(u, spec, source.contiguous(), centre, *framing.COS_SIN, *source_size,
                       *unit.tensors, unit.per_angle, edges, h, w, params, fov, attitude,
                       applied, rotation, coverage)
        yaw, pitch, roll = attitude
        return {"camera_params": params, "num_params": torch.full((n,), 4),
                "fov": fov, "blind_fov": torch.zeros(n, dtype=torch.float64), "yaw": yaw,
                "pitch": pitch, "roll": roll, "applied": applied, "rotation": rotation,
                "model": (name,) * n, "coverage": coverage}

    @staticmethod
    def _scaled(u: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
        """Uniforms ``u`` in ``[0, 1)`` to ``[lo, hi]`` as :func:`_uniform` (exactly ``lo``
        when ``lo == hi``)."""
        lo, hi = bounds
        return lo + (hi - lo) * u

    def _framed_focal(self, name: str, extra: np.ndarray, half: np.ndarray,
                      rotation: np.ndarray, intrinsics: np.ndarray,
                      source_size: tuple[int, int], centre: np.ndarray,
                      coverage: np.ndarray) -> np.ndarray:
        """``(n,)`` focals at which the pinhole sources fill the shares ``coverage`` of the
        output (:mod:`~omniscape_torch.render.framing`), for lenses ``extra``, ``half``
        centred at ``centre (n, 2)``. The lens radius at focal 1 of a lens without parameters
        comes from its table (:meth:`_unit_lens`, linear between its angles: within 1e-9 of
        the model's), of the others from the model's projection."""
        theta = framing.reach(rotation, intrinsics, source_size, half)           # (n, D)
        unit = self._unit_lens(name)
        if unit is not None:
            radius = unit.radius_at(theta)
        else:
            n, d = theta.shape
            radius = _unit_radius(name, torch.from_numpy(extra).repeat_interleave(d, 0),
                                  torch.from_numpy(theta.reshape(-1)))[0].numpy().reshape(n, d)
        return framing.focal_for_coverage(radius, self._to_edge(centre), coverage,
                                          self.image_size)

    def _to_edge(self, centre: np.ndarray) -> np.ndarray:
        """:func:`~omniscape_torch.render.framing.to_edge` of the output from ``centre (n,
        2)``: ``(1, D)`` made once where every centre is the image's (no ``center_jitter``),
        else ``(n, D)``."""
        if self.center_jitter != 0:
            return framing.to_edge(centre, self.image_size)
        key = ("to_edge", self.image_size)
        edges = self._cached.get(key)
        if edges is None:
            edges = self._cached[key] = framing.to_edge(centre[:1], self.image_size)
        return edges

    def _unit_lens(self, name: str) -> "_UnitLens | None":
        """For a lens without parameters (``equidistant``, ``equisolid``, ``stereographic``),
        None for the others: what depends on the constructor's arguments alone, made on first
        use and kept in the instance. Its radius at focal 1 at :data:`_UNIT_ANGLES` angles out
        past the widest half field of view drawn (``fov_range``), and its radius -> ray table
        (:func:`~omniscape_torch.render.kernels.radial_table` of the camera of focal 1 out to
        that radius, whatever each call's focal; the pixels beyond are invalid, outside every
        drawn field of view)."""
        if name not in _FIXED_REACH:
            return None
        key = (name, self.fov_range[1], self.image_size)
        unit = self._cached.get(key)
        if unit is None:
            f64 = dict(dtype=torch.float64)
            half = 0.5 * self.fov_range[1]     # < the model's reach (_check_fisheye_ranges)
            limit = float(get_model(name).max_angle(torch.ones(1, 4, **f64)))
            step = min(half + 0.02, 0.5 * (half + limit)) / (_UNIT_ANGLES - 1)
            theta = torch.arange(_UNIT_ANGLES, **f64) * step
            radius, _ = _unit_radius(name, torch.zeros(_UNIT_ANGLES, 0, **f64), theta)
            radius[0] = 0.0
            _, limits, table = radial_table(name, torch.tensor([[1.0, 1.0, 0.0, 0.0]], **f64),
                                            self.image_size, reach=float(radius[-1]))
            limits = limits[0, :3].clone()
            limits[2] = limits[2].clamp_max(radius[-1])   # valid within the table only
            radius = radius.numpy()
            slope = np.append(np.diff(radius), 0.0)
            unit = _UnitLens(1 / step, radius, slope, np.append(limits.numpy(), (0.0, 2.0)),
                             {torch.float64: table, torch.float32: table.float()},
                             (torch.from_numpy(radius), torch.from_numpy(slope)))
            self._cached[key] = unit
        return unit



#: them: within 1e-9 of the model's radius, relative, out to 200 degrees).
_UNIT_ANGLES = 16384


class _UnitLens(NamedTuple):
    """:meth:`RandomReproject._unit_lens`: the radius at focal 1 ``radius (A,)`` at the angles
    ``j / per_angle`` and its steps ``slope (A,)`` to the next (float64 NumPy; ``tensors``:
    both as tensors, for the C++ draw), a row of the cameras' ``limits_row (5,)`` ``scale,
    root, end`` of the table, 0 for ``cos(fov / 2)``, 2 for no blind cone, and its ``tables
    (1, 2, K)`` by dtype (float64, float32)."""

    per_angle: float
    radius: np.ndarray
    slope: np.ndarray
    limits_row: np.ndarray
    tables: dict
    tensors: tuple

    def radius_at(self, theta: np.ndarray) -> np.ndarray:
        """The radius at focal 1 at the angles ``theta`` (within the table), linear between
        its entries (``np.interp``'s values, without its search)."""
        at = theta * self.per_angle
        j = np.minimum(at.astype(np.intp), len(self.radius) - 2)
        return self.radius[j] + (at - j) * self.slope[j]

