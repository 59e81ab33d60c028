"""The standard 3DGS PLY: what the original viewer, SuperSplat and other viewers open.

One binary little-endian vertex element of float32 properties, in this order:
``x y z nx ny nz f_dc_0..2 f_rest_0..(3K-1) opacity scale_0..2 rot_0..3`` with

- normals written as zeros (the original code writes them; some viewers expect them);
- ``f_rest`` channel-major: all K red coefficients, then green, then blue;
- values before activation: opacity a logit, scales logs, ``rot`` an unnormalised
  quaternion with w first.

Open3D reads the file as a point cloud (x y z and the zero normals), which is how the
tests check that it is a valid PLY for generic tools too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from toolkit.errors import InputError, MissingInputError
from toolkit.io.atomic import atomic_path
from toolkit.splat.model import GaussianModel
from toolkit.splat.sh import degree_from_bases


def ply_attributes(n_rest: int) -> list[str]:
    """Property names for ``n_rest`` higher-band coefficients per channel."""
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def model_to_array(model: GaussianModel) -> np.ndarray:
    """[N] structured float32 array in the PLY layout."""
    s = model.state()
    n = len(model)
    rest = s["shN"]  # [N, K, 3]
    f_rest = rest.transpose(1, 2).reshape(n, -1)  # [N, 3K] channel-major
    normals = torch.zeros(n, 3, device="cpu")  # in the 3DGS layout, unused
    cols = [s["means"], normals, s["sh0"], f_rest, s["opacity_logits"][:, None],
            s["log_scales"], s["quats"]]
    flat = torch.cat([c.to(torch.float32) for c in cols], 1).numpy()
    names = ply_attributes(rest.shape[1])
    arr = np.empty(n, dtype=[(a, "<f4") for a in names])
    for i, a in enumerate(names):
        arr[a] = flat[:, i]
    return arr


def write_ply(path: Path | str, model: GaussianModel) -> None:
    """Write the model atomically as a binary 3DGS PLY."""
    arr = model_to_array(model)
    bad = ~np.all(np.isfinite(np.stack([arr[a] for a in arr.dtype.names], 1)), axis=1)
    if bad.any():
        raise InputError(f"{path}: {int(bad.sum())} of {len(arr)} Gaussians have non-finite "
                         "parameters (training diverged); not written")
    el = PlyElement.describe(arr, "vertex")
    with atomic_path(Path(path)) as tmp:
        PlyData([el], text=False, byte_order="<").write(str(tmp))


def read_ply(path: Path | str, dtype: torch.dtype = torch.float32) -> GaussianModel:
    """Read a 3DGS PLY (ours or another tool's) back into a model."""
    path = Path(path)
    if not path.exists():
        raise MissingInputError(f"{path}: splat file not found")
    try:
        ply = PlyData.read(str(path))
    except Exception as e:  # noqa: BLE001 - plyfile raises several kinds, none naming the file
        raise InputError(f"{path}: not a readable PLY file ({type(e).__name__}: {e}); a "
                         "truncated download or another format") from e
    if "vertex" not in ply:
        raise InputError(f"{path}: no 'vertex' element; not a Gaussian splat PLY")
    v = ply["vertex"].data
    names = set(v.dtype.names or ())
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [a for a in need if a not in names]
    if missing:
        raise InputError(f"{path}: missing properties {missing}; not a 3DGS PLY")
    rest_names = sorted((a for a in names if a.startswith("f_rest_")),
                        key=lambda a: int(a.split("_")[-1]))
    if len(rest_names) % 3:
        raise InputError(f"{path}: {len(rest_names)} f_rest properties is not a multiple of 3")
    k = len(rest_names) // 3
    degree_from_bases(k + 1)  # raises for an impossible band count

    def col(*keys: str) -> torch.Tensor:
        return torch.as_tensor(np.stack([np.asarray(v[a], dtype=np.float64) for a in keys], 1),
                               dtype=dtype)

    n = len(v)
    shN = (col(*rest_names).reshape(n, 3, k).transpose(1, 2) if k
           else torch.zeros(n, 0, 3, dtype=dtype))
    return GaussianModel(
        col("x", "y", "z"),
        col("scale_0", "scale_1", "scale_2"),
        col("rot_0", "rot_1", "rot_2", "rot_3"),
        col("opacity")[:, 0],
        col("f_dc_0", "f_dc_1", "f_dc_2"),
        shN.contiguous(),
    )
