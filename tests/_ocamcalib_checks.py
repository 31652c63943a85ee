"""A dataset's ``calib_results.txt`` against its camera, through OCamCalib's own C code (the
compiled harness of ``tests/c_reference``; ``harness`` fixture of test_ocamcalib_reference.py).
Shared by tests/test_dataset.py (``generate``) and tests/test_carla.py (``convert``).

Axes: OCamCalib (x_oc, y_oc, z_oc) = (y, x, -z) ours, pixel (row, col) = (v, u)
(tests/test_calibration_io.py).
"""

from __future__ import annotations

import math

import numpy as np
import torch

import omniscape_torch as ot
from omniscape_torch.data.ocamcalib import polynomial_camera
from test_ocamcalib_reference import c_cam2world, c_model, c_world2cam

#: What the files promise (omniscape_torch.data.ocamcalib): OCamCalib's cam2world and
#: world2cam within 0.05 px of the camera over its valid area.
OCAMCALIB_PX = 0.05


def ocam_to_ours(p: np.ndarray) -> np.ndarray:
    """OCamCalib's axes to ours; its own inverse (ours to OCamCalib's)."""
    return np.stack([p[..., 1], p[..., 0], -p[..., 2]], -1)


ours_to_ocam = ocam_to_ours


def check_calib_results(harness, path, camera: ot.Camera, record: dict) -> dict:
    """Load ``path`` with OCamCalib's C ``get_ocam_model`` and compare, at every pixel centre
    that ``camera`` sees:

    * ``cam2world``: the C ray, projected by the camera itself, lands on the pixel (the ray's
      angular error in the camera's local pixel scale);
    * ``world2cam``: the C pixel of the camera's ray is the pixel.

    Also checks the ``record`` of the file (its valid area is the camera's). Returns the
    largest errors (px) and the number of pixels compared."""
    cam = ot.Camera(camera.model, camera.params.detach().double(), camera.image_size,
                    fov=camera.fov, blind_fov=camera.blind_fov)
    model = c_model(harness, path)
    assert (model["height"], model["width"]) == tuple(cam.image_size)
    assert len(model["pol"]) == record["degree"] + 1
    assert record["fov_deg"] == (None if cam.fov is None else math.degrees(cam.fov))
    assert record["blind_fov_deg"] == (None if cam.blind_fov is None
                                       else math.degrees(cam.blind_fov))
    rays, valid = cam.ray_grid()
    uv = cam.pixel_grid()[valid].numpy()
    rays = rays[valid].numpy()
    compared = len(uv)
    assert compared > 0.2 * valid.numel()
    c_rays = ocam_to_ours(c_cam2world(harness, path, uv[:, ::-1]))
    assert np.isfinite(c_rays).all()
    back, _ = cam.model.project(torch.from_numpy(c_rays), cam.params)  # its domain, no fov
    cam2world = float(np.linalg.norm(back.numpy() - uv, axis=-1).max())
    c_pix = c_world2cam(harness, path, ours_to_ocam(rays))[:, ::-1]
    world2cam = float(np.linalg.norm(c_pix - uv, axis=-1).max())
    # the polynomial camera read back with the record's area sees the same pixels, but where
    # the edge of the area (fov, blind_fov) passes between the two cameras' rays of a pixel
    poly = polynomial_camera(path, record)
    all_rays, _ = cam.unproject(cam.pixel_grid())
    poly_rays, poly_valid = poly.ray_grid()
    differ = poly_valid != valid
    theta = [torch.atan2(r[differ][:, :2].norm(dim=-1), r[differ][:, 2])
             for r in (all_rays, poly_rays)]
    low, high = torch.minimum(*theta) - 1e-12, torch.maximum(*theta) + 1e-12
    edges = [0.5 * a for a in (cam.fov, cam.blind_fov) if a is not None]
    assert all(any(lo <= e <= hi for e in edges) for lo, hi in zip(low.tolist(), high.tolist()))
    return {"cam2world_px": cam2world, "world2cam_px": world2cam, "compared": compared,
            "valid_differ": int(differ.sum())}
