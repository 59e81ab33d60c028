"""Shared pieces of the CPU rasterisers: camera tensors, EWA projection, tile binning.

The projection and the compositing rules follow gsplat's "classic" 3DGS rasteriser
(EWA splatting, 0.3 px screen-space dilation, opacity-aware bounding boxes, alpha clamped
at 0.999, skip below 1/255, stop when transmittance would fall to 1e-4) so that the CPU
and CUDA backends render the same image from the same model.

Pixel convention: the toolkit's (``toolkit.camera``): pixel (u, v) has its centre at integer
coordinates, so pixel (0, 0) spans [-0.5, 0.5]. gsplat puts pixel centres at i + 0.5; the
gsplat backend shifts the principal point by half a pixel to compensate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from toolkit.camera import PinholeCamera
from toolkit.splat.sh import eval_sh

ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped (and bound the footprint)
ALPHA_MAX = 0.999  # a single Gaussian never makes a pixel fully opaque
T_MIN = 1e-4  # a pixel stops accumulating once its transmittance would drop to this
MAX_EXTEND = 3.33  # footprint cap in standard deviations (gsplat's)
# Footprint half-extents are stored as int32 no larger than this: a box this wide covers the
# image from any centre within 2^30 - width pixels of it, and a radius past 2^31 wrapped to
# -2^31 in the cast (a Gaussian of scale e^18 m 1 m in front of the camera covered no pixel
# at all, while listed as visible).
MAX_RADIUS_PX = float(1 << 30)


@dataclass
class CameraTensors:
    """A pinhole camera and its world-to-camera pose as tensors for one render."""

    viewmat: Tensor  # [4, 4] T_camera_world (may require grad: pose refinement)
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def of(cls, camera: PinholeCamera, T_camera_world: np.ndarray | Tensor,
           dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> (
        CameraTensors
    ):
        if camera.has_distortion:
            raise ValueError("the rasteriser takes an undistorted camera: undistort the "
                             "images and use camera.undistorted()")
        if isinstance(T_camera_world, Tensor):
            viewmat = T_camera_world.to(dtype=dtype, device=device)
        else:
            viewmat = torch.as_tensor(np.asarray(T_camera_world), dtype=dtype, device=device)
        if viewmat.shape != (4, 4):
            raise ValueError(f"T_camera_world must be [4, 4], got {tuple(viewmat.shape)}")
        return cls(viewmat, float(camera.fx), float(camera.fy), float(camera.cx),
                   float(camera.cy), camera.width, camera.height)


@dataclass
class Projected:
    """Gaussians that survived culling, in screen space (packed: only visible ones)."""

    gaussian_ids: Tensor  # [M] int64 index into the model
    means2d: Tensor  # [M, 2] pixels
    conics: Tensor  # [M, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    depths: Tensor  # [M] camera-frame z
    colors: Tensor  # [M, 3] view-dependent RGB
    opacities: Tensor  # [M] after sigmoid
    radii: Tensor  # [M, 2] int32 half-extent of the footprint box in pixels (x, y)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[M, 3, 3] rotation matrices of (unnormalised) wxyz quaternions [M, 4]."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(-1, 3, 3)


def survivor_colors(
    means: Tensor,  # [N, 3]
    sh: Tensor,  # [N, K, 3]
    sh_rest: Tensor | None,  # [N, K2, 3] further bands appended to ``sh``
    gids: Tensor,  # [M] int64 visible Gaussians
    viewmat: Tensor,  # [4, 4]
    sh_degree: int,
) -> Tensor:
    """[M, 3] view-dependent RGB of the visible Gaussians (differentiable, viewmat too)."""
    # Colours only for the survivors: SH evaluation is the costliest per-Gaussian step.
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    cam_pos = -R.T @ t  # [3]
    dirs = torch.index_select(means, 0, gids) - cam_pos
    k = (sh_degree + 1) ** 2  # bands in use; the rest are not even gathered
    coeffs = torch.index_select(sh[:, :k], 0, gids)
    if sh_rest is not None and coeffs.shape[1] < k:
        rest = torch.index_select(sh_rest[:, : k - coeffs.shape[1]], 0, gids)
        coeffs = torch.cat([coeffs, rest], 1)
    return eval_sh(coeffs, dirs, sh_degree)


def project(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    log_scales: Tensor,  # [N, 3]
    opacity_logits: Tensor,  # [N]
    sh: Tensor,  # [N, K, 3]
    cam: CameraTensors,
    sh_degree: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    sh_rest: Tensor | None = None,  # [N, K2, 3] further bands appended to ``sh``
) -> Projected:
    """EWA-project Gaussians into ``cam``: Sigma' = J W Sigma W^T J^T + eps2d I, then cull.

    Culled: behind ``near`` or beyond ``far``, degenerate 2D covariance, opacity below
    1/255, or footprint box entirely off the image. Differentiable in every input tensor,
    ``cam.viewmat`` included.
    """
    W = cam.viewmat
    R, t = W[:3, :3], W[:3, 3]
    # Same clamp as gsplat: Gaussians far outside the view get the Jacobian of the frustum
    # edge, which keeps their footprint finite.
    tan_x, tan_y = 0.5 * cam.width / cam.fx, 0.5 * cam.height / cam.fy
    cxg, cyg = cam.cx + 0.5, cam.cy + 0.5  # gsplat's principal point (pixel centres at +0.5)
    lim_xp, lim_xn = (cam.width - cxg) / cam.fx + 0.3 * tan_x, cxg / cam.fx + 0.3 * tan_x
    lim_yp, lim_yn = (cam.height - cyg) / cam.fy + 0.3 * tan_y, cyg / cam.fy + 0.3 * tan_y

    # 1) Cheap conservative cull without autograd (depth range, and a footprint bound from
    #    the largest scale), so the differentiable maths runs on candidates only. It never
    #    drops a Gaussian the exact test in 3) would keep.
    with torch.no_grad():
        pc = means.detach() @ R.detach().T + t.detach()  # [N, 3]
        z = pc[:, 2]
        ok = (z > near) & (z < far)
        zs = torch.where(ok, z, torch.ones_like(z))
        smax = torch.exp(log_scales.detach().amax(-1))
        jx = cam.fx / zs * math.sqrt(1.0 + max(lim_xp, lim_xn) ** 2)
        jy = cam.fy / zs * math.sqrt(1.0 + max(lim_yp, lim_yn) ** 2)
        rxb = MAX_EXTEND * torch.sqrt((jx * smax) ** 2 + eps2d) + 1.0
        ryb = MAX_EXTEND * torch.sqrt((jy * smax) ** 2 + eps2d) + 1.0
        u = cam.fx * pc[:, 0] / zs + cxg
        v = cam.fy * pc[:, 1] / zs + cyg
        ok &= (u + rxb > 0) & (u - rxb < cam.width) & (v + ryb > 0) & (v - ryb < cam.height)
        # A scale whose exp overflows makes a or c inf or NaN, so 3) culls it anyway; it must
        # not reach 2): autograd's 0 * inf there is NaN, which would spread through the
        # viewmat's gradient to every Gaussian (the C++ backward gives culled ones 0).
        ok &= torch.isfinite(smax)
        ids = torch.nonzero(ok).squeeze(1)

    # 2) EWA projection of the candidates. index_select, not x[ids]: its backward is an
    #    index_add, several times faster on CPU than the index_put of advanced indexing.
    p = torch.index_select(means, 0, ids) @ R.T + t  # [M, 3] camera frame
    x, y, z = p.unbind(-1)
    rz = 1.0 / z
    tx = z * torch.clamp(x * rz, -lim_xn, lim_xp)
    ty = z * torch.clamp(y * rz, -lim_yn, lim_yp)
    rz2 = rz * rz
    # Rows of J W_R ([M, 3] each); Sigma' = (J W_R R_q S)(J W_R R_q S)^T needs only these
    # two rows times the 3x3 factor R_q S, all elementwise (batched 3x3 matmuls are slow).
    A0 = (cam.fx * rz)[:, None] * R[0] - (cam.fx * tx * rz2)[:, None] * R[2]
    A1 = (cam.fy * rz)[:, None] * R[1] - (cam.fy * ty * rz2)[:, None] * R[2]
    Rq = quat_to_rotmat(torch.index_select(quats, 0, ids))  # [M, 3, 3]
    s = torch.exp(torch.index_select(log_scales, 0, ids))  # [M, 3]
    # Clamped to the largest finite value: a finite scale can still overflow T (|J W_R| > 1)
    # and then T * T's backward, 0 * inf, is NaN. a or c is inf with or without the clamp,
    # so 3) culls the same Gaussians, and a survivor's T is far inside the clamp.
    big = torch.finfo(s.dtype).max
    T0 = ((A0[:, :, None] * Rq).sum(1) * s).clamp(-big, big)  # [M, 3] row 0 of J W_R R_q S
    T1 = ((A1[:, :, None] * Rq).sum(1) * s).clamp(-big, big)
    a = (T0 * T0).sum(-1) + eps2d
    b = (T0 * T1).sum(-1)
    c = (T1 * T1).sum(-1) + eps2d
    det = a * c - b * b
    mx = cam.fx * x * rz + cam.cx
    my = cam.fy * y * rz + cam.cy
    opac_logit = torch.index_select(opacity_logits, 0, ids)

    # 3) Exact visibility (gsplat's rules) and footprint boxes, without autograd.
    with torch.no_grad():
        op = torch.sigmoid(opac_logit.detach())
        extend = torch.sqrt(2.0 * torch.log(op.clamp_min(ALPHA_MIN) / ALPHA_MIN))
        extend = extend.clamp(max=MAX_EXTEND)
        rx = torch.ceil(extend * torch.sqrt(a.detach().clamp_min(0)))
        ry = torch.ceil(extend * torch.sqrt(c.detach().clamp_min(0)))
        mxd, myd = mx.detach() + 0.5, my.detach() + 0.5  # gsplat's convention for the test
        keep = (
            (det.detach() > 0)
            & (op >= ALPHA_MIN)
            & ((rx > 0) | (ry > 0))
            & (mxd + rx > 0) & (mxd - rx < cam.width)
            & (myd + ry > 0) & (myd - ry < cam.height)
            & torch.isfinite(rx) & torch.isfinite(ry)
        )
        sel = torch.nonzero(keep).squeeze(1)
        radii = torch.stack([rx[sel], ry[sel]], -1).clamp(max=MAX_RADIUS_PX).to(torch.int32)

    # One gather of everything per visible Gaussian; the culled ones' det may be <= 0, so
    # divide only after selecting.
    packed = torch.index_select(torch.stack([mx, my, a, b, c, z, opac_logit], -1), 0, sel)
    mx, my, a, b, c, z, opac_logit = packed.unbind(-1)
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], -1)
    gids = ids[sel]
    colors = survivor_colors(means, sh, sh_rest, gids, W, sh_degree)
    return Projected(gids, torch.stack([mx, my], -1), conics, z, colors, torch.sigmoid(opac_logit),
                     radii)


@dataclass
class TileBins:
    """Which Gaussians touch which tile, each tile's list in front-to-back order (CSR)."""

    tile_size: int
    tiles_x: int
    tiles_y: int
    offsets: Tensor  # [tiles_x * tiles_y + 1] int32, list of tile t is ids[offsets[t]:offsets[t+1]]
    ids: Tensor  # [P] int32 index into the packed (projected) Gaussians
    rects: Tensor  # [M, 4] int32 pixel box x0, x1, y0, y1 (inclusive) clipped to the image


def pixel_rects(means2d: Tensor, radii: Tensor, width: int, height: int) -> Tensor:
    """[M, 4] int32 inclusive pixel boxes (x0, x1, y0, y1) of the footprints, clipped.

    A box with x0 > x1 or y0 > y1 covers no pixel centre.
    """
    m = means2d.detach()
    r = radii.to(m.dtype)
    x0 = torch.ceil(m[:, 0] - r[:, 0]).clamp(0, width - 1)
    x1 = torch.floor(m[:, 0] + r[:, 0]).clamp(-1, width - 1)
    y0 = torch.ceil(m[:, 1] - r[:, 1]).clamp(0, height - 1)
    y1 = torch.floor(m[:, 1] + r[:, 1]).clamp(-1, height - 1)
    return torch.stack([x0, x1, y0, y1], -1).to(torch.int32)


def bin_tiles(proj: Projected, width: int, height: int, tile_size: int) -> TileBins:
    """Tile lists in plain torch: expand (Gaussian, tile) pairs, sort by (tile, depth)."""
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n_tiles = tiles_x * tiles_y
    rects = pixel_rects(proj.means2d, proj.radii, width, height)
    with torch.no_grad():
        # Depth rank first so that a stable sort by tile keeps front-to-back order inside
        # each tile; ties in depth keep the model order (the C++ binning does the same).
        order = torch.argsort(proj.depths.detach(), stable=True)
        r = rects[order].long()
        empty = (r[:, 0] > r[:, 1]) | (r[:, 2] > r[:, 3])
        tx0, tx1 = r[:, 0] // tile_size, r[:, 1] // tile_size
        ty0, ty1 = r[:, 2] // tile_size, r[:, 3] // tile_size
        nx = torch.where(empty, 0, tx1 - tx0 + 1)
        ny = torch.where(empty, 0, ty1 - ty0 + 1)
        counts = nx * ny  # [M]
        total = int(counts.sum())
        g = torch.repeat_interleave(torch.arange(len(order)), counts)  # [P] rank
        start = torch.cumsum(counts, 0) - counts
        local = torch.arange(total) - start[g]
        nxg = nx[g].clamp_min(1)
        tile = (ty0[g] + local // nxg) * tiles_x + (tx0[g] + local % nxg)
        tile_sorted, perm = torch.sort(tile, stable=True)
        ids = order[g[perm]].to(torch.int32)
        offsets = torch.zeros(n_tiles + 1, dtype=torch.int64)
        offsets[1:] = torch.cumsum(torch.bincount(tile_sorted, minlength=n_tiles), 0)
    return TileBins(tile_size, tiles_x, tiles_y, offsets.to(torch.int32), ids, rects)
