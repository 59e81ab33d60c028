"""Differentiable Gaussian rasterisation behind one call: ``render``.

Backends (same inputs, same outputs, same image up to float rounding):

- ``cpp``: C++/OpenMP projection and compositing (``cpp_ext``; SH colours in PyTorch), the
  CPU default;
- ``torch``: everything in PyTorch (``torch_ref``), the reference and the fallback when the
  C++ extension cannot be built;
- ``gsplat``: ``gsplat.rasterization`` on a CUDA device (optional extra ``cuda``).

``backend="auto"`` picks gsplat for CUDA tensors when gsplat imports, else cpp, else torch.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from toolkit.camera import PinholeCamera
from toolkit.splat.model import GaussianModel, Gaussians
from toolkit.splat.rasterize import cpp_ext, torch_ref
from toolkit.splat.rasterize.common import CameraTensors, bin_tiles, project
from toolkit.splat.sh import degree_from_bases

log = logging.getLogger(__name__)

BACKENDS = ("auto", "cpp", "torch", "gsplat")
# Measured best on 2 cores at 320x240 (docs/splatting.md); results do not depend on the tile
# size because footprint boxes bound every contribution above the alpha threshold.
DEFAULT_TILE = {"cpp": 16, "torch": 8}


@dataclass
class RenderMeta:
    """What densification needs from a render (gsplat's ``info``, packed form)."""

    gaussian_ids: Tensor  # [M] int64 model index of each visible Gaussian
    means2d: Tensor  # [M, 2] pixels; retains its gradient after backward
    radii: Tensor  # [M, 2] int32 footprint half-extent in pixels (x, y)
    depths: Tensor  # [M] camera-frame z
    width: int
    height: int
    n_gaussians: int
    backend: str

    @property
    def visible(self) -> Tensor:
        """[N] bool over the whole model."""
        v = torch.zeros(self.n_gaussians, dtype=torch.bool, device=self.gaussian_ids.device)
        v[self.gaussian_ids] = True
        return v


@dataclass
class RenderOutput:
    """One rendered view; all image tensors are differentiable."""

    color: Tensor  # [H, W, 3] RGB in 0..1 (background composited behind)
    depth: Tensor  # [H, W] expected z-depth (accumulated depth / alpha), 0 where empty
    alpha: Tensor  # [H, W] accumulated opacity
    meta: RenderMeta


def resolve_backend(backend: str, device: torch.device) -> str:
    """The concrete backend ``render`` will use for tensors on ``device``."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasteriser backend {backend!r}; choose from {BACKENDS}")
    if device.type == "cuda":
        if backend in ("auto", "gsplat"):
            from toolkit.splat.rasterize import gsplat_backend

            if gsplat_backend.available():
                return "gsplat"
            if backend == "gsplat":
                raise RuntimeError(f"gsplat backend requested but unusable: "
                                   f"{gsplat_backend.unavailable_reason()}")
        # The CPU backends need CPU tensors; running them on CUDA data would copy every step.
        raise RuntimeError("CUDA tensors need the gsplat backend (pip install '.[cuda]'), or "
                           "move the model to the CPU")
    if backend == "gsplat":
        raise RuntimeError("the gsplat backend needs CUDA tensors")
    if backend in ("auto", "cpp"):
        if cpp_ext.available():
            return "cpp"
        if backend == "cpp":
            log.warning("C++ rasteriser unavailable (%s); using the PyTorch reference",
                        cpp_ext.extension_error())
    return "torch"


def render(
    gaussians: GaussianModel | Gaussians,
    camera: PinholeCamera,
    T_camera_world: np.ndarray | Tensor,
    background: Sequence[float] | Tensor | None = None,
    sh_degree: int | None = None,
    backend: str = "auto",
    tile_size: int | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> RenderOutput:
    """Render colour, depth and alpha of ``gaussians`` seen by ``camera`` at ``T_camera_world``.

    ``camera`` must be undistorted (undistort the images instead). ``T_camera_world`` [4, 4]
    maps world points into the optical camera frame; pass a tensor that requires grad to
    refine the pose. ``sh_degree`` defaults to the highest the coefficients allow.
    """
    g = gaussians.gaussians() if isinstance(gaussians, GaussianModel) else gaussians
    device = g.means.device
    dtype = g.means.dtype
    name = resolve_backend(backend, device)
    degree = degree_from_bases(g.num_bases) if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= degree_from_bases(g.num_bases):
        raise ValueError(f"sh_degree {degree} needs {(degree + 1) ** 2} SH coefficients per "
                         f"channel; the Gaussians have {g.num_bases}")
    bg = _background(background, dtype, device)
    cam = CameraTensors.of(camera, T_camera_world, dtype, device)
    if name == "gsplat":
        from toolkit.splat.rasterize import gsplat_backend

        return gsplat_backend.render(g, cam, bg, degree, near, far, eps2d)

    project_fn = cpp_ext.project_cpp if name == "cpp" else project
    proj = project_fn(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh, cam, degree,
                      near, far, eps2d, g.sh_rest)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()  # densification reads the screen-space gradient
    ts = tile_size or DEFAULT_TILE[name]
    W, H = cam.width, cam.height
    if name == "cpp":
        bins = cpp_ext.bin_tiles_cpp(proj, W, H, ts)
        accum, T = cpp_ext.composite(proj, bins, W, H)
    else:
        bins = bin_tiles(proj, W, H, ts)
        accum, T = torch_ref.composite(proj, bins, W, H)
    return _finish(accum, T, bg, proj.gaussian_ids, proj.means2d, proj.radii, proj.depths,
                   W, H, len(g.means), name)


def _background(background: Sequence[float] | Tensor | None, dtype: torch.dtype,
                device: torch.device) -> Tensor:
    if background is None:
        return torch.zeros(3, dtype=dtype, device=device)
    bg = torch.as_tensor(background, dtype=dtype, device=device).reshape(-1)
    if bg.shape != (3,):
        raise ValueError(f"background must be 3 values (RGB), got {tuple(bg.shape)}")
    return bg


def _finish(accum: Tensor, T: Tensor, bg: Tensor, ids: Tensor, means2d: Tensor, radii: Tensor,
            depths: Tensor, W: int, H: int, n: int, name: str) -> RenderOutput:
    alpha = 1.0 - T
    color = accum[..., :3] + T[..., None] * bg
    # Expected depth, normalised by coverage like gsplat's "ED" mode.
    depth = accum[..., 3] / alpha.clamp_min(1e-10)
    meta = RenderMeta(ids, means2d, radii, depths.detach(), W, H, n, name)
    return RenderOutput(color, depth, alpha, meta)


__all__ = ["BACKENDS", "RenderMeta", "RenderOutput", "render", "resolve_backend"]
