"""Stereo rig: two omnidirectional cameras with a baseline, each sampling its own cubemap.

The OmniScape dataset mounts its stereo fisheye and catadioptric pairs on the two front sides of
a motorcycle. A cubemap holds one viewpoint, so each camera of the rig samples the cubemap
rendered at its own position; the rig adds the extrinsics that relate the two.

Frames: the rig frame has OpenCV axes (x right, y down, z forward), like a camera looking along
the vehicle's heading. Camera ``i`` sits at ``positions[i]`` (metres, rig frame) and its rays map
to the rig frame by ``rotations[i]`` (``ray_rig = R_i @ ray_cam``). The cubemaps are rendered
with their axes along the rig frame; a vehicle attitude ``rotation`` (rig -> cube frame) rotates
both cameras together: ``ray_cube = rotation @ R_i @ ray_cam``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..cubemap.rotation import check_rotation
from .layer import OmniProjection


class StereoRig(nn.Module):
    """Two ``OmniProjection`` layers and their extrinsics.

    Args:
        left: the left camera's layer.
        right: the right camera's layer (its camera and face size may differ from the left's).
        baseline: distance between the cameras in metres, along the rig's x axis; used when
            ``positions`` is not given (left at ``-baseline / 2``, right at ``+baseline / 2``).
        positions: optional ``(2, 3)`` camera centres in the rig frame, metres.
        rotations: optional ``(2, 3, 3)`` camera -> rig rotations (default: both look forward).
    """

    def __init__(self, left: OmniProjection, right: OmniProjection, *, baseline: float = 0.3,
                 positions: Tensor | None = None, rotations: Tensor | None = None) -> None:
        super().__init__()
        for name, layer in (("left", left), ("right", right)):
            if not isinstance(layer, OmniProjection):
                raise TypeError(f"{name}: expected an OmniProjection, got {type(layer).__name__}")
        if positions is None:
            if not isinstance(baseline, (int, float)) or not baseline > 0:
                raise ValueError(f"baseline: expected a positive number of metres, got "
                                 f"{baseline!r}")
            positions = torch.tensor([[-baseline / 2, 0.0, 0.0], [baseline / 2, 0.0, 0.0]])
        if rotations is None:
            rotations = torch.eye(3).expand(2, 3, 3)
        for name, t, shape in (("positions", positions, (2, 3)),
                               ("rotations", rotations, (2, 3, 3))):
            if not isinstance(t, Tensor) or tuple(t.shape) != shape:
                raise ValueError(f"{name}: expected a tensor of shape {shape}, got "
                                 f"{tuple(t.shape) if isinstance(t, Tensor) else type(t)}")
        check_rotation(rotations, "rotations")
        self.left, self.right = left, right
        self.register_buffer("positions", positions.clone().float())
        self.register_buffer("rotations", rotations.clone().float())

    def extrinsics(self) -> dict[str, Tensor]:
        """``T_rig_left``, ``T_rig_right`` (camera -> rig, 4 x 4) and ``T_right_left`` (points
        in the left camera frame -> the right camera frame), metres."""
        def pose(i: int) -> Tensor:
            t = torch.eye(4, dtype=self.positions.dtype, device=self.positions.device)
            t[:3, :3], t[:3, 3] = self.rotations[i], self.positions[i]
            return t
        t_left, t_right = pose(0), pose(1)
        return {"T_rig_left": t_left, "T_rig_right": t_right,
                "T_right_left": torch.linalg.inv(t_right) @ t_left}

    def forward(self, left_cubemap: Tensor | None, right_cubemap: Tensor | None,
                rotation: Tensor | None = None, *, out_dtype: torch.dtype | None = None,
                channels_last: bool = False, **render: Tensor | None) -> dict:
        """Render both cameras.

        Args:
            left_cubemap: ``(B, 6, C, F, F)`` RGB cubemap rendered at the left camera's
                position (``channels_last``: ``(B, 6, F, F, C)``), floating or ``uint8``
                (sampled as it is; no gradient); pass ``None`` to render only depth/labels
                through ``render``.
            right_cubemap: the same, rendered at the right camera's position.
            rotation: optional ``(B, 3, 3)`` rig -> cube-frame attitude.
            out_dtype: dtype of both ``rgb`` images (``OmniProjection.render``): None for the
                cubemap's (``uint8`` rounded to nearest, half up), or a floating dtype (a
                ``uint8`` cube scaled to [0, 1]).
            channels_last: both cubemaps are ``(B, 6, F, F, C)`` and both ``rgb`` images come
                back ``(B, H, W, C)``.
            **render: per-camera extra modalities as ``left_depth``, ``right_labels``, ... passed
                to ``OmniProjection.render``.

        Returns:
            ``{"left": dict, "right": dict, **extrinsics()}``; each camera's dict is
            ``OmniProjection.render``'s (``rgb``, ``valid``, ``depth``, ``labels``, ...).
        """
        unknown = [k for k in render if not k.startswith(("left_", "right_"))]
        if unknown:
            raise TypeError(f"unexpected keyword arguments {unknown}; use left_<modality> or "
                            f"right_<modality>")
        if not isinstance(channels_last, bool):
            raise TypeError(f"channels_last: expected a bool, got {channels_last!r}")
        if left_cubemap is None and right_cubemap is None and (
                out_dtype is not None or channels_last):
            raise ValueError("out_dtype, channels_last: they describe the rgb cubemaps, and "
                             "neither is given")
        eye = torch.eye(3, dtype=self.rotations.dtype, device=self.rotations.device)
        out = {}
        for i, (name, layer, cube) in enumerate((("left", self.left, left_cubemap),
                                                 ("right", self.right, right_cubemap))):
            r = self.rotations[i]
            if rotation is None:  # a camera aligned with the rig keeps its cached grid
                r = None if torch.equal(r, eye) else r.unsqueeze(0)
            else:
                r = rotation @ r.to(rotation)
            extra = {key[len(name) + 1:]: value for key, value in render.items()
                     if key.startswith(name + "_")}
            if cube is not None:   # the layer refuses rgb options without rgb
                extra.setdefault("out_dtype", out_dtype)   # a left_out_dtype=... wins
                extra.setdefault("channels_last", channels_last)
            out[name] = layer.render(rgb=cube, rotation=r, **extra)
        out.update(self.extrinsics())
        return out
