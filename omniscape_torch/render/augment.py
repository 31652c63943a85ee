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
from types import MappingProxyType
from typing import Callable, Mapping, NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ..cameras import Camera
from ..cameras._checks import not_a_camera
from ..cameras.registry import get_model
from ..cubemap.faces import FACES, face_rotations
from ..cubemap.rotation import check_rotation
from . import containers, detection, extension, fast, framing
from .fast import CameraGrid
from .kernels import camera_grid, camera_rays, radial_table
from ..cameras.presets import rotation_rows, yaw_pitch_roll_to_matrix
from . import layer as projection
from .layer import OmniProjection
from .reference import check_out_dtype, warn_if_label_map
from .reproject import INTERPOLATIONS, intrinsics_from_matrix, sample_camera

__all__ = ["ApplyToKey", "RandomOmniCamera", "RandomReproject", "FISHEYE_MODELS", "MODES"]

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


#: The detection keys of the modules' dicts (beside rgb, labels, depth and the declared label
#: keys); a cubemap takes no boxes (its boxes come from its instance ids).
_TARGET_KEYS = ("instances", "boxes", "box_instance_ids", "keypoints")
_BUILT_IN_KEYS = ("rgb", "labels", "depth", "valid", "params", "intrinsics", "source_camera",
                  "keypoints_valid", "box_index", *_TARGET_KEYS)


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
    if cube and "boxes" in inputs:
        raise ValueError("boxes: a cubemap has no 2D boxes; pass instances (B, 6, F, F) and "
                         "box_instance_ids: the boxes come from the output's instance ids")
    out = {key: inputs[key] for key in _TARGET_KEYS if key in inputs}
    maps = {key: inputs[key] for key in label_keys if key in inputs}
    if maps:
        out["label_maps"] = maps
    return out


def _label_maps(label_keys: Mapping[str, int], instances: Tensor | None,
                label_maps: Mapping[str, Tensor] | None, cube: bool
                ) -> dict[str, tuple[Tensor, int]]:
    """``{key: (ids, ignore value)}`` of ``instances`` (ignore 0) and the declared label keys'
    maps, checked: integer ids ``(B, H, W)`` (a cube ``(B, 6, F, F)``), a channel of 1
    dropped, ``bool`` masks as ``uint8``."""
    given = {} if label_maps is None else dict(label_maps)
    unknown = set(given) - set(label_keys)
    if unknown:
        raise ValueError(f"label_maps: keys {sorted(unknown)} are not declared (label_keys="
                         f"{dict(label_keys)})")
    maps = {}
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
                 maps: dict, channels_last: bool) -> tuple[int, int]:
    """``(Hs, Ws)`` of a perspective batch."""
    for t in (labels, depth, *(ids for ids, _ in maps.values())):
        if t is not None:
            return tuple(t.shape[-2:])
    return tuple(image.shape[1:3] if channels_last else image.shape[-2:])


def _float(dtype: torch.dtype) -> torch.dtype:
    return dtype if dtype.is_floating_point else torch.float32


class RandomOmniCamera(_RandomCameras):
    """Per sample, a random omnidirectional camera and attitude; renders the cubemap through it.

    Cameras: the image circle of the drawn field of view ``fov`` is inscribed in the image (as in
    :func:`~omniscape_torch.cameras.presets.fisheye` and :func:`~omniscape_torch.cameras.presets.catadioptric`):
    ``f = s (min(H, W) / 2 - 0.5) / r1(fov / 2)`` with ``r1`` the model's radius at focal 1 and
    ``s`` drawn in ``focal_scale_range`` (``s > 1`` zooms in and crops the circle); the centre is
    the image centre plus a uniform jitter of at most ``center_jitter`` pixels on each axis.

    * ``mode="fisheye"``: a model drawn uniformly among ``fisheye_models``
      (:data:`FISHEYE_MODELS`: ``equidistant``, ``equisolid``, ``stereographic``,
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

    def __init__(self, image_size: tuple[int, int], face_size: int, *, mode: str = "fisheye",
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
                 label_keys: Mapping[str, int] | None = None) -> None:
        super().__init__(
            image_size, fisheye_models=fisheye_models, fov_range=fov_range,
            kb_distortion=kb_distortion, unified_xi_range=unified_xi_range,
            eucm_alpha_range=eucm_alpha_range, eucm_beta_range=eucm_beta_range,
            ds_xi_range=ds_xi_range, ds_alpha_range=ds_alpha_range,
            focal_scale_range=focal_scale_range, center_jitter=center_jitter,
            roll_range=roll_range, pitch_range=pitch_range, yaw_range=yaw_range, p=p,
            same_on_batch=same_on_batch, interpolation=interpolation, depth_output=depth_output,
            ignore_index=ignore_index, seed=seed, channels_last=channels_last,
            out_dtype=out_dtype)
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
        # drawn last, and only where a model takes them: the other draws stay those of older
        # versions for the same seed
        lens = (torch.rand(n, 2, generator=g, **f64) if self._draws_lens
                else torch.zeros(n, 2, **f64))

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
        kinds = tuple(_CATADIOPTRIC if c else self.fisheye_models[i]
                      for c, i in zip(cata.tolist(), fish_index.tolist()))

        fov = torch.where(cata, cata_fov, fish_fov)
        blind = torch.where(cata, torch.full_like(fov, self.blind_fov or 0.0),
                            torch.zeros_like(fov))
        params = torch.zeros(n, _MAX_P, **f64)
        num_params = torch.zeros(n, dtype=torch.long)
        for kind in sorted(set(kinds)):
            idx = torch.tensor([i for i, m in enumerate(kinds) if m == kind])
            half = 0.5 * fov[idx]
            if kind == _CATADIOPTRIC:   # under or over its mirror: xi_range, no distortion
                name = "unified"
                extra = torch.cat((xi[idx, None], torch.zeros(len(idx), 4, **f64)), -1)
            else:
                name = kind
                extra, half = self._lens(name, half, k[idx], lens[idx])
                fov[idx] = 2 * half
            row = self._camera_rows(name, extra, half, scale[idx], jitter[idx])
            params[idx, :row.shape[-1]] = row
            num_params[idx] = row.shape[-1]
        models = tuple("unified" if kind == _CATADIOPTRIC else kind for kind in kinds)

        zero = torch.zeros_like(yaw)
        yaw, pitch, roll = (torch.where(applied, a, zero) for a in (yaw, pitch, roll))
        mount = torch.eye(3, **f64).expand(n, 3, 3).clone()
        mount[cata] = face_rotations(torch.float64)[FACES.index(self.looking)]
        rotation = yaw_pitch_roll_to_matrix(yaw, pitch, roll) @ mount

        out = dict(model=models, camera_params=params, num_params=num_params, fov=fov,
                   blind_fov=blind, yaw=yaw, pitch=pitch, roll=roll, applied=applied,
                   rotation=rotation)
        return _on_batch(out, n, batch_size)

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
        maps = _label_maps(self.label_keys, instances, label_maps, cube=True)
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
        """:meth:`render` of the modalities alone (``valid``, ``rgb``, ``labels``, ``depth``,
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
                blind_fov=params["blind_fov"][idx].to(dtype=dtype, device=device), lazy=True)
            for start in range(0, len(idx), chunk):
                part = slice(start, start + chunk)
                cam = camera if len(idx) <= chunk else Camera(name, camera.params[part],
                                                              self.image_size)
                sel = idx[part]
                proj = OmniProjection(cam, self.face_size, interpolation=self.interpolation,
                                      ignore_index=self.ignore_index)
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
                        interpolation=self.interpolation, ignore_index=self.ignore_index)
                    layer.render(**inputs, depth_output=self.depth_output,
                                 grid=_grid_rows(grid, a, b),
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
                (:mod:`~omniscape_torch.render.containers`).
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
            unknown = set(cubemap) - {"rgb", "labels", "depth"} - _target_keys(self.label_keys)
            if unknown:
                raise ValueError(f"cubemap: unknown keys {sorted(unknown)}")
            labels = cubemap.get("labels", labels)
            depth = cubemap.get("depth", depth)
            cubemap = cubemap.get("rgb")
        given = {"rgb": cubemap, "labels": labels, "depth": depth}
        ref = next((t for t in (*given.values(), *targets.get("label_maps", {}).values(),
                                targets.get("instances")) if t is not None), None)
        if ref is None:
            raise ValueError("forward: pass at least one of cubemap, labels, depth, instances")
        if params is None:
            params = self.forward_parameters(ref.shape[0], generator=generator)
        out = self.render(cubemap, params, labels=labels, depth=depth, **targets)
        return containers.leave(out, wrapping)




class RandomReproject(_RandomCameras):
    """Per sample, a perspective (or any camera's) image seen through a random fisheye lens and
    attitude.

    For the segmentation datasets of perspective images (Cityscapes, BDD100K, Mapillary, the
    built-in town's pinhole views): each image, with its pinhole intrinsics, is reprojected
    into a fisheye camera drawn as :class:`RandomOmniCamera` draws its fisheyes (``mode=
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
    ``p``, ``same_on_batch``, ``seed``, :meth:`reseed` and the randomness across epochs and
    ``DataLoader`` workers: as :class:`RandomOmniCamera`'s.

    On the CPU without gradients (the fast path, as ``OmniProjection``'s), every pixel's ray
    comes from a table per camera (``kernels.radial_table``) and the image is sampled by the C++
    op ``sample_image`` straight from the image's memory: ``uint8`` in and out (rounded half
    up, or scaled to [0, 1] by a floating ``out_dtype``), channels-last images read without a
    copy (``channels_last``), labels written as int64 in the same pass. Elsewhere (another
    device, a gradient asked for, ``bicubic``) the exact chain: ``Camera.ray_grid`` and
    :func:`~omniscape_torch.render.reproject.sample_camera` (``grid_sample``).

    Args:
        image_size: ``(H, W)`` of the output.
        source_fov: the horizontal field of view of the perspective images (radians), used
            where no ``intrinsics`` are passed; None: they must be passed.
        source_camera: one :class:`~omniscape_torch.Camera` (any model, ``image_size`` the
            images') used where neither ``intrinsics`` nor ``source_camera`` are passed; not
            with ``source_fov``.
        fisheye_models: the lens, as for :class:`RandomOmniCamera` (``mode="fisheye"``).
        fov_range: the lens, as for :class:`RandomOmniCamera` (``mode="fisheye"``).
        kb_distortion: the lens, as for :class:`RandomOmniCamera` (``mode="fisheye"``).
        unified_xi_range: the lens, as for :class:`RandomOmniCamera` (``mode="fisheye"``).
        eucm_alpha_range: the lens, as for :class:`RandomOmniCamera` (``mode="fisheye"``).
        eucm_beta_range: the lens, as for :class:`RandomOmniCamera` (``mode="fisheye"``).
        ds_xi_range: the lens, as for :class:`RandomOmniCamera` (``mode="fisheye"``).
        ds_alpha_range: the lens, as for :class:`RandomOmniCamera` (``mode="fisheye"``).
        focal_scale_range: the focal as a multiple of the one that inscribes the drawn image
            circle (as for :class:`RandomOmniCamera`); not with ``coverage_range``. Given
            alone, it replaces the default framing (the behaviour before it).
        coverage_range: ``(min, max)`` share of the output's pixels the source fills (valid),
            drawn per sample; the focal is solved for it from the source pinhole, the drawn
            lens and attitude (:mod:`~omniscape_torch.render.framing`; ``params["coverage"]``).
            Default, when neither it nor ``focal_scale_range`` is given: ``(0.5, 0.9)``
            (``DEFAULT_COVERAGE``). Sources other than a pinhole, and
            ``forward_parameters`` without ``source_size``, use ``focal_scale_range``.
        center_jitter: the lens, as for :class:`RandomOmniCamera` (``mode="fisheye"``).
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
            :class:`RandomOmniCamera`.
        antialias: prefilter ``rgb`` where the fisheye minifies the source (an output pixel
            covering more than one source pixel): the mean of taps over each pixel's
            footprint through a mip pyramid. On the CPU fast path (``uint8``, float32 and
            float64 images, no gradient) the C++ op :func:`~omniscape_torch.render.fast.
            mip_image`; elsewhere :mod:`~omniscape_torch.render.antialias` (the same rule,
            differentiable). Pixels that do not minify are as with
            ``antialias=False`` (point samples), bit for bit; ``labels``, ``depth`` and
            ``valid`` are the same either way (nearest texel at the pixel centre, never
            blended). Not for ``interpolation="nearest"``. On by default (as in
            ``ot.reproject``): its cost is in ``docs/augmentation.md`` (Antialiasing).

    Shapes:
        ``rgb (B, C, Hs, Ws)`` (``channels_last``: ``(B, Hs, Ws, C)``) floating or ``uint8``,
        ``labels (B, Hs, Ws)`` integer, ``depth (B, Hs, Ws)`` or ``(B, 1, Hs, Ws)`` planar ->
        ``rgb (B, C, H, W)`` (``(B, H, W, C)``), ``labels (B, H, W)`` int64,
        ``depth (B, 1, H, W)``, ``valid (B, 1, H, W)`` bool; ``params`` as
        :meth:`forward_parameters` returns them, with the ``intrinsics (B, 4)`` of a pinhole
        source, or the record of the ``source_camera`` used (``model``, ``params (B, P)``
        float64 on the CPU: plain values that ``default_collate`` stacks).

    Examples:
        >>> aug = RandomReproject((64, 64), source_fov=math.radians(90), seed=0)
        >>> out = aug({"rgb": torch.rand(2, 3, 48, 64), "labels": torch.zeros(2, 48, 64).long()})
        >>> out["rgb"].shape, out["labels"].shape, out["valid"].shape
        (torch.Size([2, 3, 64, 64]), torch.Size([2, 64, 64]), torch.Size([2, 1, 64, 64]))
    """

    def __init__(self, image_size: tuple[int, int], *, source_fov: float | None = None,
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
                 antialias: bool = True) -> None:
        if focal_scale_range is not None and coverage_range is not None:
            raise ValueError("coverage_range: pass coverage_range or focal_scale_range, not both")
        if focal_scale_range is None and coverage_range is None:
            coverage_range = DEFAULT_COVERAGE
        if coverage_range is not None:
            coverage_range = _check_range(coverage_range, "coverage_range", 1e-3, 1.0)
        if not isinstance(antialias, bool):
            raise TypeError(f"antialias: expected a bool, got {antialias!r}")
        focal_scale_range = (1.0, 1.0) if focal_scale_range is None else focal_scale_range
        super().__init__(
            image_size, fisheye_models=fisheye_models, fov_range=fov_range,
            kb_distortion=kb_distortion, unified_xi_range=unified_xi_range,
            eucm_alpha_range=eucm_alpha_range, eucm_beta_range=eucm_beta_range,
            ds_xi_range=ds_xi_range, ds_alpha_range=ds_alpha_range,
            focal_scale_range=focal_scale_range, center_jitter=center_jitter,
            roll_range=roll_range, pitch_range=pitch_range, yaw_range=yaw_range, p=p,
            same_on_batch=same_on_batch, interpolation=interpolation, depth_output=depth_output,
            ignore_index=ignore_index, seed=seed, channels_last=channels_last,
            out_dtype=out_dtype)
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
        self._check_fisheye_ranges()
        # what depends on the arguments above alone, made on first use (keyed by the values
        # it depends on): _unit_lens, the framing's distances to the edges without jitter
        self._cached: dict[tuple, object] = {}

    def __getstate__(self) -> dict:
        state = super().__getstate__()
        state["_cached"] = {}   # made again on first use (no tensors in the pickle)
        return state

    def __setstate__(self, state: dict) -> None:
        state = dict(state)
        # pickled before framing and antialiasing existed: as they rendered then
        state.setdefault("coverage_range", None)
        state.setdefault("antialias", False)
        state.setdefault("_cached", {})
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
            solved for it, :mod:`~omniscape_torch.render.framing`).

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

    def _rays(self, name: str, params: Tensor, fov: Tensor) -> tuple[Tensor, Tensor]:
        """The unit rays ``(n, H, W, 3)`` and validity ``(n, H, W)`` of ``n`` cameras of model
        ``name`` (``params (n, P)`` in the rays' dtype, float32 or float64) within their fields
        of view ``fov (n,)``: :func:`~omniscape_torch.render.kernels.camera_rays`, through
        the table of :meth:`_unit_lens` where the model has one."""
        if self._unit_lens(name) is None:
            return camera_rays(name, params, self.image_size, fov=fov, dtype=params.dtype)
        return fast.camera_rays(*self._tables(name, params, fov), self.image_size, params.dtype)

    def _tables(self, name: str, params: Tensor, fov: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``affine (n, 6)``, ``limits (n, 5)`` and ``table (1, 2, K)`` of ``n`` cameras of a
        model with a :meth:`_unit_lens` table, in the dtype of ``params (n, P)``, as
        :func:`~omniscape_torch.render.fast.camera_rays` takes them: ``cx, cy`` and ``M =
        diag(1 / fx, 1 / fy)``, the table's limits with ``cos(fov / 2)`` and no blind cone."""
        unit = self._unit_lens(name)
        cams = params.numpy()[:, :4].astype(np.float64)   # (NumPy's slicing: cheaper)
        n = len(cams)
        affine = np.zeros((n, 6))          # cx, cy and M = diag(1 / fx, 1 / fy)
        affine[:, :2] = cams[:, 2:]
        affine[:, 2::3] = 1 / cams[:, :2]
        limits = np.empty((n, 5))          # scale, root, end, cos(fov / 2), no blind cone
        limits[:] = unit.limits_row
        limits[:, 3] = np.cos(0.5 * fov.numpy().astype(np.float64))
        table = unit.tables[params.dtype]
        as_dtype = cams.dtype if params.dtype == torch.float64 else np.float32   # the rays'
        return (torch.from_numpy(affine.astype(as_dtype)),
                torch.from_numpy(limits.astype(as_dtype)), table)

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
               keypoints: Tensor | None = None, label_maps: Mapping[str, Tensor] | None = None
               ) -> dict:
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

        Returns:
            the dict of ``forward``: ``params`` with the ``intrinsics (B, 4)`` of a pinhole
            source, else ``source_camera``, the source used, as ``{"model", "params" (B, P)
            float64 on the CPU[, "fov", "blind_fov"]}``, which ``default_collate`` stacks and a
            replay reads back.
        """
        return self._render(image, params, None, labels=labels, depth=depth,
                            intrinsics=intrinsics, source_camera=source_camera,
                            instances=instances, boxes=boxes, box_instance_ids=box_instance_ids,
                            keypoints=keypoints, label_maps=label_maps)

    def _render(self, image: Tensor | None, params: dict, drawn: tuple | None, *,
                labels: Tensor | None = None, depth: Tensor | None = None,
                intrinsics: Tensor | None = None, source_camera: Camera | None = None,
                instances: Tensor | None = None, boxes: Sequence[Tensor] | None = None,
                box_instance_ids: Sequence[Tensor] | None = None,
                keypoints: Tensor | None = None, label_maps: Mapping[str, Tensor] | None = None
                ) -> dict:
        """:meth:`render`; ``drawn``: where ``forward`` drew ``params`` itself in this call,
        the source ``(k, camera)`` of :meth:`_source` (checked) for images of ``(Hs, Ws)``
        that it drew them for, else None. Drawn params are not checked again (their rotations,
        cameras and batch are the module's own) nor is their source made again (for inputs of
        that size)."""
        maps = _label_maps(self.label_keys, instances, label_maps, cube=False)
        batch = _check_batches(params, **dict(
            (key, t) for key, (t, _) in maps.items()), box_instance_ids=box_instance_ids,
            keypoints=keypoints, boxes=boxes)
        kp_dtype = torch.float32
        if keypoints is not None:
            kp_dtype = _float(torch.as_tensor(keypoints).dtype)
            keypoints = detection.check_keypoints(keypoints, batch)
        box_dtype = torch.float32
        if boxes is not None:
            box_dtype = next((_float(torch.as_tensor(b).dtype) for b in boxes), box_dtype)
            boxes = detection.check_boxes(boxes, batch)
        ids = None
        if box_instance_ids is not None:
            if instances is None:
                raise ValueError("box_instance_ids: needs instances (the exact mode boxes the "
                                 "output pixels of each box's instance id)")
            ids = detection.check_box_ids(box_instance_ids, boxes, batch)
        sources = dict(intrinsics=intrinsics, source_camera=source_camera)
        targets = None
        if keypoints is not None or (boxes is not None and ids is None):
            # mapped before the maps are rendered: the boxes that the valid area cuts read
            # their pixels from the rays the maps are sampled along (Targets.scan)
            size = _source_size(image, labels, depth, maps, self.channels_last)
            k, camera = (drawn[:2] if drawn is not None and drawn[2] == size else
                         self._source(intrinsics, source_camera, size, batch))
            source = (detection.Side("pinhole", k, size) if k is not None
                      else detection.Side.of(camera, batch))
            targets = detection.Targets(
                self._changes(params, source), batch, keypoints=keypoints,
                boxes=None if ids is not None else boxes, source_size=size)
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
            result.update(targets.result(kp_dtype, box_dtype))
        return result

    def _render_maps(self, image: Tensor | None, params: dict, *, labels: Tensor | None = None,
                     depth: Tensor | None = None, intrinsics: Tensor | None = None,
                     source_camera: Camera | None = None, scan: Callable | None = None,
                     drawn: tuple | None = None) -> dict:
        """:meth:`render` of the modalities alone (``valid``, ``rgb``, ``labels``, ``depth``,
        ``params`` with the source camera's record); ``scan``: called on the fast path with
        each chunk's samples and the rays they are sampled along (``detection.Targets.scan``);
        ``drawn``: as for :meth:`_render`."""
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
        fast_path = (device.type == "cpu" and fast.available() and
                     self.interpolation in fast.MODES and not (
                         torch.is_grad_enabled() and any(
                             t is not None and t.requires_grad for t in (image, depth, k))))
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
        pinhole (``coverage_range``), and that source as :meth:`_render` takes it: ``(k,
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

    def _render_fast(self, name: str, part: "_Part", image: Tensor | None,
                     labels: Tensor | None, depth: Tensor | None, result: dict,
                     scan: Callable | None = None) -> None:
        """The samples ``part.index`` through the C++ ops: the cameras' rays from their tables
        (or ``Camera.ray_grid`` where a model has none), then ``fast.sample_image``; ``scan``
        (if given) reads the rays as ``sample_image`` does. The common case (a lens with a
        table, a pinhole source, image and ``uint8`` or int64 labels, no depth, no detection
        targets) runs as one call of the C++ op ``reproject_image`` per run of samples: the
        same kernels, in the same order, without the rays in Python."""
        if (part.source is None and scan is None and depth is None and
                self._unit_lens(name) is not None and
                (image is None or image.dtype in fast.MIPMAPPED or not self.antialias) and
                (labels is None or labels.dtype in (torch.uint8, torch.int64))):
            self._render_fused(name, part, image, labels, result)
            return
        rays, valid = self._rays(name, part.params, part.fov)
        target, rotation = rays, part.rotation
        if part.source is None:
            k = part.intrinsics.to(rays.dtype)
        else:
            # any other source model: the rays projected by it in torch, in its dtype; the C++
            # op then reads the pixels as the rays (u, v, 1) of the unit pinhole (fx = fy = 1,
            # cx = cy = 0), so u = 1 * (u / 1) + 0 exactly, and checks the image bounds
            src = torch.einsum("bij,bhwj->bhwi", rotation.to(part.source.params.dtype),
                               rays.to(part.source.params.dtype))
            pixels, seen_src = part.source.project(src)                      # (n, h, w, 2)
            valid = valid & seen_src
            pixels = torch.where(valid.unsqueeze(-1), pixels, torch.full_like(pixels, -2.0))
            rays = torch.cat((pixels, torch.ones_like(pixels[..., :1])), dim=-1)
            rotation = None
            k = torch.tensor([[1.0, 1.0, 0.0, 0.0]], dtype=rays.dtype)
        if scan is not None:
            scan(part.index, rays, rotation, k, valid)
        for at, (a, b) in _slices(part.index):   # runs of consecutive samples: views
            rows = slice(a, b)
            rot = None if rotation is None else rotation[rows]
            kr = k if part.source is not None else k[rows]
            seen = result["valid"][at, 0]
            if image is not None:
                _, seen_rgb = fast.sample_image(
                    image[at], rays[rows], rot, kr, self.interpolation,
                    valid=valid[rows], out=result["rgb"][at], out_dtype=result["rgb"].dtype)
                seen.copy_(seen_rgb)
                if self.antialias and self.interpolation != "nearest":
                    self._antialias(image[at], rays[rows], rot, kr, seen_rgb,
                                    result["rgb"][at])
            if labels is not None:
                wide = labels.dtype in (torch.uint8, torch.int64)   # int64 ids in the pass
                out = result["labels"][at].unsqueeze(1)
                ids, seen_ids = fast.sample_image(
                    labels[at].unsqueeze(1), rays[rows], rot, kr,
                    "nearest", valid=valid[rows], fill=self.ignore_index if wide else 0,
                    out=out if wide else None, out_dtype=torch.int64 if wide else None)
                if not wide:
                    out.copy_(torch.where(seen_ids.unsqueeze(1), ids.long(),
                                          torch.full_like(out, self.ignore_index)))
                seen.copy_(seen_ids)
            if depth is not None:
                z, seen_z = fast.sample_image(depth[at], rays[rows], rot, kr, "nearest",
                                              valid=valid[rows])
                result["depth"][at] = self._range(z, target[rows], part.rotation[rows],
                                                  seen_z.unsqueeze(1))
                seen.copy_(seen_z)

    def _render_fused(self, name: str, part: "_Part", image: Tensor | None,
                      labels: Tensor | None, result: dict) -> None:
        """:meth:`_render_fast` of the common case, one ``reproject_image`` call per run of
        consecutive samples."""
        affine, limits, table = self._tables(name, part.params, part.fov)
        k = part.intrinsics.to(part.params.dtype)
        minifies = (fast.MINIFIES if image is not None and self.antialias and
                    self.interpolation != "nearest" else 0.0)
        rgb, ids, valid = result.get("rgb"), result.get("labels"), result["valid"][:, 0]
        op = fast._require().reproject_image     # (the inputs are the module's own: checked)
        for at, (a, b) in _slices(part.index):   # runs of consecutive samples
            whole = b - a == len(valid)          # the batch: the tensors, not views of them

            def rows(t: Tensor | None, index: slice) -> Tensor | None:
                return t if t is None or whole else t[index]

            op(rows(image, at), rows(labels, at), rows(affine, slice(a, b)),
               rows(limits, slice(a, b)), table, rows(part.rotation, slice(a, b)),
               rows(k, slice(a, b)), self.interpolation == "bilinear", minifies,
               self.ignore_index, rows(rgb, at), rows(ids, at), rows(valid, at))

    @staticmethod
    def _antialias(image: Tensor, rays: Tensor, rotation: Tensor | None, k: Tensor,
                   seen: Tensor, out: Tensor) -> None:
        """Overwrite the pixels of ``out`` (the fast op's samples) whose footprint minifies the
        source with its mip filter, :func:`~omniscape_torch.render.fast.mip_image`; float16
        and bfloat16 images through float32, in which the op blends them."""
        if image.dtype in fast.MIPMAPPED:
            fast.mip_image(image, rays, rotation, k, seen, out)
        else:
            work = out.float()
            fast.mip_image(image.float(), rays, rotation, k, seen, work)
            out.copy_(work)

    def _render_exact(self, name: str, part: "_Part", image: Tensor | None,
                      labels: Tensor | None, depth: Tensor | None, result: dict) -> None:
        """The samples ``part.index`` through ``Camera.ray_grid`` and ``sample_camera``
        (``grid_sample``; any device, differentiable with respect to the images)."""
        camera = Camera(name, part.params, self.image_size)
        rays, valid = camera.ray_grid()                                     # (n, h, w, 3)
        valid = valid & (rays[..., 2] >= torch.cos(0.5 * part.fov)[:, None, None])
        src = torch.einsum("bij,bhwj->bhwi", part.rotation, rays)
        source = (Camera("pinhole", part.intrinsics.to(rays.dtype), part.source_size)
                  if part.source is None else part.source)
        mask = valid.unsqueeze(1)
        sel = part.index.to(result["valid"].device)
        seen = None
        if image is not None:
            values, ok = sample_camera(image[sel], source, src, interpolation=self.interpolation,
                                       out_dtype=result["rgb"].dtype, antialias=self.antialias)
            seen = ok & mask
            result["rgb"][sel] = torch.where(seen, values, torch.zeros_like(values))
        if labels is not None:
            ids, ok = sample_camera(labels[sel], source, src, labels=True,
                                    ignore_index=self.ignore_index)
            seen = ok & mask
            result["labels"][sel] = torch.where(seen[:, 0], ids, self.ignore_index)
        if depth is not None:
            z, ok = sample_camera(depth[sel], source, src, interpolation="nearest")
            seen = ok & mask
            result["depth"][sel] = self._range(z, rays, part.rotation, seen)
        result["valid"][sel] = seen

    def _range(self, z: Tensor, rays: Tensor, rotation: Tensor, seen: Tensor) -> Tensor:
        """Planar source depth ``z (n, 1, h, w)`` sampled along unit fisheye ``rays (n, h, w,
        3)`` -> their range (``|p| = z / cos`` of the ray to the source axis), or its ``z`` along
        the fisheye's axis (``depth_output``); 0 where not ``seen``."""
        axis = torch.einsum("bj,bhwj->bhw", rotation[:, 2].to(rays.dtype), rays)   # src z
        # a wide source (a fisheye) sees rays at or past 90 degrees: no planar depth there (0)
        seen = seen & (axis > 0).unsqueeze(1)
        cos = torch.where(seen[:, 0], axis, torch.ones_like(axis)).unsqueeze(1)
        out = z.to(rays.dtype) / cos
        if self.depth_output == "z":
            out = out * rays[..., 2].unsqueeze(1)
        return torch.where(seen, out, torch.zeros_like(out)).to(z.dtype)

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
                coordinates), ``box_instance_ids`` (per sample ``(N_i,)``: the exact mode) and
                ``keypoints`` ``(B, K, 2)``, and the keys of ``label_keys``
                (``docs/detection.md``); ``tv_tensors.Image`` /
                ``tv_tensors.Mask``
                are taken as the tensors they hold, and their outputs come back in their
                classes (``valid`` as a ``Mask``); an unbatched sample ``(C, H, W)``,
                ``(H, W)`` comes back unbatched, ``params`` per sample
                (:mod:`~omniscape_torch.render.containers`).
            labels: ``(B, H, W)`` integer class ids.
            depth: planar depth ``(B, H, W)``.
            intrinsics: ``(B, 4)`` or ``(4,)`` pinhole ``fx, fy, cx, cy`` of the images, or a
                camera matrix ``K (B, 3, 3)`` or ``(3, 3)`` (zero skew; else ``source_camera``,
                the module's ``source_camera`` or ``source_fov``).
            source_camera: the images' camera, any model of the registry: one
                :class:`~omniscape_torch.Camera` shared by the batch, or a batch ``(B,)`` of one
                model (e.g. ``Camera.load`` of an Aria calibration, or an ``opencv`` camera
                with its distortion).
            params: parameters from ``forward_parameters`` or a previous output, to replay.
            generator: the generator of this call (else the module's).

        Returns:
            dict ``rgb``, ``labels``, ``depth``, ``instances`` and the declared label keys
            (those given), ``valid`` and ``params``; with ``boxes``: ``boxes`` (the same
            structure, each the tight box of its object in the output, clipped to the valid
            area) and ``box_index`` (per sample ``(M_i,)`` int64: the input box of each);
            with ``keypoints``: ``keypoints (B, K, 2)`` (NaN where invalid) and
            ``keypoints_valid (B, K)``.
        """
        image, labels, depth, params, wrapping = containers.enter(
            image, labels, depth, params, batch_dims=_IMAGE_DIMS, owner=self)
        targets = _targets(image, self.label_keys, cube=False)
        if isinstance(image, dict):
            unknown = set(image) - {"rgb", "labels", "depth", "intrinsics", "source_camera"} - \
                _target_keys(self.label_keys)
            if unknown:
                raise ValueError(f"image: unknown keys {sorted(unknown)}")
            labels = image.get("labels", labels)
            depth = image.get("depth", depth)
            intrinsics = image.get("intrinsics", intrinsics)
            source_camera = image.get("source_camera", source_camera)
            image = image.get("rgb")
        given = {"rgb": image, "labels": labels, "depth": depth}
        ref = next((t for t in (*given.values(), *targets.get("label_maps", {}).values(),
                                targets.get("instances")) if t is not None), None)
        if ref is None:
            raise ValueError("forward: pass at least one of image, labels, depth, instances")
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
    """The camera of :func:`_camera_record`'s ``record`` for images of ``size``, also after
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
    """Refuse what is not one :class:`Camera` (a batch of one model) naming ``source_camera``."""
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


#: Angles of a lens's radius at focal 1 in :meth:`RandomReproject._unit_lens` (linear between
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
