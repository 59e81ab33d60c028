"""How well ``dynamic_beams`` finds people in a simulated recording, against its truth.

    python -m toolkit.fusion.dynamic_check runs/paper_benchmark/simulate/sequence

Scores the beams flagged by the near partners alone (fuse version 12) and with the far
ones (the default) against ``groundtruth/scan_dynamic``, at ground-truth poses, and apart
for beams on a person who has not moved for 0.5 s (``house.json``'s people tracks, 2 Hz):
the ones the near partners miss when that person stood for longer than they span.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from toolkit.fusion.dynamic import dynamic_beams
from toolkit.fusion.pipeline import FusionConfig, pose_arrays
from toolkit.io.sequence import SequenceFormatError, read_sequence


def standing_beams(root: Path, hits_xy: list[np.ndarray], beams: list[np.ndarray],
                   stamps: np.ndarray, shape: tuple[int, int], radius: float = 0.4,
                   still_s: float = 0.5) -> np.ndarray:
    """[S, B] bool: beams whose end point (``hits_xy`` [P_k, 2] world of ``beams`` [P_k]
    per scan) lies within ``radius`` of a person who has not moved for ``still_s``."""
    tracks = [np.asarray(t, np.float64) for t in
              json.loads((root / "groundtruth" / "house.json").read_text())["people_tracks"]]
    out = np.zeros(shape, bool)
    for k, (xy, b) in enumerate(zip(hits_xy, beams, strict=True)):
        if not len(b):
            continue
        for tr in tracks:  # [M, 3] t x y
            now = np.array([np.interp(stamps[k], tr[:, 0], tr[:, i]) for i in (1, 2)])
            then = np.array([np.interp(stamps[k] - still_s, tr[:, 0], tr[:, i]) for i in (1, 2)])
            if np.linalg.norm(now - then) > 1e-6:
                continue
            out[k, b[np.linalg.norm(xy - now, axis=1) < radius]] = True
    return out


def check(root: Path) -> dict[str, dict[str, float]]:
    """Precision and recall of the flags, all people and standing ones apart."""
    seq = read_sequence(root)
    gt = seq.groundtruth
    if gt is None or gt.scan_dynamic is None or gt.poses_base is None:
        raise SystemExit(f"{root}: no groundtruth/scan_dynamic.npz or poses: not a simulated "
                         "recording")
    _, scan_poses, _ = pose_arrays(seq, gt.poses_base)
    T_wl = scan_poses @ seq.rig.T_base_laser  # [S, 4, 4]
    truth = gt.scan_dynamic  # [S, B]
    hits_xy, beams = [], []
    for k, s in enumerate(seq.scans):
        b = np.flatnonzero(truth[k])
        r = s.ranges[b].astype(np.float64)
        a = s.angles()[b]
        p = np.stack([r * np.cos(a), r * np.sin(a)], 1) @ T_wl[k][:2, :2].T + T_wl[k][:2, 3]
        hits_xy.append(p)
        beams.append(b)
    # A recording without people tracks (the synthetic box room) is scored as a whole.
    standing = (standing_beams(root, hits_xy, beams, np.asarray(seq.scan_stamps), truth.shape)
                if (root / "groundtruth" / "house.json").is_file() else None)
    cfg = FusionConfig()
    out: dict[str, dict[str, float]] = {}
    for name, far in (("near", ()), ("near+far", cfg.dynamic_far_offsets_s)):
        t = time.perf_counter()
        flags = np.array(dynamic_beams(list(seq.scans), T_wl, cfg.dynamic_offsets_s,
                                       far_offsets_s=far,
                                       far_min_width_m=cfg.dynamic_far_min_width_m))  # [S, B]
        seconds = time.perf_counter() - t
        tp = int((flags & truth).sum())
        out[name] = {
            "seconds": round(seconds, 3),
            "flagged": int(flags.sum()),
            "false": int((flags & ~truth).sum()),
            "precision": round(tp / max(int(flags.sum()), 1), 4),
            "recall": round(tp / max(int(truth.sum()), 1), 4),
        }
        if standing is not None:
            out[name]["recall_standing"] = round(
                int((flags & standing).sum()) / max(int(standing.sum()), 1), 4)
            out[name]["recall_moving"] = round(int((flags & truth & ~standing).sum())
                                               / max(int((truth & ~standing).sum()), 1), 4)
    out["truth"] = {"beams": int(truth.sum())}
    if standing is not None:
        out["truth"]["standing"] = int(standing.sum())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m toolkit.fusion.dynamic_check",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path, help="a simulated sequence folder")
    args = ap.parse_args(argv)
    try:
        rows = check(args.sequence)
    except SequenceFormatError as exc:  # a wrong folder: its message, not a traceback
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for name, row in rows.items():
        print(name, row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
