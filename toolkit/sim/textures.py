"""Surface materials made from the photographs scikit-image ships inside its wheel.

Every material is a square tile of ``TILE`` x ``TILE`` texels with a mip pyramid, packed
into one flat ``uint32`` array (RGBA bytes) so the renderer fetches a pixel's colour with a
single gather. Grey photographs (brick, grass, gravel, moon) are made seamless and tinted
per surface by the scene (the tint is the "per-surface colour variation"); colour
photographs become framed pictures on the walls. ``plaster`` and ``ceiling`` are
deliberately almost flat, as painted walls are in real houses: feature matchers and
photometric losses must cope with them.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from toolkit.errors import MissingInputError

TILE = 512  # texels per tile side (power of two: wrapping is a bit mask)
LEVELS = 4  # mip levels 0..3 (512, 256, 128, 64 texels)


@dataclass(frozen=True)
class Material:
    """How one material looks: its source image, scale and whether it repeats."""

    name: str
    source: str  # skimage data file, or "flat"
    metres_per_tile: float  # real-world size of one tile; 0 = stretch over the face (pictures)
    contrast: float = 1.0  # texture contrast around the mean (1 = as photographed)
    stretch: float = 1.0  # anisotropic stretch along u (wood grain from grass blades)
    seams: float = 0.0  # planks / tiles: dark seam every 1/seams of the tile (0 = none)


# The order is the material id stored per triangle; append only (ids end up in tests/plots).
MATERIALS: tuple[Material, ...] = (
    Material("plaster", "flat", 2.0, contrast=0.008),
    Material("ceiling", "flat", 2.0, contrast=0.006),
    Material("brick", "brick.png", 1.1),
    Material("stucco", "gravel.png", 0.9, contrast=0.3),
    Material("wood", "grass.png", 1.6, contrast=0.45, stretch=8.0, seams=4),
    Material("carpet", "gravel.png", 0.7, contrast=0.7),
    Material("tiles", "gravel.png", 1.2, contrast=0.35, seams=4),
    Material("stone", "moon.png", 1.8, contrast=0.8),
    Material("fabric", "grass.png", 0.45, contrast=0.35),
    Material("rug", "grass.png", 0.6, contrast=0.9),
    Material("paint", "flat", 1.0, contrast=0.03),
    Material("metal", "gravel.png", 1.0, contrast=0.06),
    Material("picture_astronaut", "astronaut.png", 0.0),
    Material("picture_cat", "chelsea.png", 0.0),
    Material("picture_coffee", "coffee.png", 0.0),
    Material("picture_rocket", "rocket.jpg", 0.0),
    Material("picture_motorcycle", "motorcycle_left.png", 0.0),
    Material("picture_hubble", "hubble_deep_field.jpg", 0.0),
    Material("picture_color", "color.png", 0.0),
    Material("picture_camera", "camera.png", 0.0),
    Material("skin", "flat", 1.0, contrast=0.02),
)
MATERIAL_ID: dict[str, int] = {m.name: i for i, m in enumerate(MATERIALS)}
PICTURES: tuple[str, ...] = tuple(m.name for m in MATERIALS if m.name.startswith("picture_"))


def skimage_data_dir() -> Path:
    """Folder of the images scikit-image ships (no download: they are in its wheel)."""
    import skimage

    return Path(skimage.__file__).parent / "data"


def _load(name: str) -> np.ndarray:
    path = skimage_data_dir() / name
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise MissingInputError(f"{path}: texture image missing from the scikit-image wheel")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _seamless(img: np.ndarray) -> np.ndarray:
    """Make a square image tile without visible seams.

    Cross-fades it with a copy rolled by half a tile: at the border the rolled copy (whose
    own border lies in the middle) takes over, so wrapping around is continuous.
    """
    s = img.shape[0]
    rolled = np.roll(img, (s // 2, s // 2), axis=(0, 1))
    ramp = 1.0 - np.abs(np.linspace(-1.0, 1.0, s))  # 0 at the edges, 1 in the middle
    w = np.minimum(ramp[:, None], ramp[None, :]).clip(0, 0.35) / 0.35  # [S, S]
    w = w.reshape(w.shape + (1,) * (img.ndim - 2))
    return (w * img + (1.0 - w) * rolled).astype(np.float32)


def _material_image(m: Material, rng: np.random.Generator) -> np.ndarray:
    """[TILE, TILE, 3] float32 in 0..1 (grey materials are neutral, tinted later)."""
    if m.source == "flat":
        # Barely visible, smooth blotches, as on a painted wall.
        noise = rng.standard_normal((TILE // 16, TILE // 16)).astype(np.float32)
        noise = cv2.resize(noise, (TILE, TILE), interpolation=cv2.INTER_CUBIC)
        grey = 0.8 + m.contrast * noise
        return np.repeat(grey[..., None], 3, -1).clip(0, 1).astype(np.float32)
    img = _load(m.source).astype(np.float32) / 255.0
    if m.metres_per_tile == 0.0:  # picture: keep colours, fill the tile
        return cv2.resize(img, (TILE, TILE), interpolation=cv2.INTER_AREA)
    grey = img.mean(-1)
    if m.stretch != 1.0:
        # Wood grain: blades of grass stretched along u read as fibres.
        h = grey.shape[0]
        grey = cv2.resize(grey[: int(h / m.stretch) + 1], (grey.shape[1], h),
                          interpolation=cv2.INTER_LINEAR)
    grey = cv2.resize(grey, (TILE, TILE), interpolation=cv2.INTER_AREA)
    grey = _seamless(grey)
    grey = (grey - grey.mean()) / (grey.std() + 1e-6)
    grey = 0.75 + 0.12 * m.contrast * grey
    if m.seams:
        period = TILE // int(m.seams)
        idx = np.arange(TILE)
        seam = (idx % period < 3).astype(np.float32)
        if m.stretch != 1.0:  # planks: seams between boards only (along u)
            grey = grey * (1.0 - 0.35 * seam[:, None])
        else:  # tiles: grout lines both ways
            grey = grey * (1.0 - 0.3 * np.maximum(seam[:, None], seam[None, :]))
    return np.repeat(grey[..., None], 3, -1).clip(0, 1).astype(np.float32)


@dataclass
class TextureBank:
    """All materials' mip pyramids, flattened for one-gather lookup.

    ``texels[offset[m, l] + (v >> l) * (TILE >> l) + (u >> l)]`` is the RGBA (little-endian
    uint32) colour of material ``m`` at level ``l`` and level-0 texel (u, v).
    """

    texels: np.ndarray  # [sum of level sizes] uint32 RGBA
    offset: np.ndarray  # [M, LEVELS] int64 start of each level in ``texels``
    mean_rgb: np.ndarray  # [M, 3] float32 0..1 mean colour (for the coloured mesh)
    texels_per_metre: np.ndarray  # [M] float32; 0 for pictures (stretched over their face)

    @property
    def n_materials(self) -> int:
        return len(self.offset)

    def material_image(self, material: int | str, level: int = 0) -> np.ndarray:
        """[S, S, 3] uint8 image of one material's mip level (for plots and tests)."""
        m = MATERIAL_ID[material] if isinstance(material, str) else int(material)
        s = TILE >> level
        flat = self.texels[self.offset[m, level]: self.offset[m, level] + s * s]
        return flat.view(np.uint8).reshape(s, s, 4)[..., :3].copy()


@lru_cache(maxsize=4)
def build_texture_bank(seed: int = 0) -> TextureBank:
    """Load and prepare every material (about 0.3 s; cached per seed)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
    chunks: list[np.ndarray] = []
    offset = np.zeros((len(MATERIALS), LEVELS), np.int64)
    mean_rgb = np.zeros((len(MATERIALS), 3), np.float32)
    tpm = np.zeros(len(MATERIALS), np.float32)
    pos = 0
    for mi, m in enumerate(MATERIALS):
        img = _material_image(m, rng)
        mean_rgb[mi] = img.reshape(-1, 3).mean(0)
        tpm[mi] = TILE / m.metres_per_tile if m.metres_per_tile > 0 else 0.0
        level = img
        for lv in range(LEVELS):
            if lv:
                level = cv2.resize(level, (TILE >> lv, TILE >> lv), interpolation=cv2.INTER_AREA)
            rgba = np.empty(level.shape[:2] + (4,), np.uint8)
            rgba[..., :3] = np.clip(level * 255.0 + 0.5, 0, 255).astype(np.uint8)
            rgba[..., 3] = 255
            offset[mi, lv] = pos
            flat = rgba.reshape(-1, 4).view(np.uint32).reshape(-1)
            chunks.append(flat)
            pos += len(flat)
    return TextureBank(np.concatenate(chunks), offset, mean_rgb, tpm)
