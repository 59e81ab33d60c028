"""The fast CPU path: projection and tile compositing in a C++/OpenMP extension built on first use.

``torch.utils.cpp_extension.load`` compiles ``csrc/composite.cpp`` with gcc (``-O3
-fopenmp -ffast-math -march=native``) into a per-user cache folder; later processes load the
cached build in well under a second. The build folder's name hashes the source, the flags,
the torch/Python versions and the CPU, so an edit, an upgrade or a different machine
sharing a home folder gets its own build. Where no compiler is present or the build
fails, ``load_extension`` returns None, the reason is logged once, and ``render`` falls back
to the PyTorch reference.

What runs here: the EWA projection and culling (``project_cpp``: what ``common.project``
computes, forward and backward, the camera pose's gradient included), the tile binning (a
counting sort) and the compositing forward and backward. The SH colours of the visible
Gaussians stay in PyTorch (autograd). Every kernel is one OpenMP loop whose results do not
depend on the thread count (sums over Gaussians run over fixed blocks in a fixed order),
so CPU training stays bit-identical run to run.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import platform
import shutil
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import torch
from torch import Tensor

from toolkit.splat.rasterize.common import (
    CameraTensors,
    Projected,
    TileBins,
    pixel_rects,
    survivor_colors,
)

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

SOURCE = Path(__file__).parent / "csrc" / "composite.cpp"
CFLAGS = ["-O3", "-fopenmp", "-ffast-math", "-march=native"]
# -ffast-math stays out of the link flags: linking with it pulls in crtfastmath.o, which
# would switch the whole process to flush-denormals-to-zero.
LDFLAGS = ["-fopenmp"]
ENV_CACHE = "TOOLKIT_EXT_CACHE"
ENV_DISABLE = "TOOLKIT_NO_CPP_EXT"

_lock = threading.Lock()
_state: dict[str, Any] = {"tried": False, "module": None, "error": None}
_threads: dict[str, int | None] = {"composite": None}


def set_threads(n: int | None) -> None:
    """Threads of the compositing kernels; None follows ``torch.get_num_threads()``.

    Compositing is one parallel loop per pass, so it keeps its speed-up on a machine busy
    with other work, where PyTorch's hundreds of small parallel regions per step do not;
    that is why it can be set apart from torch's thread count.
    """
    if n is not None and n < 1:
        raise ValueError(f"thread count must be >= 1, got {n}")
    _threads["composite"] = n


def get_threads() -> int:
    n = _threads["composite"]
    return torch.get_num_threads() if n is None else n


def cache_root() -> Path:
    """Where builds are kept: $TOOLKIT_EXT_CACHE, else $XDG_CACHE_HOME or ~/.cache."""
    env = os.environ.get(ENV_CACHE)
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "lidarcam-recon" / "torch_extensions"


def _cpu_signature() -> str:
    # -march=native code can crash on another CPU model: key the build on the CPU.
    try:
        text = Path("/proc/cpuinfo").read_text(errors="ignore")
        lines = [ln for ln in text.splitlines() if ln.startswith(("model name", "flags"))][:2]
        return "\n".join(lines)
    except OSError:
        return platform.processor() or platform.machine()


def build_name() -> str:
    """Extension module name: stable for one source, flag set, toolchain, CPU and torch
    installation."""
    h = hashlib.sha256()
    # The torch folder too: ninja's build file names its include and library folders, so
    # two environments with the same torch version (a project's venv and a CI clone's)
    # sharing one build folder rebuilt it (about a minute) each time they took turns.
    torch_dir = str(Path(torch.__file__).resolve().parent)
    for part in (SOURCE.read_bytes(), " ".join(CFLAGS + LDFLAGS).encode(),
                 torch.__version__.encode(), sys.version.encode(), _cpu_signature().encode(),
                 torch_dir.encode()):
        h.update(part)
    return f"toolkit_splat_composite_{h.hexdigest()[:16]}"


# torch's own build lock: a file that ``load`` creates (O_EXCL) and deletes when done.
TORCH_BATON = "lock"
# Ours beside it, held with flock: the kernel lets go of it when its process dies.
BUILD_LOCK = ".toolkit_build.lock"


@contextlib.contextmanager
def _build_lock(build_dir: Path) -> Iterator[None]:
    """Hold the build folder for one process at a time, and clear the lock torch's
    ``load`` left in it when a process was killed while holding it.

    ``load`` takes the folder by creating its ``lock`` file and deletes it when it is
    done; a process killed in between (SIGKILL during the first build, which takes a
    minute or more; a ``timeout``) leaves the file, and every later ``load`` waited for it
    to go, forever and without a word: a splat stage that never ended. Every build here
    holds this flock first, so a ``lock`` file found while holding it belongs to no live
    build of ours and is removed. (A process of a toolkit from before this lock, building
    the same source at that moment, is not seen.)"""
    if fcntl is None:  # Windows: torch's file lock alone, as before
        yield
        return
    with open(build_dir / BUILD_LOCK, "a") as handle:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX)  # another build of ours: wait for it
        try:
            baton = build_dir / TORCH_BATON
            if baton.exists():
                log.warning("C++ rasteriser: removing %s, left by a build that was killed; "
                            "building again", baton)
                baton.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)


def load_extension(verbose: bool = False) -> ModuleType | None:
    """The compiled module, building it on the first call; None when it cannot be built."""
    with _lock:
        if _state["tried"]:
            return _state["module"]
        _state["tried"] = True
        if os.environ.get(ENV_DISABLE):
            _state["error"] = f"disabled by ${ENV_DISABLE}"
            log.info("C++ rasteriser %s; using the PyTorch reference", _state["error"])
            return None
        compiler = os.environ.get("CXX", "c++")
        if shutil.which(compiler) is None:
            _state["error"] = f"no C++ compiler ({compiler!r} not on PATH)"
            log.warning("C++ rasteriser unavailable: %s; falling back to the PyTorch "
                        "reference (about 10x slower). Install g++ to enable it.",
                        _state["error"])
            return None
        try:
            from torch.utils.cpp_extension import load

            name = build_name()
            build_dir = cache_root() / name
            build_dir.mkdir(parents=True, exist_ok=True)
            # Compile a copy kept in the build folder: ninja's build file names the source
            # by absolute path, so another checkout or install of the same source (a CI
            # clone, a second venv) would otherwise rebuild it (about a minute) each time
            # the two take turns. The folder name already hashes the source's content.
            src = build_dir / SOURCE.name
            with _build_lock(build_dir):
                if not src.is_file():
                    from toolkit.io.atomic import atomic_write_bytes

                    atomic_write_bytes(src, SOURCE.read_bytes())
                _state["module"] = load(
                    name=name,
                    sources=[str(src)],
                    extra_cflags=CFLAGS,
                    extra_ldflags=LDFLAGS,
                    build_directory=str(build_dir),
                    verbose=verbose,
                )
        except Exception as exc:  # noqa: BLE001 - any build failure means: fall back
            _state["error"] = f"{type(exc).__name__}: {str(exc).strip().splitlines()[-1:]}"
            log.warning("C++ rasteriser build failed (%s); falling back to the PyTorch "
                        "reference. Run with verbose=True for the compiler output.",
                        _state["error"])
            _state["module"] = None
        return _state["module"]


def extension_error() -> str | None:
    """Why the extension is unavailable (None if it loaded or was never tried)."""
    return _state["error"]


def available() -> bool:
    return load_extension() is not None


class _Composite(torch.autograd.Function):
    """Differentiable compositing: (means2d, conics, features, opacities) -> image, T."""

    @staticmethod
    def forward(
        ctx: Any,
        means2d: Tensor,  # [M, 2]
        conics: Tensor,  # [M, 3]
        feats: Tensor,  # [M, C]
        opacities: Tensor,  # [M]
        rects: Tensor,  # [M, 4] int32
        offsets: Tensor,  # [T + 1] int32
        ids: Tensor,  # [P] int32
        width: int,
        height: int,
        tile_size: int,
    ) -> tuple[Tensor, Tensor]:
        ext = load_extension()
        assert ext is not None
        args = [x.contiguous() for x in (means2d, conics, feats, opacities)]
        threads = get_threads()
        accum, T, last = ext.composite_forward(*args, rects, offsets, ids, width, height,
                                               tile_size, threads)
        ctx.save_for_backward(*args, rects, offsets, ids, T, last)
        ctx.dims = (width, height, tile_size, threads)
        return accum, T  # [H, W, C], [H, W]

    @staticmethod
    def backward(ctx: Any, g_accum: Tensor, g_T: Tensor) -> tuple[Tensor | None, ...]:
        ext = load_extension()
        assert ext is not None
        means2d, conics, feats, opac, rects, offsets, ids, T, last = ctx.saved_tensors
        width, height, tile_size, threads = ctx.dims
        g_m, g_c, g_f, g_o = ext.composite_backward(
            means2d, conics, feats, opac, rects, offsets, ids, width, height, tile_size, T, last,
            g_accum.contiguous(), g_T.contiguous(), threads,
        )
        return g_m, g_c, g_f, g_o, None, None, None, None, None, None


def bin_tiles_cpp(proj: Projected, width: int, height: int, tile_size: int) -> TileBins:
    """Same lists as ``common.bin_tiles`` (identical order), by a counting sort in C++."""
    ext = load_extension()
    assert ext is not None
    rects = pixel_rects(proj.means2d, proj.radii, width, height).contiguous()
    # torch.argsort(stable=True)'s order by a radix sort (a tenth of its time)
    order = ext.depth_order(proj.depths.detach())
    offsets, ids = ext.bin_tiles(rects, order, width, height, tile_size)
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    return TileBins(tile_size, tiles_x, tiles_y, offsets, ids, rects)


def composite(proj: Projected, bins: TileBins, width: int, height: int) -> tuple[Tensor, Tensor]:
    """[H, W, 4] accumulated (RGB, depth) and [H, W] final transmittance."""
    feats = torch.cat([proj.colors, proj.depths[:, None]], -1)  # [M, 4]
    return _Composite.apply(proj.means2d, proj.conics, feats, proj.opacities, bins.rects,
                            bins.offsets, bins.ids, width, height, bins.tile_size)


class _Project(torch.autograd.Function):
    """Differentiable EWA projection and culling, what ``common.project`` computes but SH.

    Outputs (packed, visible Gaussians only): ids [M] int64, means2d [M, 2], conics [M, 3],
    depths [M], opacities [M], radii [M, 2] int32. The backward recomputes the per-Gaussian
    intermediates instead of saving them.
    """

    @staticmethod
    def forward(
        ctx: Any,
        means: Tensor,  # [N, 3]
        quats: Tensor,  # [N, 4] wxyz, unnormalised
        log_scales: Tensor,  # [N, 3]
        opacity_logits: Tensor,  # [N]
        viewmat: Tensor,  # [4, 4]
        intrinsics: tuple[float, float, float, float, int, int],  # fx, fy, cx, cy, W, H
        near: float,
        far: float,
        eps2d: float,
    ) -> tuple[Tensor, ...]:
        ext = load_extension()
        assert ext is not None
        args = [x.contiguous() for x in (means, quats, log_scales, opacity_logits, viewmat)]
        threads = get_threads()
        gids, means2d, conics, depths, opac, radii = ext.project_forward(
            *args, *intrinsics, near, far, eps2d, threads)
        ctx.save_for_backward(*args, gids)
        ctx.consts = (intrinsics, near, far, eps2d, threads)
        ctx.mark_non_differentiable(gids, radii)
        return gids, means2d, conics, depths, opac, radii

    @staticmethod
    def backward(
        ctx: Any, _g_ids: Tensor | None, g_means2d: Tensor, g_conics: Tensor, g_depths: Tensor,
        g_opac: Tensor, _g_radii: Tensor | None,
    ) -> tuple[Tensor | None, ...]:
        ext = load_extension()
        assert ext is not None
        means, quats, log_scales, logits, viewmat, gids = ctx.saved_tensors
        intrinsics, near, far, eps2d, threads = ctx.consts
        need_view = bool(ctx.needs_input_grad[4])
        g_m, g_q, g_s, g_o, g_v = ext.project_backward(
            means, quats, log_scales, logits, viewmat, gids, *intrinsics, near, far, eps2d,
            g_means2d, g_conics, g_depths, g_opac, need_view, threads)
        return g_m, g_q, g_s, g_o, (g_v if need_view else None), None, None, None, None


def project_cpp(
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
    """``common.project`` with the projection and culling (and their backward) in C++.

    Same survivors and outputs up to float rounding; SH colours of the survivors stay in
    PyTorch. Differentiable in every input tensor, ``cam.viewmat`` included.
    """
    intr = (float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy), int(cam.width),
            int(cam.height))
    gids, means2d, conics, depths, opac, radii = _Project.apply(
        means, quats, log_scales, opacity_logits, cam.viewmat, intr, float(near), float(far),
        float(eps2d))
    colors = survivor_colors(means, sh, sh_rest, gids, cam.viewmat, sh_degree)
    return Projected(gids, means2d, conics, depths, colors, opac, radii)
