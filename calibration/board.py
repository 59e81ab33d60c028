"""Checkerboard targets: the board's geometry and its detection in images.

A board is named by its *inner* corner grid, as OpenCV counts it: ``11x8`` is a board of
12 x 9 squares. Object points lie in the board frame (x along the first count, y along the
second, z = 0 on the surface), in the row-major order ``cv2.findChessboardCorners`` returns.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from toolkit.errors import InputError, MissingInputError

# Corner refinement stops when a corner moves less than 1e-3 px or after 50 iterations:
# the refined corners then sit well below the 0.1 px level that matters for PnP.
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-3)


class BoardError(InputError):
    """A board specification or a detection problem; the message says what to change."""


def found_in(found: int, total: int) -> str:
    """Which of ``total`` images the board was found in, for a message: "in only 2 of the 5
    images", "in all 3 images", "in the only image" (it said "in only 1 of the 1 images"
    and "only 3 of the 3"). With ``found`` 0, for "no board found ...": "in any of the 5
    images", "in the only image"."""
    if total == 1:
        return "in the only image"
    if found == 0:
        return f"in any of the {total} images"
    if found == total:
        return "in both images" if total == 2 else f"in all {total} images"
    return f"in only {found} of the {total} images"


@dataclass(frozen=True)
class BoardSpec:
    """A planar checkerboard: inner corners ``cols`` x ``rows``, square side in metres."""

    cols: int
    rows: int
    square: float
    # Physical board (width along the first count, height), metres, with the pattern
    # printed in its middle; None when unknown. Lets the scan's end points on the board
    # constrain the extrinsic too.
    size: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2:
            raise BoardError(f"board {self.cols}x{self.rows}: a checkerboard needs at least "
                             "2x2 inner corners (--board counts inner corners, e.g. 11x8)")
        if not 0 < self.square < np.inf:
            raise BoardError(f"board square size must be positive metres, got {self.square} "
                             "(--square, the calibrate stage's square_m)")
        if self.size is not None:
            # NaN passed the "smaller than the pattern" test below (every comparison with it
            # is False): the scan's segments were then all "wrong length", and an infinite
            # side made the joint refinement's outline residuals NaN.
            if not all(0 < v < np.inf for v in self.size):
                raise BoardError(f"board size {self.size[0]:g} x {self.size[1]:g} m: both sides "
                                 "must be finite positive metres (--board-size W H, the "
                                 "calibrate stage's board_size_m)")
            w, h = self.pattern_extent
            if self.size[0] < w - 1e-9 or self.size[1] < h - 1e-9:
                raise BoardError(f"board size {self.size[0]:g} x {self.size[1]:g} m is smaller "
                                 f"than its printed pattern ({w:g} x {h:g} m); --board-size is "
                                 "the whole board, width along the first corner count")
            if self.cols == self.rows and abs(self.size[0] - self.size[1]) > 1e-9:
                # A square corner grid is the same turned 90 degrees, and OpenCV returns it
                # either way round (in 4-7 of 10 views): the outline was then checked with
                # width and height swapped, and --board-size 0.5 0.8 on a 7x7 grid made the
                # result worse (0.30-0.62 deg / 4.9-7.9 mm off against 0.05-0.32 deg /
                # 0.9-4.0 mm without it), marked reliable.
                raise BoardError(
                    f"board {self.cols}x{self.rows} with board size {self.size[0]:g} x "
                    f"{self.size[1]:g} m (--board-size, the calibrate stage's board_size_m): "
                    "a square corner grid looks the same turned 90 degrees, so which board "
                    "side runs along its first corner count is not known from an image, and "
                    "the scan's ends would be checked against the board turned in about half "
                    "the views. Leave --board-size out, or print a board whose inner corner "
                    f"counts differ (e.g. {self.cols + 1}x{self.rows}); a square board "
                    "(equal sides) may keep its --board-size")

    @classmethod
    def parse(cls, text: str, square: float, size: tuple[float, float] | None = None) -> (
        BoardSpec
    ):
        """From ``"11x8"`` (inner corners), the square side and the board size in metres."""
        m = re.fullmatch(r"\s*(\d+)\s*[xX*,]\s*(\d+)\s*", str(text))
        if m is None:
            raise BoardError(f"board {text!r}: expected inner corners as COLSxROWS, e.g. 11x8")
        return cls(int(m.group(1)), int(m.group(2)), float(square),
                   None if size is None else (float(size[0]), float(size[1])))

    def outline(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Board-frame corners [2] (lower) and [2] (upper) of the physical board, if known."""
        if self.size is None:
            return None
        c = self.center[:2]
        half = np.array(self.size) / 2
        return c - half, c + half

    @property
    def pattern_size(self) -> tuple[int, int]:
        """(cols, rows) as OpenCV's ``patternSize``."""
        return self.cols, self.rows

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows

    @property
    def pattern_extent(self) -> tuple[float, float]:
        """Width and height in metres of the printed squares (one square past each corner)."""
        return (self.cols + 1) * self.square, (self.rows + 1) * self.square

    @property
    def center(self) -> np.ndarray:
        """[3] the middle of the corner grid in the board frame."""
        return np.array([(self.cols - 1) * self.square / 2, (self.rows - 1) * self.square / 2,
                         0.0])

    def object_points(self) -> np.ndarray:
        """[N, 3] float64 corners in the board frame, OpenCV's row-major order."""
        i, j = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        pts = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], -1).astype(np.float64)
        return pts * self.square

    def __str__(self) -> str:
        return (f"{self.cols}x{self.rows} checkerboard (inner corners, "
                f"{self.square * 1000:g} mm squares)")


@dataclass
class Detection:
    """The board's corners found in one image."""

    name: str
    corners: np.ndarray  # [N, 2] float64 pixels, distorted (as seen in the raw image)
    image_size: tuple[int, int]  # (width, height)


def _gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image if image.dtype == np.uint8 else cv2.normalize(
            image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    # Channel order does not matter for a grey conversion of a black and white target.
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def detect_corners(image: np.ndarray, board: BoardSpec, name: str = "image") -> (
    Detection | None
):
    """Find the board's inner corners with sub-pixel refinement, or None.

    ``image`` is [H, W] grey or [H, W, 3] RGB/BGR uint8. The classic detector is tried
    first and its corners refined with ``cv2.cornerSubPix`` in a window sized to the
    squares as they appear (a fixed 11 px window would straddle two corners on a distant
    board); the sector-based detector is the fallback for blurred or low-contrast views.
    """
    gray = _gray(np.asarray(image))
    h, w = gray.shape
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(gray, board.pattern_size, flags=flags)
    if ok:
        c = corners.reshape(-1, 2)
        half = _subpix_half_window(c, board)
        corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (half, half), (-1, -1),
                                   _SUBPIX_CRITERIA)
    else:
        ok, corners = cv2.findChessboardCornersSB(
            gray, board.pattern_size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY)
        if not ok:
            return None
    c = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    if len(c) != board.n_corners:
        return None
    return Detection(name=name, corners=c, image_size=(w, h))


def _subpix_half_window(corners: np.ndarray, board: BoardSpec) -> int:
    # Smallest spacing between neighbouring corners in pixels; the window must stay inside
    # one square or the refinement snaps to the wrong corner.
    grid = corners.reshape(board.rows, board.cols, 2)
    dx = np.linalg.norm(np.diff(grid, axis=1), axis=-1).min()
    dy = np.linalg.norm(np.diff(grid, axis=0), axis=-1).min()
    return int(np.clip(0.4 * min(dx, dy), 2, 11))


def board_hint(image: np.ndarray, board: BoardSpec, where: str = "the first image") -> str:
    """A hint for when the board is not found: does a neighbouring grid size match in
    ``image`` (named ``where``)?"""
    gray = _gray(np.asarray(image))
    for c, r in ((board.cols - 1, board.rows - 1), (board.cols + 1, board.rows + 1),
                 (board.rows, board.cols)):
        if c < 2 or r < 2:
            continue
        ok, _ = cv2.findChessboardCorners(gray, (c, r), flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                          | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if ok:
            return (f" A {c}x{r} inner-corner grid was found in {where}; "
                    f"pass --board {c}x{r} (the board counts inner corners, not squares).")
    return (" Check --board (inner corners: a board of 12x9 squares is 11x8), that the whole "
            "board is visible with a white margin, and that the images are in focus.")


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


def list_images(folder: Path) -> list[Path]:
    """Image files of a folder, sorted by name (stamps in names sort in time order)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MissingInputError(f"{folder}: image folder not found")
    paths = sorted(p for p in folder.iterdir()
                   if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if not paths:
        raise MissingInputError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    return paths


def read_image(path: Path) -> np.ndarray:
    """[H, W, 3] uint8 (BGR order: only used for detection and drawing) with a clear error.
    The stored pixels, EXIF orientation not applied, as ``toolkit.sensors.load_rgb`` reads
    the frames these intrinsics are then used on."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise MissingInputError(f"{path}: missing or not a readable image")
    return img
