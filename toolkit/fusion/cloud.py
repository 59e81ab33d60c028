"""Scaled depth -> coloured world-frame points, without invalid, far and flying pixels.

Flying pixels are the ramps a network (or any blur) puts across depth edges: points
floating between a chair and the wall behind it. A pixel is dropped when the depth range
in its neighbourhood is large relative to its own depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from toolkit.camera import PinholeCamera


@dataclass
class CloudOptions:
    """What a frame contributes to the map."""

    min_depth_m: float = 0.2
    max_depth_m: float = 6.0  # monocular depth far away is mostly guesswork
    edge_threshold: float = 0.06  # drop pixels whose 5x5 depth range exceeds this x depth
    edge_window: int = 5
    stride: int = 2  # every n-th pixel in both directions
    # Nearer than near_depth_m only every near_stride-th pixel (a multiple of stride): there
    # even that spacing is below half a voxel, so the frame still reaches every voxel it
    # sees, with fewer redundant points (0: off).
    near_stride: int = 0
    near_depth_m: float = 0.0
    # Drop pixels where inverse depth bends: |L(1 / z)| x z above this, L OpenCV's 3x3
    # Laplacian aperture (4x the 5-point one) after a 1-pixel Gaussian (0: off). Any
    # plane is affine in inverse depth, so flat surfaces pass whatever their slant; the
    # gentle ramps a smooth network draws across depth edges bend at both ends and are
    # too gradual for the range test above.
    ramp_threshold: float = 0.0


class RayCache:
    """Pixel rays of one camera at one stride, computed once (undistortion is costly)."""

    def __init__(self, camera: PinholeCamera, stride: int = 1) -> None:
        self.camera = camera
        self.stride = stride
        rays = camera.pixel_rays()[::stride, ::stride]  # [h, w, 3] with z = 1
        self.rays = np.ascontiguousarray(rays, dtype=np.float32)
        self.shape = rays.shape[:2]
        # [h, w] bool: pixels a ray reaches (not beyond the lens model's turning radius);
        # None when all do
        finite = np.isfinite(rays[..., 0])
        self.reachable: np.ndarray | None = None if finite.all() else finite
        h, w = self.shape
        # [h * w] flat full-resolution index of every strided pixel: gathering colours
        # from the contiguous image is 4x faster than from a strided view of it.
        self.pixel_index = ((np.arange(h)[:, None] * stride) * camera.width
                            + np.arange(w)[None, :] * stride).ravel()
        self._off_grid: dict[int, np.ndarray] = {}

    def off_grid(self, near_stride: int) -> np.ndarray:
        """[h, w] bool: strided pixels that are not on the coarser ``near_stride`` grid."""
        if near_stride not in self._off_grid:
            k = max(1, near_stride // self.stride)
            g = np.ones(self.shape, bool)
            g[::k, ::k] = False
            self._off_grid[near_stride] = g
        return self._off_grid[near_stride]


def edge_mask(depth: np.ndarray, threshold: float, window: int = 5,
              stride: int = 1) -> np.ndarray:
    """[H, W] bool: pixels near a depth discontinuity (flying-pixel candidates); with
    ``stride``, those of every stride-th pixel only ([::stride, ::stride] of it)."""
    d = np.ascontiguousarray(depth, dtype=np.float32)
    bad = ~np.isfinite(d)
    if bad.any():
        d = d.copy()  # non-finite pixels become 0 in it, not in the caller's
        d[bad] = 0.0
    kernel = np.ones((window, window), np.uint8)
    hi = cv2.dilate(d, kernel)
    # Invalid pixels (0) must not look like a jump to zero; lift them before the min filter.
    # OpenCV's threshold and add, not np.where: a third of the time on 640x480.
    lift = cv2.threshold(d, 0.0, 1e6, cv2.THRESH_BINARY_INV)[1]
    lo = cv2.erode(cv2.add(d, lift), kernel)
    s = stride
    return hi[::s, ::s] - lo[::s, ::s] > threshold * d[::s, ::s]


def valid_pixels(depth: np.ndarray, opts: CloudOptions, stride: int = 1) -> np.ndarray:
    """[H, W] bool: finite, within the depth range and not on an edge; with ``stride``,
    the same of every stride-th pixel only ([::stride, ::stride] of it: the filters see
    every pixel, the tests after them only those)."""
    d = depth[::stride, ::stride]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(d) & (d >= opts.min_depth_m) & (d <= opts.max_depth_m)
    if opts.edge_threshold > 0:
        ok &= ~edge_mask(depth, opts.edge_threshold, opts.edge_window, stride)
    if opts.ramp_threshold > 0:
        ok &= ~ramp_mask(depth, opts.ramp_threshold, stride)
    return ok


def ramp_mask(depth: np.ndarray, threshold: float, stride: int = 1) -> np.ndarray:
    """[H, W] bool: pixels where the inverse depth is not locally planar: its Laplacian
    (OpenCV's 3x3 aperture [[2, 0, 2], [0, -8, 0], [2, 0, 2]], 4x the 5-point one; after a
    1-pixel Gaussian) above ``threshold`` x the inverse depth itself. Pixels within 4 of
    invalid ones (non-finite or <= 0) count as bent. With ``stride``, every stride-th
    pixel's ([::stride, ::stride] of it)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        # NaN and -inf fail the test, and 1 / +inf is 0 as well.
        inv = np.where(depth > 0, 1.0 / depth, 0.0).astype(np.float32, copy=False)
    # Continued linearly past the border (odd reflection): a mirrored plane would bend there.
    r = 4  # the Gaussian's 3 pixels and the Laplacian's 1
    padded = np.pad(inv, r, mode="reflect", reflect_type="odd")
    lap = cv2.Laplacian(cv2.GaussianBlur(padded, (7, 7), 1.0), cv2.CV_32F, ksize=3)
    s = stride
    return np.abs(lap[r:-r:s, r:-r:s]) > threshold * inv[::s, ::s]


def depth_to_points(depth: np.ndarray, rgb: np.ndarray, rays: RayCache,
                    T_world_camera: np.ndarray, opts: CloudOptions,
                    extra_mask: np.ndarray | None = None,
                    valid: np.ndarray | None = None) -> tuple[
                        np.ndarray, np.ndarray, np.ndarray]:
    """World points [N, 3] float32, colours [N, 3] uint8 and their flat pixel indices [N] in
    the strided grid, from a full-resolution scaled depth [H, W] and image [H, W, 3].

    ``extra_mask`` [H, W] bool removes more pixels (e.g. known dynamic ones); ``valid``
    is ``valid_pixels(depth, opts)`` when the caller already has it.
    """
    s = rays.stride
    if np.shape(T_world_camera) != (4, 4):
        raise ValueError(f"T_world_camera must be [4, 4], got {list(np.shape(T_world_camera))}")
    if depth.shape != (rays.camera.height, rays.camera.width):
        raise ValueError(f"depth {depth.shape} does not match the camera "
                         f"{rays.camera.height}x{rays.camera.width}")
    if rgb.shape[:2] != depth.shape:
        raise ValueError(f"image {rgb.shape[:2]} does not match the depth {depth.shape}")
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        # An RGBA image read as three channels a pixel gave half the points shifted colours.
        raise ValueError(f"image {list(rgb.shape)}: give an RGB image [H, W, 3] (drop an "
                         "alpha channel, stack a grey one)")
    ok = valid_pixels(depth, opts, s) if valid is None else valid[::s, ::s]
    if rays.reachable is not None:
        ok = ok & rays.reachable
    if extra_mask is not None:
        ok = ok & ~extra_mask[::s, ::s]
    if opts.near_stride > s and opts.near_depth_m > 0:
        with np.errstate(invalid="ignore"):
            ok = ok & ~((depth[::s, ::s] < opts.near_depth_m) & rays.off_grid(opts.near_stride))
    # Flat indices into the strided grid: measured faster than 2-D boolean masks on the
    # strided views, even though the reshapes copy the grid.
    idx = np.flatnonzero(ok)
    z = depth[::s, ::s].reshape(-1)[idx].astype(np.float32)
    # np.take along axis 0: row gathers of [N, 3] arrays at a third of fancy indexing's cost.
    pc = np.take(rays.rays.reshape(-1, 3), idx, axis=0) * z[:, None]  # [N, 3] camera frame
    R = T_world_camera[:3, :3].astype(np.float32)
    t = T_world_camera[:3, 3].astype(np.float32)
    pw = pc @ R.T
    pw += t
    col = np.take(rgb.reshape(-1, 3), rays.pixel_index[idx], axis=0)
    return pw, col, idx
