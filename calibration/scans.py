"""Reading 2D scans for calibration and pairing them with images by timestamp.

Formats: ASCII or binary PCD (one scan per file, as ROS ``pcl`` tools write them), CSV
(``x,y[,z]`` or ``angle,range`` columns, one scan per file), npz (``points`` [N, 2|3], or
the sequence format's ``stamps``/``ranges`` arrays holding many scans), and the project's
sequence folder. A file's stamp comes from its name (``stamp_from_name``): an integer of
10, 13, 16 or 19 digits is a Unix time in seconds, milliseconds, microseconds or
nanoseconds (``1773380642785313094.pcd``), a decimal number is seconds (``12.5.csv``);
other integers name no unit, and ``stamp_unit`` must say it.
"""

from __future__ import annotations

import csv
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.errors import InputError, MissingInputError

SCAN_SUFFIXES = (".pcd", ".csv", ".npz")
# Beams that return exactly the sensor origin are "no return" in many drivers' PCD output.
_MIN_RANGE_M = 1e-3


class ScanFormatError(InputError):
    """A scan file is malformed; the message names the file and the field."""


class PairingError(InputError):
    """Images and scans cannot be matched in time; the message lists the offenders."""


@dataclass
class StampedScan:
    """One 2D scan's valid end points in the laser frame."""

    stamp: float  # seconds
    points: np.ndarray  # [N, 2] float64 metres, laser frame (x forward, y left)
    source: str  # file (and index) it came from, for messages


# ---------------------------------------------------------------------------- stamps


STAMP_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
# A Unix time between 2001-09 and 2286 has 10 digits in seconds, 13 in milliseconds, 16 in
# microseconds and 19 in nanoseconds; any other length is not a Unix time in any of them.
_EPOCH_DIGITS = {10: "s", 13: "ms", 16: "us", 19: "ns"}


def stamp_from_name(path: Path, unit: str = "auto") -> float:
    """Seconds from a file name such as ``1773380642785313094.pcd`` or ``12.25.png``.

    ``unit`` "auto" reads an integer by its digit count (10 s, 13 ms, 16 us, 19 ns: a Unix
    time in each), and up to 9 digits or a decimal number as seconds; "s", "ms", "us" or
    "ns" scale whatever number the name holds. A ``<sec>_<nsec>`` name (ROS's fields) is
    read as such with "auto" or "s" and refused with another unit.
    """
    if unit != "auto" and unit not in STAMP_UNITS:
        raise ValueError(f"stamp unit {unit!r}: use auto, {', '.join(STAMP_UNITS)}")
    stem = Path(path).stem
    # <seconds>_<nanoseconds> (ROS's sec and nsec fields, nanoseconds zero-padded to 9
    # digits): the first run of digits alone would drop the fraction.
    pair = re.search(r"(?<!\d)(\d{9,10})[_-](\d{9})(?!\d)", stem)
    if pair is not None and unit in ("auto", "s"):
        return int(pair.group(1)) + int(pair.group(2)) * 1e-9
    if pair is not None:
        # The digit run alone in the unit given read the seconds 1700000000 as
        # nanoseconds: 1.7 s.
        raise ScanFormatError(
            f"{path}: the name holds <seconds>_<nanoseconds> ({pair.group(0)}), whose unit is "
            f"its form, but the stamp unit given is {unit!r}, which would read "
            f"{pair.group(1)} alone as {unit}. Fix: drop --stamp-unit (auto) or pass "
            "--stamp-unit s")
    # A bare number, or a Unix time inside a name with its decimals (cam_1700000000.990:
    # the integer part alone paired it with a scan 0.9 s away, reported as 0 ms).
    m = re.fullmatch(r"\d+(\.\d*)?", stem) or re.search(r"(?<!\d)\d{10,}(\.\d+)?", stem)
    if m is None:
        raise ScanFormatError(
            f"{path}: cannot read a timestamp from the file name; name files by their stamp "
            "(<nanoseconds>.ext, <seconds>.ext, ...), or pass a sequence folder")
    text = m.group(0)
    if unit != "auto":
        return float(text) * STAMP_UNITS[unit]
    digits = len(text.split(".")[0].lstrip("0"))
    if "." in text or digits < 10:
        return float(text)
    found = _EPOCH_DIGITS.get(digits)
    if found is None:
        raise ScanFormatError(
            f"{path}: the stamp {text} in the file name has {digits} digits, which is not a "
            "Unix time in seconds (10), milliseconds (13), microseconds (16) or nanoseconds "
            "(19), so its unit is unknown. Pass --stamp-unit s|ms|us|ns.")
    return int(text) * STAMP_UNITS[found]


# ---------------------------------------------------------------------------- readers


def _planar(points: np.ndarray, source: str) -> np.ndarray:
    """[N, 2] valid points of [N, 2|3] input; a scan with height is not a 2D scan."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise ScanFormatError(f"{source}: points must be [N, 2] or [N, 3], got {pts.shape}")
    if pts.shape[1] == 3:
        z = pts[:, 2][np.isfinite(pts[:, 2])]
        if len(z) and np.abs(z).max() > 0.01:
            raise ScanFormatError(f"{source}: z reaches {np.abs(z).max():.3f} m; this tool "
                                  "calibrates planar (2D) scans given in the laser frame (z = 0)")
        pts = pts[:, :2]
    ok = np.all(np.isfinite(pts), axis=1) & (np.linalg.norm(pts, axis=1) > _MIN_RANGE_M)
    return pts[ok]


def read_pcd(path: Path) -> np.ndarray:
    """[N, 2] points of a PCD file (DATA ascii or binary; x and y fields)."""
    path = Path(path)
    raw = path.read_bytes()
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise ScanFormatError(f"{path}: PCD header has no DATA line")
        line = raw[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
    fields = header.get("FIELDS")
    if not fields or "x" not in fields or "y" not in fields:
        raise ScanFormatError(f"{path}: PCD field 'FIELDS' must name x and y, got {fields}")
    n = _pcd_int(header, "POINTS" if "POINTS" in header else "WIDTH", path)
    counts = _pcd_ints(header, "COUNT", len(fields), path, ["1"] * len(fields))
    kind = header["DATA"][0].lower() if header["DATA"] else ""
    ix, iy = fields.index("x"), fields.index("y")
    iz = fields.index("z") if "z" in fields else None
    if kind == "ascii":
        text = raw[pos:].decode("ascii", "replace")
        rows = [r.split() for r in text.splitlines() if r.strip()]
        if len(rows) != n:
            raise ScanFormatError(f"{path}: header field 'POINTS' says {n} but the file holds "
                                  f"{len(rows)} rows (truncated file?)")
        width = sum(counts)
        short = next((k for k, r in enumerate(rows) if len(r) < width), None)
        if short is not None:
            raise ScanFormatError(f"{path}: data row {short + 1} has {len(rows[short])} values "
                                  f"but header fields 'FIELDS'/'COUNT' make {width} per point")
        try:
            # [N, width] even for N = 0 (a scan with no returns is valid input)
            data = np.array([[float(v) for v in r[:width]] for r in rows],
                            dtype=np.float64).reshape(len(rows), width)
        except ValueError as e:
            raise ScanFormatError(f"{path}: non-numeric PCD data: {e}") from None
        offs = np.cumsum([0, *counts])
        cols = [offs[ix], offs[iy]] + ([offs[iz]] if iz is not None else [])
        return _planar(data[:, cols], str(path))
    if kind == "binary":
        sizes = _pcd_ints(header, "SIZE", len(fields), path)
        types = header.get("TYPE")
        if types is None or len(types) != len(fields):
            raise ScanFormatError(f"{path}: binary PCD header field 'TYPE' must give one of F, I "
                                  f"or U for each of the {len(fields)} FIELDS, got {types}")
        dt = np.dtype([(f"f{k}", _pcd_dtype(types[k], sizes[k], path), (counts[k],))
                       for k in range(len(fields))])
        if len(raw) - pos < n * dt.itemsize:
            raise ScanFormatError(
                f"{path}: header field 'POINTS' says {n} points of {dt.itemsize} bytes "
                f"(SIZE x COUNT) but the binary data holds {len(raw) - pos} bytes, "
                f"{(len(raw) - pos) // max(dt.itemsize, 1)} points (truncated file?)")
        rec = np.frombuffer(raw, dtype=dt, count=n, offset=pos)
        cols = [rec[f"f{ix}"][:, 0], rec[f"f{iy}"][:, 0]]
        if iz is not None:
            cols.append(rec[f"f{iz}"][:, 0])
        return _planar(np.stack(cols, -1), str(path))
    raise ScanFormatError(f"{path}: PCD 'DATA {kind}' is not supported; convert with "
                          "pcl_convert_pcd_ascii_binary <in> <out> 0 (ascii)")


def _pcd_int(header: dict[str, list[str]], key: str, path: Path) -> int:
    vals = header.get(key)
    try:
        n = int(vals[0]) if vals else -1
    except ValueError:
        n = -1
    if n < 0:
        raise ScanFormatError(f"{path}: PCD header field '{key}' must be a count of points, "
                              f"got {vals}")
    return n


def _pcd_ints(header: dict[str, list[str]], key: str, n_fields: int, path: Path,
              default: list[str] | None = None) -> list[int]:
    """One positive integer per field from header line ``key`` (SIZE, COUNT)."""
    vals = header.get(key, default)
    try:
        out = [int(v) for v in vals] if vals is not None else []
    except ValueError:
        out = []
    if len(out) != n_fields or min(out, default=0) < 1:
        raise ScanFormatError(f"{path}: PCD header field '{key}' must give a positive integer "
                              f"for each of the {n_fields} FIELDS, got {vals}")
    return out


def _pcd_dtype(t: str, size: int, path: Path) -> str:
    kinds = {"F": "f", "I": "i", "U": "u"}
    if t.upper() not in kinds:
        raise ScanFormatError(f"{path}: PCD field 'TYPE' {t!r} unknown (F, I or U)")
    valid = (4, 8) if t.upper() == "F" else (1, 2, 4, 8)
    if size not in valid:
        raise ScanFormatError(f"{path}: PCD field 'SIZE' {size} does not fit TYPE {t} "
                              f"(sizes {', '.join(map(str, valid))})")
    return f"<{kinds[t.upper()]}{size}"


def read_csv_scan(path: Path) -> np.ndarray:
    """[N, 2] points of a CSV with a header naming ``x,y[,z]`` or ``angle,range`` (radians)."""
    path = Path(path)
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise ScanFormatError(f"{path}: empty CSV")
    head = [h.strip().lower() for h in rows[0]]
    body = [r for r in rows[1:] if r and any(c.strip() for c in r)]
    if not body:
        raise ScanFormatError(f"{path}: no data rows below the header {head}")
    ragged = [n for n, r in enumerate(body, start=2) if len(r) != len(head)]
    if ragged:
        raise ScanFormatError(f"{path}: row {ragged[0]} has {len(body[ragged[0] - 2])} "
                              f"values for the {len(head)} columns of the header {head}")
    try:
        data = np.array([[float(c) for c in r] for r in body], dtype=np.float64)
    except ValueError as e:
        raise ScanFormatError(f"{path}: non-numeric value below the header: {e}") from None
    data = data.reshape(len(body), -1)
    if {"x", "y"} <= set(head):
        cols = [head.index("x"), head.index("y")] + ([head.index("z")] if "z" in head else [])
        return _planar(data[:, cols], str(path))
    if {"angle", "range"} <= set(head):
        a, r = data[:, head.index("angle")], data[:, head.index("range")]
        if np.nanmax(np.abs(a), initial=0.0) > 2 * np.pi + 1e-6:
            raise ScanFormatError(
                f"{path}: column 'angle' reaches {np.nanmax(np.abs(a)):.1f}, more than 2 pi: "
                "the angles look like degrees; this reader takes radians (convert the "
                "column, or write x,y columns)")
        return _planar(np.stack([r * np.cos(a), r * np.sin(a)], -1), str(path))
    raise ScanFormatError(f"{path}: CSV header {head} must name columns x,y[,z] or "
                          "angle,range (radians)")


def _npz_arrays(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an npz file, or an error naming it: a truncated file, a lone .npy
    array or pickled objects stopped extrinsic and check with numpy's traceback."""
    try:
        with np.load(path) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, EOFError, TypeError, zipfile.BadZipFile) as e:
        # TypeError: np.load returned one array (a .npy file), not an archive to open.
        raise ScanFormatError(f"{path}: not a readable npz scan file ({e}); write it with "
                              "numpy.savez(points=[N, 2] x y in metres)") from None


def read_scan_file(path: Path, stamp_unit: str = "auto") -> list[StampedScan]:
    """Scans of one file: one for PCD/CSV/npz-with-points, many for a sequence-style npz."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        return [StampedScan(stamp_from_name(path, stamp_unit), read_pcd(path), str(path))]
    if suffix == ".csv":
        return [StampedScan(stamp_from_name(path, stamp_unit), read_csv_scan(path), str(path))]
    if suffix == ".npz":
        arrays = _npz_arrays(path)
        if "points" in arrays:
            stamp = (float(arrays["stamp"]) if "stamp" in arrays
                     else stamp_from_name(path, stamp_unit))
            return [StampedScan(stamp, _planar(arrays["points"], str(path)), str(path))]
        if "ranges" in arrays:
            from toolkit.io.sequence import scans_from_arrays

            scans = scans_from_arrays(arrays, str(path))
            return [StampedScan(s.stamp, s.points(), f"{path}[{i}]") for i, s in enumerate(scans)]
        raise ScanFormatError(f"{path}: npz must hold 'points' [N, 2] (one scan) or the "
                              "sequence arrays 'stamps', 'ranges', 'angle_min', ...")
    raise ScanFormatError(f"{path}: unknown scan format {suffix!r}; use "
                          f"{', '.join(SCAN_SUFFIXES)} or a sequence folder")


def refuse_same_stamps(folder: Path, names: list[str], stamps: np.ndarray, what: str) -> None:
    """Refuse two files of one folder whose names give one stamp (``1.png`` and ``1.jpg``,
    ``12.5.csv`` and ``12.50.csv``): pairing took one and called the other unpaired, or
    dropped it without a word."""
    order = np.argsort(stamps, kind="stable")
    same = np.flatnonzero(np.diff(stamps[order]) == 0)
    if len(same):
        a, b = names[order[same[0]]], names[order[same[0] + 1]]
        raise PairingError(
            f"{folder}: {a} and {b} have the same stamp ({stamps[order[same[0]]]:.9f} s)"
            f"{f' and {len(same) - 1} more pairs of {what} do' if len(same) > 1 else ''}: "
            f"one moment cannot have two {what}; remove the copy (or rename it by its own "
            "stamp)")


def read_scans(source: Path, stamp_unit: str = "auto") -> list[StampedScan]:
    """All scans of a folder of scan files, an npz of many scans, or a sequence folder."""
    source = Path(source)
    if not source.exists():
        raise MissingInputError(f"{source}: scan file or folder not found")
    if source.is_file():
        scans = read_scan_file(source, stamp_unit)
    elif (source / "scans.npz").exists() and (source / "rig.yaml").exists():
        from toolkit.io.sequence import read_scans as read_sequence_scans

        scans = [StampedScan(s.stamp, s.points(), f"{source / 'scans.npz'}[{i}]")
                 for i, s in enumerate(read_sequence_scans(source / "scans.npz"))]
    else:
        files = sorted(p for p in source.iterdir()
                       if p.suffix.lower() in SCAN_SUFFIXES and not p.name.startswith("."))
        if not files:
            raise MissingInputError(f"{source}: no scan files ({', '.join(SCAN_SUFFIXES)}) and "
                                    "not a sequence folder (rig.yaml + scans.npz)")
        scans = [s for p in files for s in read_scan_file(p, stamp_unit)]
        refuse_same_stamps(source, [Path(s.source).name for s in scans],
                           np.array([s.stamp for s in scans]), "scans")
    scans.sort(key=lambda s: s.stamp)
    return scans


# ---------------------------------------------------------------------------- pairing


@dataclass
class Pair:
    image_index: int
    scan_index: int
    dt: float  # scan stamp - image stamp, seconds


def pair_by_stamp(image_stamps: np.ndarray, scan_stamps: np.ndarray, max_dt: float) -> (
    tuple[list[Pair], list[int]]
):
    """Nearest scan for each image within ``max_dt`` seconds; and the images left unpaired.

    A scan is used at most once (the closest pairs first) so that two images taken while
    the board moved cannot share one scan; an image whose nearest scan went to another
    takes its next one within ``max_dt`` (it was left unpaired, "nearest scan 30 ms
    away" under a 100 ms limit).
    """
    image_stamps = np.asarray(image_stamps, dtype=np.float64)  # [I]
    scan_stamps = np.asarray(scan_stamps, dtype=np.float64)  # [S]
    if len(scan_stamps) == 0:
        return [], list(range(len(image_stamps)))
    order = np.argsort(scan_stamps)
    sorted_stamps = scan_stamps[order]
    cand: list[Pair] = []
    for i, t in enumerate(image_stamps):
        lo = int(np.searchsorted(sorted_stamps, t - max_dt, "left"))
        hi = int(np.searchsorted(sorted_stamps, t + max_dt, "right"))
        cand += [Pair(i, int(order[j]), float(sorted_stamps[j] - t)) for j in range(lo, hi)]
    taken: dict[int, Pair] = {}
    images_done: set[int] = set()
    for p in sorted(cand, key=lambda p: abs(p.dt)):
        if p.scan_index not in taken and p.image_index not in images_done:
            taken[p.scan_index] = p
            images_done.add(p.image_index)
    pairs = sorted(taken.values(), key=lambda p: p.image_index)
    paired = {p.image_index for p in pairs}
    return pairs, [i for i in range(len(image_stamps)) if i not in paired]


def describe_unpaired(unpaired: list[int], image_names: list[str], image_stamps: np.ndarray,
                      scan_stamps: np.ndarray, max_dt: float) -> str:
    """A message naming each unpaired image and its nearest scan."""
    lines = []
    for i in unpaired[:10]:
        if len(scan_stamps):
            dt = float(np.min(np.abs(np.asarray(scan_stamps) - image_stamps[i])))
            lines.append(f"  {image_names[i]}: nearest scan {dt * 1000:.1f} ms away")
        else:
            lines.append(f"  {image_names[i]}: no scans at all")
    more = f"\n  ... and {len(unpaired) - 10} more" if len(unpaired) > 10 else ""
    return (f"{len(unpaired)} image(s) have no scan within {max_dt * 1000:.0f} ms:\n"
            + "\n".join(lines) + more
            + "\nFix: raise --max-dt if the sensors are not synchronised that well, check that "
              "image and scan file names hold the same clock in the same unit (names of 10, "
              "13, 16 or 19 digits are read as Unix times in s, ms, us or ns; pass "
              "--stamp-unit otherwise), or pass --skip-unpaired to calibrate from the paired "
              "views only.")
