"""The Gaussian model: parameters stored before activation, as in 3DGS and its PLY files.

- means [N, 3] world frame (metres)
- log_scales [N, 3] (scale = exp)
- quats [N, 4] wxyz, unnormalised (normalised where used)
- opacity_logits [N] (opacity = sigmoid)
- sh0 [N, 3] DC colour coefficient; shN [N, K, 3] higher bands, K = (degree+1)^2 - 1

Initialisation follows 3DGS/gsplat: one Gaussian per point of the (subsampled) fused cloud,
isotropic scale from the mean distance to the 3 nearest neighbours, identity rotation,
opacity 0.1, DC colour from the point colour. ``init_random_in_views`` is the start without
a fused cloud (the paper's "MonoGS with lidar" row): points on random camera rays at random
depths, grey, then the same per-point initialisation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor, nn

from toolkit.camera import PinholeCamera
from toolkit.splat.sh import num_sh_bases, rgb_to_sh0

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh0", "shN")


@dataclass
class Gaussians:
    """The tensors a rasteriser needs (a view of a model, or hand-made for tests)."""

    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4] wxyz
    log_scales: Tensor  # [N, 3]
    opacity_logits: Tensor  # [N]
    sh: Tensor  # [N, K, 3] SH coefficients, DC first (only the leading bands if sh_rest)
    # Optional further bands [N, K2, 3], appended to ``sh``. A model passes its DC and higher
    # bands separately so that a render gathers the visible rows of each instead of
    # concatenating the whole model's coefficients every step.
    sh_rest: Tensor | None = None

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def num_bases(self) -> int:
        return self.sh.shape[1] + (0 if self.sh_rest is None else self.sh_rest.shape[1])

    def full_sh(self) -> Tensor:
        """[N, K, 3] all coefficients in one tensor."""
        return self.sh if self.sh_rest is None else torch.cat([self.sh, self.sh_rest], 1)


class GaussianModel(nn.Module):
    """Trainable Gaussians; parameters live in ``self.params`` under ``PARAM_NAMES``."""

    def __init__(self, means: Tensor, log_scales: Tensor, quats: Tensor, opacity_logits: Tensor,
                 sh0: Tensor, shN: Tensor) -> None:
        super().__init__()
        n = means.shape[0]
        shapes = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4),
                  "opacity_logits": (n,), "sh0": (n, 3)}
        given = {"means": means, "log_scales": log_scales, "quats": quats,
                 "opacity_logits": opacity_logits, "sh0": sh0}
        for k, shape in shapes.items():
            if tuple(given[k].shape) != shape:
                raise ValueError(f"{k} must be {list(shape)}, got {list(given[k].shape)}")
        if shN.dim() != 3 or shN.shape[0] != n or shN.shape[2] != 3:
            raise ValueError(f"shN must be [N, K, 3], got {list(shN.shape)}")
        if shN.shape[1] + 1 not in (1, 4, 9, 16):
            raise ValueError(f"shN has {shN.shape[1]} bands per channel; expected 0, 3, 8 or 15")
        self.params = nn.ParameterDict(
            {k: nn.Parameter(v.detach().clone().contiguous()) for k, v in
             {**given, "shN": shN}.items()}
        )

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def means(self) -> Tensor:
        return self.params["means"]

    @property
    def log_scales(self) -> Tensor:
        return self.params["log_scales"]

    @property
    def quats(self) -> Tensor:
        return self.params["quats"]

    @property
    def opacity_logits(self) -> Tensor:
        return self.params["opacity_logits"]

    @property
    def sh0(self) -> Tensor:
        return self.params["sh0"]

    @property
    def shN(self) -> Tensor:
        return self.params["shN"]

    @property
    def max_sh_degree(self) -> int:
        return {1: 0, 4: 1, 9: 2, 16: 3}[self.shN.shape[1] + 1]

    @property
    def opacities(self) -> Tensor:
        """[N] after sigmoid."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def scales(self) -> Tensor:
        """[N, 3] after exp."""
        return torch.exp(self.log_scales)

    def gaussians(self) -> Gaussians:
        """Rasteriser input; gradients flow back into the parameters."""
        return Gaussians(self.means, self.quats, self.log_scales, self.opacity_logits,
                         self.sh0[:, None, :], self.shN)

    def replace_params(self, new: dict[str, Tensor]) -> None:
        """Swap in new parameter tensors (densification changes N)."""
        for k, v in new.items():
            self.params[k] = v if isinstance(v, nn.Parameter) else nn.Parameter(v)

    def state(self) -> dict[str, Tensor]:
        """Detached CPU copies of all parameters (for checkpoints and export)."""
        return {k: v.detach().cpu().clone() for k, v in self.params.items()}

    @classmethod
    def from_state(cls, state: dict[str, Tensor]) -> GaussianModel:
        return cls(state["means"], state["log_scales"], state["quats"], state["opacity_logits"],
                   state["sh0"], state["shN"])

    # ------------------------------------------------------------------ constructors
    @classmethod
    def empty(cls, n: int, sh_degree: int = 3, dtype: torch.dtype = torch.float32) -> (
        GaussianModel
    ):
        """``n`` unit Gaussians at the origin (placeholder shapes, e.g. before loading)."""
        k = num_sh_bases(sh_degree) - 1
        quats = torch.zeros(n, 4, dtype=dtype)
        quats[:, 0] = 1
        return cls(torch.zeros(n, 3, dtype=dtype), torch.zeros(n, 3, dtype=dtype), quats,
                   torch.zeros(n, dtype=dtype), torch.zeros(n, 3, dtype=dtype),
                   torch.zeros(n, k, 3, dtype=dtype))


def init_from_points(
    points: np.ndarray,  # [P, 3]
    colors: np.ndarray | None = None,  # [P, 3] RGB 0..1 (or uint8 0..255)
    budget: int | None = None,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    scale_factor: float = 1.0,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> GaussianModel:
    """One Gaussian per point (a random subset of ``budget`` if the cloud is larger).

    Scale: mean distance to the 3 nearest neighbours (``scale_factor`` times it), the same
    on all axes; duplicate points get the smallest positive distance found instead of 0.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise ValueError("cannot initialise Gaussians from an empty point cloud")
    finite = np.all(np.isfinite(pts), axis=1)
    if colors is None:
        rgb = np.full((len(pts), 3), 0.5)
    else:
        rgb = np.asarray(colors, dtype=np.float64).reshape(-1, 3)
        if len(rgb) != len(pts):
            raise ValueError(f"{len(rgb)} colours for {len(pts)} points; give one RGB per "
                             "point")
        # A NaN colour trains NaN Gaussians that spread to their neighbours' gradients.
        finite &= np.all(np.isfinite(rgb), axis=1)
        # The range is judged on the finite rows: one NaN made the maximum NaN, and a
        # 0..255 cloud was then clipped to white.
        if np.asarray(colors).dtype.kind in "ui" or rgb[finite].max(initial=0.0) > 1.5:
            rgb = rgb / 255.0  # 8-bit colours (a float cloud a hair over 1 is still 0..1)
        rgb = np.clip(rgb, 0.0, 1.0)
    pts, rgb = pts[finite], rgb[finite]
    if len(pts) == 0:
        raise ValueError("no point of the cloud has a finite position and colour")
    if budget is not None and len(pts) > budget:
        keep = np.random.default_rng(seed).choice(len(pts), size=budget, replace=False)
        keep.sort()
        pts, rgb = pts[keep], rgb[keep]
    if not 0.0 < init_opacity < 1.0:
        raise ValueError(f"init_opacity must be in (0, 1), got {init_opacity}")
    n = len(pts)
    k = min(4, n)  # self + 3 neighbours
    if n > 1:
        d, _ = cKDTree(pts).query(pts, k=k)
        dist = d[:, 1:].mean(axis=1)
    else:
        dist = np.ones(1)
    positive = dist[dist > 0]
    floor = positive.min() if len(positive) else 1e-3
    dist = np.maximum(dist, floor) * scale_factor
    log_s = np.log(dist)[:, None].repeat(3, axis=1)
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    logit = float(np.log(init_opacity / (1.0 - init_opacity)))

    def t(x: np.ndarray) -> Tensor:
        return torch.as_tensor(x, dtype=dtype)

    sh0 = rgb_to_sh0(t(rgb))
    shN = torch.zeros(n, num_sh_bases(sh_degree) - 1, 3, dtype=dtype)
    return GaussianModel(t(pts), t(log_s), t(quats), torch.full((n,), logit, dtype=dtype), sh0,
                         shN)


def random_points_in_views(
    cameras: Sequence[PinholeCamera],
    T_world_cameras: Sequence[np.ndarray],  # each [4, 4]
    n: int,
    depth_range_m: tuple[float, float] = (0.3, 5.0),
    seed: int = 0,
) -> np.ndarray:
    """[n, 3] world points on random pixel rays of random views, at random z-depths.

    Views are drawn uniformly, pixels uniformly over the image, z uniformly in
    ``depth_range_m``: every point lies in some camera's frustum, so each starts with a
    gradient, and the density follows what the cameras saw (more where views overlap).
    Uniform in depth rather than in volume on purpose: uniform in volume puts most points
    near the far limit, which in rooms is behind the walls.
    """
    if len(cameras) != len(T_world_cameras) or not cameras:
        raise ValueError("need one pose per camera and at least one view")
    near, far = depth_range_m
    if not 0.0 < near < far:
        raise ValueError(f"depth_range_m must satisfy 0 < near < far, got {depth_range_m}")
    rng = np.random.default_rng(seed)
    which = rng.integers(0, len(cameras), size=n)
    out = np.empty((n, 3))
    for k in np.unique(which):
        m = which == k
        cam, T = cameras[k], np.asarray(T_world_cameras[k], dtype=np.float64)
        uv = np.stack([rng.uniform(-0.5, cam.width - 0.5, m.sum()),
                       rng.uniform(-0.5, cam.height - 0.5, m.sum())], -1)
        p_cam = cam.backproject(uv, rng.uniform(near, far, m.sum()))  # [M, 3]
        out[m] = p_cam @ T[:3, :3].T + T[:3, 3]
    return out


def init_random_in_views(
    cameras: Sequence[PinholeCamera],
    T_world_cameras: Sequence[np.ndarray],
    n: int,
    depth_range_m: tuple[float, float] = (0.3, 5.0),
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> GaussianModel:
    """``n`` grey Gaussians at ``random_points_in_views`` (no point cloud needed).

    Grey (0.5) as 3DGS's random initialisation effectively is (its random SH DC values are
    below 1/255); scales from the 3-NN spacing like ``init_from_points``.
    """
    pts = random_points_in_views(cameras, T_world_cameras, n, depth_range_m, seed)
    return init_from_points(pts, np.full_like(pts, 0.5), sh_degree=sh_degree,
                            init_opacity=init_opacity, seed=seed, dtype=dtype)
