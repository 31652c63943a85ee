"""`ApplyToKey`: a pixelwise module applied to one key of the augmentation's dicts."""

from __future__ import annotations

import torch
from torch import Tensor, nn


def _check_pixelwise(module: nn.Module) -> None:
    """Refuse a kornia augmentation that moves pixels (see `ApplyToKey`)."""
    from kornia.augmentation import GeometricAugmentationBase2D
    moving = [m for m in module.modules() if isinstance(m, GeometricAugmentationBase2D)]
    if moving:
        raise TypeError(f"module: {type(moving[0]).__name__} moves pixels: applied to one key it "
                        "would move the rgb and not the labels, depth and valid mask. Apply it "
                        "to the cubes before RandomOmniCamera, or to every key with kornia's "
                        "AugmentationSequential(data_keys=[...])")


class ApplyToKey(nn.Module):
    """Apply an image augmentation (e.g. kornia's ``ColorJitter``) to one entry of the dict that
    `RandomOmniCamera` returns, so both compose in an ``nn.Sequential``::

        nn.Sequential(RandomOmniCamera(...), ApplyToKey(kornia.augmentation.ColorJitter(...)))

    The invalid pixels are zeroed again afterwards (``mask_invalid``), in the value's dtype
    (``uint8`` included). Note that kornia's own augmentations draw from torch's global RNG,
    not from this package's generators, and take ``(B, C, H, W)`` floating images.

    Only augmentations that leave every pixel where it is (colour, noise, blur): a geometric
    one (kornia's ``GeometricAugmentationBase2D``: flips, crops, affine warps) would move the
    RGB and not the labels, depth and valid mask, so it is refused with a ``TypeError``. Apply
    those to the cubes before `RandomOmniCamera` (a new attitude is the geometric
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
