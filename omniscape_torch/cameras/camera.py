"""``Camera``: one camera, or a batch of cameras of one model, as an ``nn.Module``."""

from __future__ import annotations

import math
import operator
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor, nn

from . import export, formats, readers, woodscape_files
from ._base import CameraModel
from .registry import get_model


class Camera(nn.Module):
    """A camera of a registered model with fixed or learnable intrinsics.

    Validity combines the model's domain, the image bounds (u in [-0.5, W - 0.5], v in
    [-0.5, H - 0.5], pixel centres at integers) and, when given, the field of view ``fov``: the
    full cone angle around the optical axis (+z), in radians, and ``blind_fov``, the full cone
    angle around the axis that the camera cannot see (a catadioptric camera's own reflection in
    its mirror).

    Args:
        model: a model name of ``ot.cameras.MODELS`` or a ``CameraModel``.
        params: ``(P,)`` for one camera or ``(*B, P)`` for a batch; sequences are converted with
            the default dtype. The values are checked (finite, inside the model's ranges).
        image_size: ``(H, W)`` in pixels.
        fov: optional full field of view in radians (degrees only at the CLI), in (0, 2 pi].
        learnable: hold ``params`` as an ``nn.Parameter`` (else a buffer).
        blind_fov: optional full angle in radians of the central blind cone, below ``fov``.

    Examples:
        >>> import omniscape_torch as ot, torch
        >>> cam = ot.Camera("equidistant", [300.0, 300.0, 319.5, 319.5], (640, 640))
        >>> rays, valid = cam.ray_grid()
        >>> rays.shape, valid.shape
        (torch.Size([640, 640, 3]), torch.Size([640, 640]))
    """

    def __init__(self, model: str | CameraModel, params: Tensor | Sequence[float],
                 image_size: tuple[int, int], fov: float | None = None,
                 learnable: bool = False, *, blind_fov: float | None = None) -> None:
        super().__init__()
        self.model = get_model(model)
        if not isinstance(params, Tensor):
            try:
                params = torch.tensor(params, dtype=torch.get_default_dtype())
            except (TypeError, ValueError) as err:
                raise TypeError(f"params: expected a tensor or a sequence of numbers ({err})"
                                ) from None
        self.model.validate_params(params, "params")
        self.image_size = _check_image_size(image_size)
        self.fov = _check_fov(fov)
        self.blind_fov = _check_fov(blind_fov, "blind_fov")
        if self.blind_fov is not None and self.blind_fov >= (self.fov or 2 * math.pi):
            raise ValueError(f"blind_fov: must be smaller than fov, got {blind_fov} >= {fov}")
        params = params.detach().clone()
        self.invpol: Tensor | None = None  # OCamCalib's inverse polynomial, set by from_ocamcalib
        if learnable:
            self.params = nn.Parameter(params)
        else:
            self.register_buffer("params", params)

    # Pickled with its model's name (the registry entry): some models hold closures, which do
    # not pickle, and a Camera must cross to DataLoader workers.
    def __getstate__(self) -> dict:
        return {**self.__dict__, "model": self.model.name}

    def __setstate__(self, state: dict) -> None:
        super().__setstate__({**state, "model": get_model(state["model"])})

    # ---------------------------------------------------------------------------------------
    @property
    def batch_shape(self) -> torch.Size:
        """Leading shape of ``params``: () for one camera."""
        return self.params.shape[:-1]

    @property
    def learnable(self) -> bool:
        return isinstance(self.params, nn.Parameter)

    @property
    def param_names(self) -> tuple[str, ...]:
        return self.model.names_for(self.params.shape[-1])

    def extra_repr(self) -> str:
        h, w = self.image_size
        fov = "" if self.fov is None else f", fov={math.degrees(self.fov):.1f} deg"
        if self.blind_fov is not None:
            fov += f", blind_fov={math.degrees(self.blind_fov):.1f} deg"
        return (f"model={self.model.name!r}, batch={tuple(self.batch_shape)}, image_size=({h}, "
                f"{w}){fov}, learnable={self.learnable}")

    def _params_for(self, values: Tensor, what: str) -> Tensor:
        """``params`` viewed as ``(*B, 1, ..., 1, P)`` to broadcast against ``values``."""
        b = len(self.batch_shape)
        if values.dim() - 1 < b or values.shape[:b] != self.batch_shape:
            raise ValueError(f"{what}: a camera batch of shape {tuple(self.batch_shape)} needs "
                             f"{what} of shape ({', '.join(map(str, self.batch_shape))}, ..., "
                             f"{values.shape[-1] if values.dim() else '?'}), got "
                             f"{tuple(values.shape)}")
        extra = values.dim() - 1 - b
        return self.params.reshape(self.batch_shape + (1,) * extra + self.params.shape[-1:])

    def check_params(self) -> None:
        """Check the parameters against the model's domain (finite, positive focal lengths,
        the model's own ranges); the layer calls it on every forward of a camera whose
        parameters may have changed, so a diverging fit or training run stops with the name of
        the parameter instead of rendering a black or mirrored image.

        Raises:
            ValueError: naming the parameter and its values.
        """
        try:
            self.model.validate_params(self.params.detach(), "camera.params")
        except ValueError as err:
            raise ValueError(f"{err} (the parameters left the {self.model.name} model's "
                             f"domain: a diverging fit or training run?)") from None

    def in_image(self, pixels: Tensor) -> Tensor:
        """``(...)`` True where ``pixels (..., 2)`` lie in the image (pixel edges included)."""
        h, w = self.image_size
        u, v = pixels[..., 0], pixels[..., 1]
        return (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)

    def within_fov(self, directions: Tensor) -> Tensor:
        """``(...)`` True where ``directions (..., 3)`` are inside the ``fov`` cone and outside the
        ``blind_fov`` cone (all True without either)."""
        inside = torch.ones(directions.shape[:-1], dtype=torch.bool, device=directions.device)
        if self.fov is None and self.blind_fov is None:
            return inside
        rho = torch.linalg.vector_norm(directions[..., :2].detach(), dim=-1)
        theta = torch.atan2(rho, directions[..., 2].detach())
        if self.fov is not None:
            inside = inside & (theta <= 0.5 * self.fov)
        if self.blind_fov is not None:
            inside = inside & (theta > 0.5 * self.blind_fov)
        return inside

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project ``points (*B, ..., 3)`` to ``pixels (*B, ..., 2)`` and ``valid (*B, ...)``."""
        pixels, valid = self.model.project(points, self._params_for(points, "points"))
        return pixels, valid & self.in_image(pixels) & self.within_fov(points)

    def unproject(self, pixels: Tensor) -> tuple[Tensor, Tensor]:
        """Unit rays ``(*B, ..., 3)`` and ``valid (*B, ...)`` of ``pixels (*B, ..., 2)``."""
        rays, valid = self.model.unproject(pixels, self._params_for(pixels, "pixels"))
        return rays, valid & self.in_image(pixels) & self.within_fov(rays)

    def pixel_grid(self) -> Tensor:
        """``(H, W, 2)`` pixel centres (u, v), in the dtype and device of ``params``.

        Raises:
            MemoryError: the grid cannot be allocated (as `ray_grid`).
        """
        h, w = self.image_size
        kw = dict(dtype=self.params.dtype, device=self.params.device)
        try:
            v, u = torch.meshgrid(torch.arange(h, **kw), torch.arange(w, **kw), indexing="ij")
            return torch.stack((u, v), dim=-1)
        except RuntimeError as err:
            raise self._grid_memory_error(err) from None

    def ray_grid(self) -> tuple[Tensor, Tensor]:
        """Unit ray of every pixel centre and its validity.

        Returns:
            ``rays (*B, H, W, 3)`` and ``valid (*B, H, W)``: model domain, inside the image,
            within ``fov``. Differentiable with respect to ``params``.

        Raises:
            ValueError: the parameters left the model's domain (`check_params`).
            MemoryError: the grid cannot be allocated (the message gives ``image_size`` and
                the memory it needs), rather than torch's raw allocator error.
        """
        self.check_params()
        grid = self.pixel_grid()
        try:
            return self.unproject(grid.expand(self.batch_shape + grid.shape))
        except RuntimeError as err:
            raise self._grid_memory_error(err) from None

    def _grid_memory_error(self, err: RuntimeError) -> Exception:
        """`err` itself, or where torch could not allocate (its CPU allocator, or a GPU's
        `torch.OutOfMemoryError`) a `MemoryError` naming ``image_size`` and the memory needed."""
        if not (isinstance(err, torch.OutOfMemoryError) or "can't allocate" in str(err)):
            return err
        h, w = self.image_size
        count = math.prod(self.batch_shape) * h * w
        need = count * (5 * self.params.element_size() + 1)   # (u, v), the ray, valid
        return MemoryError(
            f"image_size {tuple(self.image_size)}: the ray grid of {count:,} pixels needs at "
            f"least {need / 1e9:,.1f} GB ({self.params.dtype} pixel centres and rays on "
            f"{self.params.device}), more than can be allocated; use a smaller image_size")

    # ---------------------------------------------------------------------------------------
    def max_angle(self) -> Tensor:
        """``(*B)`` supremum of the angle to the optical axis of the model's domain and ``fov``
        (radians), whatever the image bounds."""
        angle = self.model.max_angle(self.params.detach())
        return angle if self.fov is None else angle.clamp(max=0.5 * self.fov)

    @torch.no_grad()
    def field_of_view(self) -> Tensor:
        """``(*B)`` full field of view in radians: twice the largest angle to the optical axis
        among the valid pixel centres."""
        rays, valid = self.ray_grid()
        theta = torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2])
        theta = torch.where(valid, theta, torch.zeros_like(theta))
        return 2 * theta.flatten(-2).amax(dim=-1)

    @torch.no_grad()
    def pixels_per_radian(self, step: float = 1e-3) -> tuple[Tensor, Tensor]:
        """Angular sampling density at every pixel centre.

        The Jacobian ``J = d ray / d (u, v)`` (central differences of ``unproject`` with
        ``step`` pixels, in float64) has singular values ``s_min <= s_max`` (radians per pixel);
        ``1 / s_min`` is the density in the direction where pixels are finest, ``1 / s_max``
        where they are coarsest. A cube face of F texels samples ``F / 2`` pixels per radian at
        its centre.

        Returns:
            ``finest (*B, H, W)`` and ``coarsest (*B, H, W)`` in pixels per radian, 0 where the
            pixel or its neighbourhood is invalid.
        """
        params = self.params.detach().double()
        params = params.reshape(self.batch_shape + (1, 1) + params.shape[-1:])
        grid = self.pixel_grid().double()
        columns = []
        valid = None
        for axis in (0, 1):
            offset = torch.zeros(2, dtype=torch.float64, device=grid.device)
            offset[axis] = step
            plus, vp = self.model.unproject(grid + offset, params)
            minus, vm = self.model.unproject(grid - offset, params)
            columns.append((plus - minus) / (2 * step))
            valid = vp & vm if valid is None else valid & vp & vm
        # Singular values of the 3 x 2 Jacobian from the eigenvalues of J^T J (closed form).
        a = (columns[0] * columns[0]).sum(-1)
        b = (columns[0] * columns[1]).sum(-1)
        c = (columns[1] * columns[1]).sum(-1)
        mean, dev = 0.5 * (a + c), torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
        s_max, s_min = torch.sqrt(mean + dev), torch.sqrt((mean - dev).clamp(min=0))
        ok = valid & (s_min > 0)
        _, in_valid = self.unproject(self.pixel_grid().expand(self.batch_shape + grid.shape))
        ok = ok & in_valid
        finest = torch.where(ok, 1 / s_min.clamp(min=1e-300), torch.zeros_like(s_min))
        coarsest = torch.where(ok, 1 / s_max.clamp(min=1e-300), torch.zeros_like(s_max))
        return finest.to(self.params.dtype), coarsest.to(self.params.dtype)

    @torch.no_grad()
    def angular_resolution(self) -> dict[str, Tensor]:
        """Pixels per radian at the optical axis and at the edge of the valid area.

        Returns:
            ``center``: density at the valid pixel nearest to the optical axis (finest direction);
            ``edge_finest``/``edge_coarsest``: at the valid pixels farthest from the axis (the
            tangential and radial directions of a radially symmetric lens); ``finest``: the
            largest density anywhere. Each ``(*B)`` in pixels per radian.
        """
        finest, coarsest = self.pixels_per_radian()
        rays, valid = self.ray_grid()
        theta = torch.atan2(torch.linalg.vector_norm(rays[..., :2], dim=-1), rays[..., 2])
        ok = valid & (finest > 0)
        flat = lambda t: t.flatten(-2)  # noqa: E731
        near = torch.where(flat(ok), flat(theta), torch.full_like(flat(theta), math.inf))
        far = torch.where(flat(ok), flat(theta), torch.full_like(flat(theta), -math.inf))
        i_near = near.argmin(-1, keepdim=True)
        i_far = far.argmax(-1, keepdim=True)
        return {
            "center": flat(finest).gather(-1, i_near).squeeze(-1),
            "edge_angle": flat(theta).gather(-1, i_far).squeeze(-1),
            "edge_finest": flat(finest).gather(-1, i_far).squeeze(-1),
            "edge_coarsest": flat(coarsest).gather(-1, i_far).squeeze(-1),
            "finest": flat(finest).amax(-1),
        }

    # ---------------------------------------------------------------------------------------
    # Other formats (cameras/formats.py).
    @classmethod
    def from_ocamcalib(cls, path: str | Path, **kwargs) -> "Camera":
        """Load OCamCalib's ``calib_results.txt`` as a ``scaramuzza`` camera (centre converted
        from (row, column) to (u, v)); the file's inverse polynomial is kept as ``invpol``."""
        return formats.read_ocamcalib(cls, path, **kwargs)

    def to_ocamcalib(self, path: str | Path, **kwargs) -> None:
        """Write OCamCalib's ``calib_results.txt``, fitting ``invpol`` the way OCamCalib does."""
        formats.write_ocamcalib(self, path, **kwargs)

    @classmethod
    def from_opencv_fisheye(cls, K, D, image_size: tuple[int, int], **kwargs) -> "Camera":
        """``cv2.fisheye`` (K 3x3, D 4) as a ``kannala_brandt`` camera."""
        return formats.from_opencv_fisheye(cls, K, D, image_size, **kwargs)

    def to_opencv_fisheye(self, *, accept_fov: bool = False):
        """``(K (3, 3), D (4,))`` numpy arrays for ``cv2.fisheye`` (the skew in ``K[0, 1]``;
        refused past 90 degrees off the axis, where it folds, unless ``accept_fov``)."""
        return formats.to_opencv_fisheye(self, accept_fov=accept_fov)

    @classmethod
    def from_opencv_omnidir(cls, K, D, xi, image_size: tuple[int, int], **kwargs) -> "Camera":
        """``cv2.omnidir`` (K 3x3, D 4, xi) as a ``unified`` camera."""
        return formats.from_opencv_omnidir(cls, K, D, xi, image_size, **kwargs)

    def to_opencv_omnidir(self):
        """``(K (3, 3), D (1, 4), xi (1,))`` numpy arrays for ``cv2.omnidir``."""
        return formats.to_opencv_omnidir(self)

    def to_dict(self) -> dict:
        """A JSON-ready dict (one camera, or a list of cameras under ``"cameras"``)."""
        return formats.camera_to_dict(self)

    @classmethod
    def from_dict(cls, data: dict, **kwargs) -> "Camera":
        return formats.camera_from_dict(cls, data, **kwargs)

    def save_json(self, path: str | Path) -> None:
        """Write ``to_dict()`` as JSON (atomically)."""
        formats.save_json(self, path)

    @classmethod
    def load_json(cls, path: str | Path, **kwargs) -> "Camera":
        return formats.load_json(cls, path, **kwargs)

    @classmethod
    def load(cls, path, format: str | None = None, *, name: str | int | None = None,
             image_size: tuple[int, int] | None = None, dtype: torch.dtype = torch.float64,
             **kwargs) -> "Camera":
        """Read a camera from another tool's file (``cameras/readers.py``).

        Args:
            path: the file (``ot.cameras.READ_FORMATS``: json, ocamcalib, opencv, kalibr,
                basalt, orbslam3, colmap, aria), a COLMAP sparse folder, or a
                ``pycolmap.Camera`` / ``pycolmap.Reconstruction``.
            format: one of ``READ_FORMATS``; recognised from the content when ``None``.
            name: the camera of a multi-camera file (Kalibr ``cam1``, ORB-SLAM3 ``Camera2``,
                a COLMAP camera id, an Aria label); the first when ``None``
                (``ot.cameras.load_all`` returns them all).
            image_size: ``(H, W)``, overriding the file's (needed where it has none).
            dtype: dtype of the parameters.
            **kwargs: passed to ``Camera`` (``fov``, ``learnable``, ``blind_fov``).

        Raises:
            ValueError: one line naming the file, the line or key, and what was expected.
        """
        return readers.load(cls, path, format, name=name, image_size=image_size, dtype=dtype,
                            **kwargs)

    def save(self, path: str | Path, format: str = "json", *, accept_fov: bool = False,
             accept_skew: bool = False) -> Path:
        """Write the file another tool reads: ``format`` is one of ``ot.cameras.FORMATS``
        (json, ocamcalib, opencv, kalibr, basalt, orbslam3, colmap); a camera the format
        cannot hold is refused unless accepted (``cameras/export.py``). Returns the path."""
        return export.write_camera(self, path, format, accept_fov=accept_fov,
                                   accept_skew=accept_skew)


def load_all(path, format: str | None = None, *, image_size: tuple[int, int] | None = None,
             dtype: torch.dtype = torch.float64, **kwargs) -> dict[str, Camera]:
    """Every camera of a file another tool wrote, in the file's order (``Camera.load`` reads
    one; ``cameras/readers.py`` lists the formats and their models).

    Args:
        path: the file, a COLMAP sparse folder, or a ``pycolmap.Camera`` /
            ``pycolmap.Reconstruction``.
        format: one of ``ot.cameras.READ_FORMATS``; recognised from the content when ``None``.
        image_size: ``(H, W)`` for every camera, overriding the file's (needed where it has
            none: ORB-SLAM2-style settings, an Aria camera of an unknown label; json and
            ocamcalib files always have one and keep it).
        dtype: dtype of the parameters.
        **kwargs: passed to ``Camera`` (``fov``, ``learnable``, ``blind_fov``).

    Returns:
        ``{name: Camera}``: Kalibr's and basalt's ``cam0``, ``cam1``...; ORB-SLAM3's
        ``Camera1``, ``Camera2`` (``Camera`` in the older format); COLMAP's camera ids as
        strings; Aria's labels (``camera-rgb``...); ``camera`` for the single-camera formats
        (json, ocamcalib, opencv).

    Raises:
        ValueError: one line naming the file, the line or key, and what was expected.
        FileNotFoundError: no such file.

    Examples:
        >>> import tempfile, pathlib, omniscape_torch as ot
        >>> cam = ot.Camera("pinhole", [400.0, 401.0, 319.5, 239.5], (480, 640))
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     cams = ot.cameras.load_all(cam.save(pathlib.Path(tmp) / "cameras.txt", "colmap"))
        >>> list(cams), cams["1"].params.tolist()
        (['1'], [400.0, 401.0, 319.5, 239.5])
    """
    return readers.read_all(Camera, path, format, image_size=image_size, dtype=dtype, **kwargs)


def _check_image_size(image_size) -> tuple[int, int]:
    """`(H, W)` as two positive ints (any integral numbers: NumPy's, a 0-d tensor's)."""
    try:
        h, w = image_size
    except (TypeError, ValueError):
        raise ValueError(f"image_size: expected (H, W), got {image_size!r}") from None
    out = []
    for name, value in (("H", h), ("W", w)):
        try:
            number = operator.index(value) if not isinstance(value, bool) else 0
        except TypeError:
            number = 0
        if number <= 0:
            raise ValueError(f"image_size: {name} must be a positive int, got {value!r}")
        out.append(number)
    return out[0], out[1]


def _check_fov(fov, name: str = "fov") -> float | None:
    if fov is None:
        return None
    if isinstance(fov, bool) or not isinstance(fov, (int, float)) or not math.isfinite(fov):
        raise ValueError(f"{name}: expected a number of radians, got {fov!r}")
    if not 0 < fov <= 2 * math.pi:
        hint = f"; in radians, did you mean math.radians({fov})?" if fov > 2 * math.pi else ""
        raise ValueError(f"{name}: expected a full angle in (0, 2 pi] radians, got {fov}{hint}")
    return float(fov)


def read_woodscape(path: str | Path, *, dtype: torch.dtype = torch.float64, **kwargs
                   ) -> tuple[Camera, Tensor, str]:
    """A WoodScape (or SynWoodScape) calibration file: its camera, extrinsic and name
    (``cameras/woodscape_files.py`` describes the file and its conventions).

    Args:
        path: the JSON file (``calibration_data/{frame}_{CAM}.json``, WoodScape's
            ``front.json``).
        dtype: dtype of the camera's parameters.
        **kwargs: passed to ``Camera`` (``fov``, ``blind_fov``, ``learnable``), above the
            file's ``fov_deg`` / ``blind_fov_deg``.

    Returns:
        ``(camera, T, name)``: the ``woodscape`` camera, ``T (4, 4)`` float64, the transform
        from the camera frame (OpenCV axes) to the vehicle frame (ISO 8855, metres), and the
        file's camera name (``FV``, ``MVL``, ``MVR``, ``RV``).

    Raises:
        ValueError: not valid JSON, or a key missing or of the wrong kind (named).
        FileNotFoundError: no such file.
    """
    return woodscape_files.read(Camera, path, dtype=dtype, **kwargs)
