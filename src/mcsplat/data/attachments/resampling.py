"""How a per-view input follows its image through a resize and an undistortion: two rules, one per kind of value.

AREA is for weights (a mask's keep): each new pixel is the mean over its footprint, as the image's own pixels are
(`images._area_resize` at load time, `View.image_float` at a reduced training resolution), and the undistortion is
pycolmap's, the image's own. NEAREST is for values that must not be mixed (a depth): each new pixel takes the value
of the one old pixel under its centre, so a pixel on an object's edge gets the object's depth or the background's,
never one between them where there is no surface. Both keep COLMAP's convention that pixel centres sit at +0.5.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import images


class Area:
    """Weights, uint8 (255: the whole weight): averaged over each pixel's footprint."""

    name = "area"

    def resize(self, values: np.ndarray, size: images.Size) -> np.ndarray:
        if values.dtype != np.uint8:
            raise TypeError(f"area resampling takes uint8 weights, got {values.dtype}")
        resized = images._area_resize(values.reshape(*values.shape[:2], -1), size)
        return np.clip(np.rint(resized), 0, 255).astype(np.uint8).reshape(size[1], size[0], *values.shape[2:])

    def undistort(self, values: np.ndarray, job) -> np.ndarray:
        """Through pycolmap's undistortion (bilinear), which the image itself went through (data/undistort.py)."""
        import pycolmap

        if values.dtype != np.uint8 or values.ndim != 2:
            raise TypeError(f"area undistortion takes uint8 [H, W] weights, got {values.dtype} {values.shape}")
        rgb = np.ascontiguousarray(np.repeat(values[:, :, None], 3, axis=2))
        bitmap, _ = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(rgb),
                                             job.camera)
        return np.ascontiguousarray(bitmap.to_array()[:, :, 0])

    def resize_tensor(self, values: torch.Tensor, size: images.Size) -> torch.Tensor:
        """[H, W, C] float on any device to `size`, as View.image_float shrinks the image."""
        chw = torch.nn.functional.interpolate(values.permute(2, 0, 1)[None], size=(size[1], size[0]), mode="area")
        return chw[0].permute(1, 2, 0).contiguous()


class Nearest:
    """Values of any dtype: each pixel the value of the source pixel under its centre; 0 where none lies."""

    name = "nearest"

    def resize(self, values: np.ndarray, size: images.Size) -> np.ndarray:
        rows = centre_indices(values.shape[0], size[1])
        columns = centre_indices(values.shape[1], size[0])
        return np.ascontiguousarray(values[rows[:, None], columns[None, :]])

    def undistort(self, values: np.ndarray, job) -> np.ndarray:
        """Each pixel of the pinhole image looks up the distorted pixel its ray falls in (what pycolmap's
        undistortion interpolates bilinearly, here without mixing); `values` are at the distorted camera's size."""
        pinhole, camera = job.pinhole, job.camera
        width, height = pinhole.width, pinhole.height
        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        rays = np.asarray(pinhole.cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1)), dtype=np.float64)
        found = np.asarray(camera.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], axis=1)),
                           dtype=np.float64)
        with np.errstate(invalid="ignore"):
            column, row = np.floor(found[:, 0]), np.floor(found[:, 1])
            inside = np.isfinite(found).all(axis=1) & (column >= 0) & (column < camera.width) & (row >= 0) & \
                (row < camera.height)
        out = np.zeros((height * width, *values.shape[2:]), dtype=values.dtype)
        out[inside] = values[row[inside].astype(np.int64), column[inside].astype(np.int64)]
        return out.reshape(height, width, *values.shape[2:])

    def resize_tensor(self, values: torch.Tensor, size: images.Size) -> torch.Tensor:
        """[H, W, C] on any device to `size`, by the same rule as `resize`."""
        rows = torch.from_numpy(centre_indices(values.shape[0], size[1])).to(values.device)
        columns = torch.from_numpy(centre_indices(values.shape[1], size[0])).to(values.device)
        return values.index_select(0, rows).index_select(1, columns)


def centre_indices(old: int, new: int) -> np.ndarray:
    """For each of `new` pixels along an axis, the one of `old` pixels its centre falls in."""
    return np.minimum(np.floor((np.arange(new) + 0.5) * (old / new)).astype(np.int64), old - 1)


AREA = Area()
NEAREST = Nearest()
