"""The fisheye lenses and attitudes both augmentation modules draw: their generator (seeding
across epochs and `DataLoader` workers), their checks, and the draws themselves."""

from __future__ import annotations

import math
import os
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ..cameras import Camera
from ..cameras._checks import check_one_camera
from ..cameras.camera import _check_image_size
from ..cameras.registry import get_model
from ..render import detection
from ..render.kernels import check_backend
from ..render.kernels import draw as kdraw
from .targets import _on_batch

#: The fisheye lenses drawn (`fisheye_models`): the models of the registry that say how
#: (`CameraModel.fisheye_draw`).
FISHEYE_MODELS = kdraw.FISHEYE_MODELS
MODES = ("fisheye", "catadioptric", "mixed")
#: Fisheye models whose reach is fixed: a `fov_range` beyond it is refused at construction.
#: The others are fitted to each drawn field of view (`kernels.draw.fisheye_lens`).
_FIXED_REACH = tuple(m for m in FISHEYE_MODELS if get_model(m).fisheye_draw.fixed_reach)
#: The lens parameters drawn per model (beyond fx, fy, cx, cy), by the argument of their range.
_LENS_RANGES = MappingProxyType({m: tuple(a for a, _ in get_model(m).fisheye_draw.ranges)
                                 for m in FISHEYE_MODELS if get_model(m).fisheye_draw.ranges})
#: Their defaults (typical fisheye lenses: Usenko et al. 2018 fit EUCM alpha 0.63, beta 1.04
#: and double sphere xi -0.2, alpha 0.59 to theirs), also for modules pickled before they
#: existed.
_LENS_DEFAULTS = MappingProxyType({a: d for m in FISHEYE_MODELS
                                   for a, d in get_model(m).fisheye_draw.ranges})
#: Dimension count of each batched input (one less: an unbatched sample; ``containers``).
_IMAGE_DIMS = MappingProxyType({"rgb": 4, "labels": 3, "instances": 3, "depth": 3})
_CUBE_DIMS = MappingProxyType({"rgb": 5, "labels": 4, "instances": 4, "depth": 4})
#: ``RandomReproject``'s ``coverage_range`` when neither it nor ``focal_scale_range`` is given:
#: a pinhole source fills 50 to 90 % of the output.
DEFAULT_COVERAGE = (0.5, 0.9)
_DEG = math.pi / 180
_ANGLE_MARGIN = kdraw.ANGLE_MARGIN




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



#: The constructor arguments both modules hand to `_RandomCameras` as they are given.
SHARED_ARGUMENTS = ("fisheye_models", "fov_range", "kb_distortion", "unified_xi_range",
                    "eucm_alpha_range", "eucm_beta_range", "ds_xi_range", "ds_alpha_range",
                    "focal_scale_range", "center_jitter", "roll_range", "pitch_range",
                    "yaw_range", "p", "same_on_batch", "interpolation", "depth_output",
                    "ignore_index", "seed", "channels_last", "out_dtype", "backend", "camera",
                    "focal_jitter")


def shared_arguments(arguments: Mapping[str, object]) -> dict:
    """The `SHARED_ARGUMENTS` among a module constructor's `locals()`."""
    return {name: arguments[name] for name in SHARED_ARGUMENTS}


def _target_camera(camera: object) -> Camera | None:
    """The modules' `camera`: one `ot.Camera` (a batch shape of `()`), a calibration file that
    `Camera.load` reads, or None."""
    if camera is None:
        return None
    if isinstance(camera, (str, os.PathLike)):
        camera = Camera.load(camera)
    check_one_camera(camera)
    return camera


class _RandomCameras(nn.Module):
    """What `RandomOmniCamera` and `RandomReproject` share: the module's
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
                 seed: int | None, channels_last: bool, out_dtype: torch.dtype | None,
                 backend: str, camera: object = None, focal_jitter: float = 0.0) -> None:
        super().__init__()
        camera = _target_camera(camera)
        if camera is not None:
            if image_size is None:
                image_size = camera.image_size
            elif tuple(int(v) for v in image_size) != camera.image_size:
                raise ValueError(f"image_size: {tuple(image_size)} differs from the camera's "
                                 f"{camera.image_size} (pass image_size=None to take it)")
        if (isinstance(focal_jitter, bool) or not isinstance(focal_jitter, (int, float))
                or not 0 <= focal_jitter < 1):
            raise ValueError(f"focal_jitter: expected a relative focal change in [0, 1), got "
                             f"{focal_jitter!r}")
        h, w = _check_image_size(image_size)
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
        self.backend = check_backend(backend)
        self.camera = camera   # the fixed target camera, or None: a drawn lens
        self.focal_jitter = float(focal_jitter)
        # what depends on the arguments above alone, made on first use (keyed by the values it
        # depends on): the lenses' tables, the framing's distances to the edges
        self._cached: dict[tuple, object] = {}
        self._generator: torch.Generator | None = None
        self._generator_key: tuple[int, int] | None = None   # _context_key() it was made in

    def _check_fisheye_ranges(self) -> None:
        """Fail at construction, not mid-training, if ``fov_range`` leaves the domain of a
        model whose reach is fixed (the drawn lenses of the others are fitted to each drawn
        field of view: `_lens`)."""
        half = torch.tensor([0.5 * self.fov_range[1]], dtype=torch.float64)
        for name in self.fisheye_models:
            if name not in _FIXED_REACH:
                continue
            _, ok = kdraw.unit_radius(name, torch.zeros(1, 0, dtype=torch.float64), half)
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
        state["_cached"] = {}         # (likewise)
        return state

    def __setstate__(self, state: dict) -> None:
        state = dict(state)
        saved = state.get("_generator")
        if isinstance(saved, bytes):   # (an older pickle holds the torch.Generator itself)
            state["_generator"] = torch.Generator()
            state["_generator"].set_state(torch.frombuffer(bytearray(saved), dtype=torch.uint8))
        # pickled before these existed: their defaults
        for key, default in (("_generator_key", None), ("channels_last", False),
                             ("out_dtype", None), ("label_keys", {}), ("backend", "auto"),
                             ("focal_jitter", 0.0),
                             ("_cached", {}),
                             *_LENS_DEFAULTS.items()):
            state.setdefault(key, default)
        super().__setstate__(state)

    # ---------------------------------------------------------------------------------------
    # The draw
    # ---------------------------------------------------------------------------------------
    def _spec(self) -> kdraw.DrawSpec:
        """The arguments the draw depends on (`kernels.draw.DrawSpec`), read as they are now."""
        d = self.__dict__   # (plain attributes: no nn.Module lookups on the per-call path)
        return kdraw.DrawSpec(
            self.image_size, self.fisheye_models, self.fov_range, self.kb_distortion,
            {m: tuple(d[a] for a in attrs) for m, attrs in _LENS_RANGES.items()},
            self.focal_scale_range, self.center_jitter, self.yaw_range, self.pitch_range,
            self.roll_range, self.p, d.get("coverage_range"), d.get("mode", "fisheye"),
            d.get("cata_fov_range", (0.0, 0.0)), d.get("xi_range", (0.0, 0.0)),
            d.get("blind_fov"), d.get("looking", "down"), d.get("catadioptric_prob", 0.0),
            self._camera_spec(), d.get("focal_jitter", 0.0))

    def _camera_spec(self) -> tuple | None:
        """The fixed target camera as `DrawSpec.camera` reads it, or None."""
        camera = self._modules.get("camera") or self.__dict__.get("camera")
        if camera is None:
            return None
        fov = None if camera.fov is None else float(torch.as_tensor(camera.fov))
        return (camera.model.name, tuple(camera.params.detach().double().tolist()), fov)

    def _draw_params(self, batch_size: int, generator: torch.Generator | None,
                     source: Tensor | None = None, source_size: tuple[int, int] | None = None
                     ) -> dict:
        """`batch_size` cameras and attitudes (`forward_parameters`): one block of
        `kernels.draw.STREAM_WIDTH` uniforms per sample from the generator, then
        `kernels.draw.draw_cameras` (the one draw of both modules), framed to the pinholes
        `source (B, 4)` of images of `source_size` where given (`RandomReproject`'s
        `coverage_range`)."""
        g = self.generator if generator is None else generator
        n = 1 if self.same_on_batch else batch_size
        u = torch.rand(kdraw.STREAM_WIDTH * n, generator=g, dtype=torch.float64)
        drawn = kdraw.draw_cameras(self._spec(), u, n,
                                   source=None if source is None else source[:n],
                                   source_size=source_size, cache=self._cached,
                                   backend=self.backend)
        return _on_batch(drawn, n, batch_size)

    def _unit_lens(self, name: str) -> kdraw.UnitLens | None:
        """`kernels.draw.unit_lens` of `name` for this module's widest field of view and
        output size (kept in the module)."""
        return kdraw.unit_lens(name, self.fov_range[1], self.image_size, self._cached)

    def cameras(self, params: dict, dtype: torch.dtype = torch.float32,
                device: torch.device | str | None = None) -> dict[str, tuple[Tensor, Camera]]:
        """One batched `Camera` per model in ``params``:
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
        """What `cameras` holds, checked as ``Camera`` checks it, without making the
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




