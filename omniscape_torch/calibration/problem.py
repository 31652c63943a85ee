"""The least-squares problem of a fit: residuals of target points seen in views, and their
Jacobian in free variables (``calibration.fit`` module docstring: autograd, one copy of the
parameters and of its view's pose per observation)."""

from __future__ import annotations

import torch
from torch import Tensor

from .params import IntrinsicsMap, transform

#: Cost per observation (pixels squared) below which residuals are at rounding level: relative
#: convergence tests are then skipped (exact data, as in a conversion between nested models).
COST_FLOOR = 0.5e-18



class Problem:
    """Residuals ``project(R_v X + t_v, params) - pixels`` and their Jacobian in free variables.

    With no views (``poses0`` of shape ``(0, 6)``) the points are already in the camera frame
    (a model conversion fits rays to pixels); with ``rotation_only`` the views' translations
    stay at ``poses0``'s (a conversion that fits the rotation between two camera frames).
    ``weights`` ``(M,)`` scale each observation's squared residual (its residual by their
    square root).

    Args:
        intrinsics: the `IntrinsicsMap` of the model.
        points: ``(M, 3)`` target points of every observation.
        pixels: ``(M, 2)`` observed pixels.
        view: ``(M,)`` view index of each observation.
        poses0: ``(V, 6)`` initial poses.
        rotation_only: free rotations, held translations.
        weights: ``(M,)`` positive weights (None: all 1).
    """

    def __init__(self, intrinsics: IntrinsicsMap, points: Tensor, pixels: Tensor, view: Tensor,
                 poses0: Tensor, *, rotation_only: bool = False,
                 weights: Tensor | None = None) -> None:
        self.intrinsics = intrinsics
        self.model = intrinsics.model
        self.points, self.pixels, self.view = points, pixels, view
        self.scale = None if weights is None else weights.sqrt()[:, None]
        self.poses0 = poses0.detach().clone()
        self.num_views = poses0.shape[0]
        self.pose_dofs = 3 if rotation_only else 6
        self.pose_scale = float(poses0[:, 3:].norm(dim=-1).mean()) if self.num_views else 1.0
        self.num_intrinsics = len(intrinsics.free)
        self.num_free = self.num_intrinsics + self.pose_dofs * self.num_views

    def z0(self) -> Tensor:
        return torch.cat((self.intrinsics.z0(),
                          torch.zeros(self.pose_dofs * self.num_views, dtype=torch.float64)))

    def poses(self, z: Tensor) -> Tensor:
        dz = z[self.num_intrinsics:].reshape(self.num_views, self.pose_dofs)
        dz = torch.cat((dz, dz.new_zeros(self.num_views, 6 - self.pose_dofs)), -1)
        return self.poses0 + dz * torch.tensor([1.0] * 3 + [self.pose_scale] * 3,
                                               dtype=z.dtype)

    def _weighted(self, residuals: Tensor) -> Tensor:
        return residuals if self.scale is None else residuals * self.scale

    def project(self, params: Tensor, poses: Tensor | None) -> tuple[Tensor, Tensor]:
        """``(M, 2)`` pixels and ``(M,)`` model validity; ``params`` ``(P,)`` or ``(M, P)``,
        ``poses`` per observation ``(M, 6)`` (None without views)."""
        points = self.points if poses is None else transform(poses, self.points)
        return self.model.project(points, params)

    def residuals(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """``(M, 2)`` residuals (differentiable in ``z``) and ``(M,)`` validity."""
        poses = self.poses(z)[self.view] if self.num_views else None
        pixels, valid = self.project(self.intrinsics.natural(z[:self.num_intrinsics]), poses)
        return self._weighted(pixels - self.pixels), valid

    def evaluate(self, z: Tensor, jacobian: bool) -> tuple[Tensor, Tensor | None]:
        """Residuals ``(M, 2)`` and, if asked, the Jacobian ``(M, 2, n)`` (module docstring)."""
        if not jacobian:
            with torch.no_grad():
                return self.residuals(z)[0], None
        p_obs, pose_obs = self.leaves(z)
        res = self._weighted(self.project(p_obs, pose_obs)[0] - self.pixels)
        inputs = [p_obs] if pose_obs is None else [p_obs, pose_obs]
        grads = [torch.autograd.grad(res[:, k].sum(), inputs, retain_graph=k == 0)
                 for k in range(2)]
        return res.detach(), self.assemble(z, grads)

    def leaves(self, z: Tensor) -> tuple[Tensor, Tensor | None]:
        """Per-observation copies of the intrinsics ``(M, P)`` and poses ``(M, 6)`` (None
        without views) at ``z``, requiring grad: each residual depends on its own copies."""
        m = self.points.shape[0]
        params = self.intrinsics.natural(z[:self.num_intrinsics]).detach()
        p_obs = params.expand(m, -1).clone().requires_grad_(True)
        pose_obs = None
        if self.num_views:
            pose_obs = self.poses(z).detach()[self.view].clone().requires_grad_(True)
        return p_obs, pose_obs

    def assemble(self, z: Tensor, grads: list[tuple[Tensor, ...]]) -> Tensor:
        """The Jacobian ``(M, 2, n)`` in free variables from the gradients of the sum of each
        pixel coordinate's residuals (``grads[k]``: ``(M, P)`` and, with views, ``(M, 6)``) with
        respect to the `leaves`."""
        m = self.points.shape[0]
        jac = torch.zeros(m, 2, self.num_free, dtype=torch.float64)
        d_natural = self.intrinsics.jacobian(z[:self.num_intrinsics])  # [P, n_i]
        jac[:, :, :self.num_intrinsics] = torch.stack([g[0] for g in grads], 1) @ d_natural
        if self.num_views:
            k = self.pose_dofs
            d_pose = torch.stack([g[1] for g in grads], 1)[..., :k]  # [M, 2, k]
            d_pose = d_pose * torch.tensor([1.0] * 3 + [self.pose_scale] * 3,
                                           dtype=z.dtype)[:k]
            cols = self.num_intrinsics + k * self.view[:, None] + torch.arange(k)  # [M, k]
            rows = torch.arange(m)[:, None].expand(m, k)
            for k in range(2):
                jac[:, k][rows, cols] = d_pose[:, k]
        return jac


def view_index(points: list[Tensor]) -> Tensor:
    """``(M,)`` the view of each observation of the per-view ``points`` concatenated."""
    return torch.cat([torch.full((len(p),), i) for i, p in enumerate(points)])
