"""3D Gaussian splatting on CPU (own rasterisers) or CUDA (gsplat): model, render, train, export.

``render`` is the one rasterisation call; ``GaussianModel``/``init_from_points`` hold and
create the Gaussians; ``Trainer`` optimises them against posed images; ``write_ply`` and
``read_ply`` speak the standard 3DGS PLY. The recipe stage is ``toolkit.splat.stage``.
"""

from toolkit.splat.export import read_ply, write_ply
from toolkit.splat.model import GaussianModel, Gaussians, init_from_points
from toolkit.splat.rasterize import RenderMeta, RenderOutput, render

__all__ = [
    "GaussianModel",
    "Gaussians",
    "RenderMeta",
    "RenderOutput",
    "init_from_points",
    "read_ply",
    "render",
    "write_ply",
]
