"""The plain-PyTorch rasteriser: the reference and test oracle for the faster backends.

Compositing works on padded blocks: a chunk of tiles with at most K Gaussians each becomes
[tiles, K, pixels] tensors, front-to-back order along K. Transmittance is an exclusive
cumulative product, and early termination is a mask from the inclusive product (the
sequential rule "stop before the Gaussian that would take T to <= 1e-4" keeps exactly the
prefix whose inclusive product stays above 1e-4). Autograd does the backward.

It is several times slower than the C++ path and needs far more memory; what it offers is
that every rule is a few visible tensor expressions, with no loop over pixels or Gaussians.
"""

from __future__ import annotations

import torch
from torch import Tensor

from toolkit.splat.rasterize.common import ALPHA_MAX, ALPHA_MIN, T_MIN, Projected, TileBins

# Elements of one [tiles, K, pixels] block; bounds the memory of one chunk's intermediates.
CHUNK_ELEMENTS = 1 << 21


def _composite_chunk(
    tiles: Tensor,  # [m] tile indices
    bins: TileBins,
    means2d: Tensor,  # [M, 2]
    conics: Tensor,  # [M, 3]
    feats: Tensor,  # [M, C]
    opac: Tensor,  # [M]
) -> tuple[Tensor, Tensor]:
    ts = bins.tile_size
    off = bins.offsets.long()
    start, count = off[tiles], off[tiles + 1] - off[tiles]  # [m]
    K = int(count.max())
    k = torch.arange(K)
    present = k[None, :] < count[:, None]  # [m, K]
    pair = torch.where(present, start[:, None] + k[None, :], 0)
    gid = bins.ids.long()[pair]  # [m, K]
    # Pixel centres of each tile: [m, ts*ts].
    local = torch.arange(ts * ts)
    px = ((tiles % bins.tiles_x) * ts)[:, None] + (local % ts)[None, :]
    py = ((tiles // bins.tiles_x) * ts)[:, None] + (local // ts)[None, :]
    dtype = means2d.dtype
    dx = means2d[gid, 0][:, :, None] - px[:, None, :].to(dtype)  # [m, K, P]
    dy = means2d[gid, 1][:, :, None] - py[:, None, :].to(dtype)
    cg = conics[gid]  # [m, K, 3]
    sigma = 0.5 * (cg[..., 0:1] * dx * dx + cg[..., 2:3] * dy * dy) + cg[..., 1:2] * dx * dy
    alpha = torch.clamp(opac[gid][:, :, None] * torch.exp(-sigma), max=ALPHA_MAX)
    valid = present[:, :, None] & (sigma >= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        keep = torch.cumprod(1.0 - alpha, dim=1) > T_MIN  # early termination
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    T_incl = torch.cumprod(1.0 - alpha, dim=1)  # [m, K, P]
    T_excl = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], 1)
    w = alpha * T_excl
    accum = torch.einsum("mkp,mkc->mpc", w, feats[gid])  # [m, P, C]
    return accum, T_incl[:, -1]


def composite(
    proj: Projected, bins: TileBins, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """[H, W, 4] accumulated (RGB, depth) and [H, W] final transmittance."""
    feats = torch.cat([proj.colors, proj.depths[:, None]], -1)  # [M, 4]
    C = feats.shape[1]
    ts = bins.tile_size
    n_tiles = bins.tiles_x * bins.tiles_y
    counts = (bins.offsets[1:] - bins.offsets[:-1]).long()
    busy = torch.nonzero(counts > 0).squeeze(1)
    # Chunks of tiles with similar list lengths waste little padding.
    busy = busy[torch.argsort(counts[busy], stable=True)]
    results_a, results_t, chunks = [], [], []
    i = 0
    while i < len(busy):
        j = i + 1
        while j < len(busy) and (j + 1 - i) * int(counts[busy[j]]) * ts * ts <= CHUNK_ELEMENTS:
            j += 1
        tiles = busy[i:j]
        a, t = _composite_chunk(tiles, bins, proj.means2d, proj.conics, feats, proj.opacities)
        results_a.append(a)
        results_t.append(t)
        chunks.append(tiles)
        i = j
    dtype = feats.dtype
    accum = torch.zeros(n_tiles, ts * ts, C, dtype=dtype)
    T = torch.ones(n_tiles, ts * ts, dtype=dtype)
    if chunks:
        tiles = torch.cat(chunks)
        accum = accum.index_copy(0, tiles, torch.cat(results_a))
        T = T.index_copy(0, tiles, torch.cat(results_t))
    # [tiles_y, tiles_x, ts, ts] -> image rows and columns, then crop the padding.
    accum = accum.reshape(bins.tiles_y, bins.tiles_x, ts, ts, C).permute(0, 2, 1, 3, 4)
    accum = accum.reshape(bins.tiles_y * ts, bins.tiles_x * ts, C)[:height, :width]
    T = T.reshape(bins.tiles_y, bins.tiles_x, ts, ts).permute(0, 2, 1, 3)
    T = T.reshape(bins.tiles_y * ts, bins.tiles_x * ts)[:height, :width]
    return accum, T
