"""``python -m toolkit.recipe doctor``: what this installation can run, and what to fix.

One line per part: the packages the toolkit imports (version, or why the import failed
and the pip command that installs it), the splat rasteriser's two paths (the C++ one on
the CPU: a compiler and the cached build; gsplat on a CUDA GPU) and the depth network's
onnxruntime providers. Nothing is downloaded, and nothing is compiled unless ``--build``
asks (the C++ rasteriser takes about a minute, gsplat's kernels minutes): without it the
doctor says whether the first run will have to. The JSON form (``--json``) is what to
paste into a bug report.
"""

from __future__ import annotations

import importlib
import os
import platform
import shutil
import sys
from dataclasses import asdict, dataclass
from importlib import metadata
from typing import Any, Literal

Status = Literal["ok", "note", "missing"]


@dataclass(frozen=True)
class Check:
    """One part: ``status`` ok (works), note (works, with a caveat, or optional and
    absent) or missing (a required part that does not work: runs will fail)."""

    part: str
    status: Status
    detail: str
    fix: str = ""


# (import name, distribution to pip install, required). Required: install_requires.
PACKAGES: tuple[tuple[str, str, bool], ...] = (
    ("numpy", "numpy", True),
    ("scipy", "scipy", True),
    ("torch", "torch", True),
    ("open3d", "open3d-cpu", True),
    ("cv2", "opencv-python-headless", True),
    ("pycolmap", "pycolmap", True),
    ("onnxruntime", "onnxruntime", True),
    ("onnx", "onnx", True),
    ("sklearn", "scikit-learn", True),
    ("skimage", "scikit-image", True),
    ("yaml", "PyYAML", True),
    ("pydantic", "pydantic", True),
    ("rich", "rich", True),
    ("matplotlib", "matplotlib", True),
    ("plyfile", "plyfile", True),
    ("rosbags", "rosbags", True),
    ("gsplat", "gsplat", False),  # the cuda extra
)


def _version(module: Any, dist: str) -> str:
    version = getattr(module, "__version__", None)
    if isinstance(version, str):
        return version
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "version unknown"


def check_package(name: str, dist: str, required: bool) -> Check:
    """Import ``name``; its version, or the failure and the install command."""
    if name == "gsplat":
        # Importing gsplat can start its CUDA kernel build; its version is enough here.
        try:
            return Check(name, "ok", metadata.version("gsplat"))
        except metadata.PackageNotFoundError:
            return Check(name, "note", "not installed (only used on a CUDA GPU)",
                         "pip install -e '.[cuda]' on a machine with a CUDA GPU")
    try:
        module = importlib.import_module(name)
    except Exception as exc:  # noqa: BLE001 - an import fails in many ways (a missing .so)
        text = str(exc).strip().splitlines()
        reason = f"{type(exc).__name__}: {text[0] if text else ''}"
        status: Status = "missing" if required else "note"
        return Check(name, status, f"cannot import: {reason}",
                     f"bash install.sh (or pip install '{dist}')")
    return Check(name, "ok", _version(module, dist))


def check_torch_device() -> Check:
    """Which device torch sees; a CUDA build without a device is a note, not a fault."""
    import torch

    cuda = torch.version.cuda
    if torch.cuda.is_available():
        return Check("torch device", "ok",
                     f"CUDA {cuda}: {torch.cuda.get_device_name()} "
                     f"({torch.cuda.device_count()} device(s)); {torch.get_num_threads()} "
                     "CPU threads")
    build = f"CUDA {cuda} build, no usable GPU" if cuda else "CPU build"
    return Check("torch device", "ok", f"CPU only ({build}); {torch.get_num_threads()} "
                 "CPU threads")


def check_cpp_rasteriser(build: bool = False) -> Check:
    """The splat stage's CPU rasteriser: a C++ compiler, and whether its build is cached."""
    from toolkit.splat.rasterize import cpp_ext

    if os.environ.get(cpp_ext.ENV_DISABLE):
        return Check("splat C++ rasteriser", "note",
                     f"disabled by ${cpp_ext.ENV_DISABLE}: the PyTorch reference is used "
                     "(about 10x slower)", f"unset {cpp_ext.ENV_DISABLE}")
    compiler = os.environ.get("CXX", "c++")
    found = shutil.which(compiler)
    if found is None:
        return Check("splat C++ rasteriser", "note",
                     f"no C++ compiler ({compiler!r} not on PATH): splat trains with the "
                     "PyTorch reference, about 10x slower",
                     "install g++ (apt install g++), or set CXX")
    name = cpp_ext.build_name()
    folder = cpp_ext.cache_root() / name
    built = any(folder.glob(f"{name}*.so")) or any(folder.glob(f"{name}*.pyd"))
    if build and not built:
        if cpp_ext.load_extension() is None:
            return Check("splat C++ rasteriser", "note",
                         f"build failed ({cpp_ext.extension_error()}): splat trains with the "
                         "PyTorch reference", "python -c 'from toolkit.splat.rasterize "
                         "import cpp_ext; cpp_ext.load_extension(verbose=True)' shows the "
                         "compiler's output")
        built = True
    if built:
        return Check("splat C++ rasteriser", "ok", f"built ({folder}); compiler {found}")
    return Check("splat C++ rasteriser", "note",
                 f"not built yet: the first splat run compiles it (about a minute) with "
                 f"{found}, into {folder}", "python -m toolkit.recipe doctor --build")


def check_gsplat(build: bool = False) -> Check:
    """The splat stage's GPU path: a CUDA device and gsplat with its kernels."""
    import torch

    if not torch.cuda.is_available():
        return Check("splat on a GPU (gsplat)", "note",
                     "no CUDA device: the splat stage trains on the CPU")
    try:
        version = metadata.version("gsplat")
    except metadata.PackageNotFoundError:
        return Check("splat on a GPU (gsplat)", "note",
                     "a CUDA device but no gsplat: the splat stage trains on the CPU",
                     "pip install -e '.[cuda]'")
    if not build:
        return Check("splat on a GPU (gsplat)", "ok",
                     f"gsplat {version}; its CUDA kernels are built (minutes, nvcc) or "
                     "loaded at the first GPU run", "python -m toolkit.recipe doctor "
                     "--build checks the build now")
    from toolkit.splat.rasterize import gsplat_backend

    if gsplat_backend.available():
        return Check("splat on a GPU (gsplat)", "ok", f"gsplat {version}, kernels built")
    return Check("splat on a GPU (gsplat)", "note",
                 f"unusable: {gsplat_backend.unavailable_reason()}; the splat stage trains "
                 "on the CPU", gsplat_backend.unavailable_fix() or "")


def check_onnxruntime() -> Check:
    """The depth network's execution providers (CUDA only with onnxruntime-gpu)."""
    import onnxruntime as ort

    providers = ort.get_available_providers()
    detail = ", ".join(providers)
    if "CUDAExecutionProvider" in providers:
        return Check("depth network (onnxruntime)", "ok", f"{detail} (device: auto uses CUDA)")
    return Check("depth network (onnxruntime)", "ok", f"{detail} (the CPU build)")


def collect(build: bool = False) -> list[Check]:
    """Every check, packages first; the device checks only where their package imports."""
    checks = [Check("python", "ok" if sys.version_info >= (3, 11) else "missing",
                    f"{platform.python_version()} on {platform.platform()}, "
                    f"{os.cpu_count()} CPU(s)",
                    "" if sys.version_info >= (3, 11) else "Python 3.11 or newer")]
    try:
        checks.append(Check("lidarcam-recon", "ok", metadata.version("lidarcam-recon")))
    except metadata.PackageNotFoundError:
        checks.append(Check("lidarcam-recon", "note", "not installed as a package (imported "
                            "from a folder on the path)", "bash install.sh"))
    packages = [check_package(*p) for p in PACKAGES]
    checks += packages
    imported = {c.part for c in packages if c.status == "ok"}
    if "torch" in imported:
        checks += [check_torch_device(), check_cpp_rasteriser(build)]
        checks.append(check_gsplat(build))
    if "onnxruntime" in imported:
        checks.append(check_onnxruntime())
    return checks


def as_dict(checks: list[Check]) -> dict[str, Any]:
    """JSON form: the checks and whether a required part is missing."""
    return {"ok": all(c.status != "missing" for c in checks),
            "checks": [asdict(c) for c in checks]}
