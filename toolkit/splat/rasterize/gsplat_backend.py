"""The CUDA backend: ``gsplat.rasterization`` behind the toolkit's ``render`` interface.

gsplat (optional extra ``cuda``) is only used for CUDA tensors. Its settings are the ones the
CPU rasterisers reproduce: classic (not antialiased) mode, 0.3 px dilation, packed output,
expected depth ("RGB+ED"), SH colours with gsplat's +0.5 offset. gsplat puts pixel centres
at i + 0.5 where the toolkit puts them at i, so the principal point is shifted by half a
pixel; the two conventions then render the same image.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from toolkit.splat.model import Gaussians
from toolkit.splat.rasterize.common import CameraTensors

_reason: str | None = None
# What to do about ``_reason``: the fix differs by cause (on a GPU machine without nvcc,
# "install the cuda extra on a machine with an NVIDIA GPU" named two things already there).
_fix: str | None = None
_FIX_NO_GPU = ("run it on a machine with an NVIDIA GPU that torch sees "
               "(torch.cuda.is_available(); torch's CPU build sees none)")
_FIX_INSTALL = "install the cuda extra: pip install -e '.[cuda]'"


def _toolkit_fix() -> str:
    cuda = torch.version.cuda
    return (f"install the CUDA toolkit {cuda + ' ' if cuda else ''}(the version torch was "
            "built with; nvcc) and point CUDA_HOME at it")


def _unusable(reason: str, fix: str) -> bool:
    global _reason, _fix
    _reason, _fix = reason, fix
    return False


def _import() -> Any:
    try:
        # unused-ignore: gsplat is missing only on some machines, and imports are checked
        # only without --ignore-missing-imports.
        import gsplat  # type: ignore[import-not-found, unused-ignore]
    except Exception as exc:  # noqa: BLE001 - gsplat's import may fail in many ways (CUDA JIT)
        _unusable(f"cannot import gsplat: {exc}", _FIX_INSTALL)
        return None
    return gsplat


def available() -> bool:
    """gsplat imports, its CUDA kernels load (built on first use: minutes) and a CUDA
    device is present."""
    if not torch.cuda.is_available():
        return _unusable("no CUDA device", _FIX_NO_GPU)
    if _import() is None:
        return False
    # gsplat imports without its kernels and builds them at the first render; build (or
    # load) them here, so that a machine without the CUDA toolkit is found before training.
    try:
        from gsplat.cuda._backend import _C  # type: ignore[import-not-found, unused-ignore]
    except Exception as exc:  # noqa: BLE001 - a failed nvcc / ninja build raises many kinds
        return _unusable(f"gsplat could not build its CUDA kernels: {type(exc).__name__}: "
                         f"{exc}", f"{_toolkit_fix()}, with a C++ compiler and ninja")
    if _C is None:
        # Seen on an H100 machine with the toolkit moved away (session 29): gsplat prints
        # "No CUDA toolkit found" and imports with _C None.
        return _unusable("gsplat found no CUDA toolkit to build its kernels with (no nvcc, "
                         "CUDA_HOME unset)", _toolkit_fix())
    return True


def unavailable_reason() -> str | None:
    return _reason


def unavailable_fix() -> str | None:
    """What to do about ``unavailable_reason()``."""
    return _fix


def render(g: Gaussians, cam: CameraTensors, background: Tensor, sh_degree: int, near: float,
           far: float, eps2d: float) -> Any:
    """Same contract as ``toolkit.splat.rasterize.render`` (returns a RenderOutput)."""
    from toolkit.splat.rasterize import RenderMeta, RenderOutput

    gsplat = _import()
    if gsplat is None:
        raise RuntimeError(_reason)
    dev, dt = g.means.device, g.means.dtype
    K = torch.tensor([[cam.fx, 0.0, cam.cx + 0.5], [0.0, cam.fy, cam.cy + 0.5],
                      [0.0, 0.0, 1.0]], dtype=dt, device=dev)
    colors, alphas, info = gsplat.rasterization(
        means=g.means,
        quats=g.quats,
        scales=torch.exp(g.log_scales),
        opacities=torch.sigmoid(g.opacity_logits),
        colors=g.full_sh(),
        viewmats=cam.viewmat[None],
        Ks=K[None],
        width=cam.width,
        height=cam.height,
        near_plane=near,
        far_plane=far,
        eps2d=eps2d,
        sh_degree=sh_degree,
        # No backgrounds: gsplat 1.5.3's packed rasteriser checks them against the packed
        # means' leading dimensions (none) and so refuses the per-camera [1, 4] that its own
        # rasterization() passes on; the background is composited below instead.
        render_mode="RGB+ED",
        packed=True,
        rasterize_mode="classic",
    )
    alpha = alphas[0, ..., 0]  # [H, W]
    # What the light left after the last Gaussian (1 - alpha) shows the background.
    color = colors[0, ..., :3] + (1.0 - alpha)[..., None] * background  # [H, W, 3]
    depth = colors[0, ..., 3]  # [H, W] expected depth, already divided by alpha
    means2d = info["means2d"]  # [nnz, 2], gsplat pixel convention
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = info["radii"]
    if radii.dim() == 1:  # gsplat < 1.5 gives one radius per Gaussian
        radii = radii[:, None].expand(-1, 2)
    meta = RenderMeta(
        gaussian_ids=info["gaussian_ids"].long(),
        means2d=means2d,
        radii=radii.to(torch.int32),
        depths=info["depths"].detach(),
        width=cam.width,
        height=cam.height,
        n_gaussians=len(g.means),
        backend="gsplat",
    )
    return RenderOutput(color, depth, alpha, meta)
