"""The TSDF mesh rendered at the splats' held-out views, scored the same way as the splats.

The comparison the paper makes ("splats >= 3 dB above the TSDF mesh coloured by the same
images") is only exact when both are rendered at the same poses, at the same size, against
the same target images, with the same PSNR. Here:

- the mesh (vertex colours, barycentric interpolation: ``toolkit.baselines.tsdf.MeshRenderer``)
  is ray-cast at the full undistorted camera resolution and area-resized to the training size,
  i.e. exactly the processing the real images get (``stage.prepare_image``), so the mesh is
  not penalised for point sampling at the lower resolution;
- pixels whose ray hits nothing show the splats' background colour, and the headline PSNR is
  over all pixels (a hole is an error the splats would pay for too);
- "covered" pixels are those where every full-resolution ray hit the mesh; PSNR over them is
  given for the mesh and for the splats on the same pixels, which isolates colour quality
  from coverage.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from toolkit.camera import PinholeCamera
from toolkit.eval.image import psnr as psnr_fn
from toolkit.eval.image import ssim as ssim_fn
from toolkit.geometry import inv_se3


@dataclass
class MeshRender:
    """One view of the mesh at the evaluation size."""

    color: torch.Tensor  # [h, w, 3] float32 0..1
    coverage: np.ndarray  # [h, w] float32: fraction of full-resolution rays that hit

    @property
    def covered(self) -> np.ndarray:
        """[h, w] bool: every full-resolution ray of the pixel hit the mesh."""
        return self.coverage >= 1.0 - 1e-6


class MeshViewRenderer:
    """Render a coloured triangle mesh like the stage's evaluation images.

    ``camera_full`` is the undistorted full-resolution camera; ``size`` (w, h) the evaluation
    size; ``background`` RGB 0..1 for pixels that see no triangle.
    """

    def __init__(self, mesh_path: Path | str, camera_full: PinholeCamera,
                 size: tuple[int, int], background: tuple[float, float, float]) -> None:
        from toolkit.baselines.tsdf import MeshRenderer, read_mesh

        if camera_full.has_distortion:
            raise ValueError("pass the undistorted camera (the target images are undistorted)")
        mesh = read_mesh(mesh_path)
        self.n_triangles = len(mesh.triangles)
        self.has_colors = bool(mesh.has_vertex_colors())
        self.renderer = MeshRenderer(mesh)
        self.camera = camera_full
        self.size = size
        self.background_u8 = tuple(int(round(255 * float(c))) for c in background)

    def render(self, T_camera_world: np.ndarray) -> MeshRender:
        rgb, depth = self.renderer.render(self.camera, inv_se3(np.asarray(T_camera_world)),
                                          self.background_u8)  # type: ignore[arg-type]
        hit = (depth > 0).astype(np.float32)
        col = rgb.astype(np.float32) / 255.0
        if (col.shape[1], col.shape[0]) != self.size:
            col = cv2.resize(col, self.size, interpolation=cv2.INTER_AREA)
            hit = cv2.resize(hit, self.size, interpolation=cv2.INTER_AREA)
        return MeshRender(torch.from_numpy(np.ascontiguousarray(col)), hit)


@dataclass
class Comparison:
    """Per-view figures of the mesh and of the splats on the same views."""

    psnr_all: list[float]  # mesh, all pixels (background where no hit)
    ssim_all: list[float]
    psnr_covered: list[float]  # mesh, covered pixels only
    splat_psnr_covered: list[float]  # splats on the mesh's covered pixels
    coverage: list[float]  # fraction of covered pixels

    def __init__(self) -> None:
        self.psnr_all, self.ssim_all, self.psnr_covered = [], [], []
        self.splat_psnr_covered, self.coverage = [], []

    def add(self, mesh: MeshRender, splat: torch.Tensor, target: torch.Tensor,
            valid: torch.Tensor | None = None) -> None:
        """``splat`` and ``target``: [h, w, 3] float 0..1 (the stage's evaluation tensors);
        ``valid`` [h, w] bool: the pixels the splats are scored on (lens corners of an
        undistorted image have no source pixel), so that both are scored alike."""
        color = mesh.color
        if valid is not None:
            # As the splats' scores treat them: outside, the target itself.
            color = torch.where(valid[..., None], color, target)
        self.psnr_all.append(float(psnr_fn(color, target, mask=valid)))
        self.ssim_all.append(float(ssim_fn(color, target, mask=valid)))
        m = torch.from_numpy(mesh.covered)
        if valid is not None:
            m = m & valid
        self.coverage.append(float(m.float().mean()))
        if bool(m.any()):
            self.psnr_covered.append(float(psnr_fn(mesh.color, target, mask=m)))
            self.splat_psnr_covered.append(float(psnr_fn(splat, target, mask=m)))

    def metrics(self, prefix: str) -> dict[str, Any]:
        """Means over views, keys ``tsdf_<prefix>_*`` and ``<prefix>_psnr_on_tsdf_covered_db``."""
        def mean(x: list[float]) -> float:
            return float(np.mean(x)) if x else float("nan")

        return {
            f"tsdf_{prefix}_psnr_db": mean(self.psnr_all),
            f"tsdf_{prefix}_ssim": mean(self.ssim_all),
            f"tsdf_{prefix}_psnr_covered_db": mean(self.psnr_covered),
            f"tsdf_{prefix}_coverage": mean(self.coverage),
            f"{prefix}_psnr_on_tsdf_covered_db": mean(self.splat_psnr_covered),
        }
