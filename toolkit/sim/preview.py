"""Pictures of a simulated sequence: an image/depth strip and a top-down map.

Both read the written sequence folder (not the simulator's memory), so they show what
downstream stages will get.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from toolkit.errors import InputError, WriteError
from toolkit.geometry import transform_points
from toolkit.io.atomic import atomic_path
from toolkit.io.sequence import read_sequence


def _depth_colour(depth: np.ndarray, max_m: float = 8.0) -> np.ndarray:
    """[H, W, 3] RGB uint8 of a depth map: turbo from blue (0 m) to red (``max_m``), as
    every depth figure of the toolkit; black where invalid."""
    d = np.clip(np.nan_to_num(depth) / max_m, 0, 1)
    col = cv2.applyColorMap((255 * d).astype(np.uint8), cv2.COLORMAP_TURBO)
    col = cv2.cvtColor(col, cv2.COLOR_BGR2RGB)
    col[~(depth > 0)] = 0
    return col


def preview_strip(root: Path | str, out_png: Path | str, n: int = 4, width: int = 320) -> Path:
    """PNG with ``n`` evenly spaced frames: RGB on top, depth below, moving people outlined."""
    seq = read_sequence(root)
    gt = seq.groundtruth
    if not seq.frames:
        raise InputError(f"{root}: no camera frames to preview")
    idx = np.linspace(0, len(seq.frames) - 1, n).round().astype(int)
    cols = []
    for i in idx:
        rgb = seq.frames[i].image.copy()
        h = int(round(rgb.shape[0] * width / rgb.shape[1]))
        if gt is not None and gt.mask_paths:
            m = gt.mask(i).astype(np.uint8)
            contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            cv2.drawContours(rgb, contours, -1, (255, 0, 255), 2)
        rgb = cv2.resize(rgb, (width, h), interpolation=cv2.INTER_AREA)
        if gt is not None and gt.depth_paths:
            dep = _depth_colour(cv2.resize(gt.depth(i), (width, h),
                                           interpolation=cv2.INTER_NEAREST))
        else:
            dep = np.zeros_like(rgb)
        cv2.putText(rgb, f"#{i} t={seq.frames[i].stamp - seq.frames[0].stamp:.1f}s", (5, 15),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        cols.append(np.vstack([rgb, dep]))
    strip = np.hstack([np.pad(c, ((0, 0), (0, 4), (0, 0)), constant_values=255) for c in cols])
    out_png = Path(out_png)
    with atomic_path(out_png) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(strip, cv2.COLOR_RGB2BGR)):
            raise WriteError(f"{out_png}: could not write preview")
    return out_png


def plot_topdown(root: Path | str, out_png: Path | str, n_scans: int = 10) -> Path:
    """Top-down PNG: walls, furniture (by height vs the lidar plane), ground-truth path,
    odometry, people tracks and a few lidar scans in the world frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    root = Path(root)
    seq = read_sequence(root)
    house = json.loads((root / "groundtruth" / "house.json").read_text())
    gt = seq.groundtruth
    lidar_z = float(seq.rig.T_base_laser[2, 3])
    fig, ax = plt.subplots(figsize=(9, 9 * 0.75))
    for w in house["walls"]:
        w = np.asarray(w)
        ax.plot(w[:, 0], w[:, 1], "-", color="0.15", lw=3, solid_capstyle="butt")
    labels_done: set[str] = set()
    for it in house["furniture"]:
        fp = np.asarray(it["footprint"])
        z0, z1 = it["z_range"]
        if z1 < lidar_z:
            c, lab = "tab:green", "furniture below lidar plane"
        elif z0 > lidar_z:
            c, lab = "tab:orange", "above lidar plane"
        else:
            c, lab = "tab:brown", "crosses lidar plane"
        ax.fill(fp[:, 0], fp[:, 1], color=c, alpha=0.35, lw=0,
                label=None if lab in labels_done else lab)
        labels_done.add(lab)
    for r in house["rooms"]:
        x0, y0, x1, y1 = r["rect"]
        ax.text((x0 + x1) / 2, (y0 + y1) / 2, r["kind"], ha="center", va="center", fontsize=8,
                color="0.4")
    if gt is not None and gt.poses_base is not None:
        p = gt.poses_base.positions
        ax.plot(p[:, 0], p[:, 1], "-", color="tab:blue", lw=1.5, label="ground-truth path")
        ax.plot(p[0, 0], p[0, 1], "o", color="tab:blue", ms=6)
        if seq.odometry is not None:
            # Odometry starts at the origin; draw it from the true start pose.
            T0 = gt.poses_base.poses[0]
            q = transform_points(T0, seq.odometry.positions)
            ax.plot(q[:, 0], q[:, 1], "--", color="tab:gray", lw=1, label="wheel odometry")
        if seq.scans:
            sel = np.linspace(0, len(seq.scans) - 1, n_scans).round().astype(int)
            dyn = gt.scan_dynamic
            T_wb = gt.poses_base.interpolate(seq.scan_stamps[sel]).poses
            for j, k in enumerate(sel):
                scan = seq.scans[k]
                valid = scan.valid_mask()
                pts = transform_points(T_wb[j] @ seq.rig.T_base_laser, scan.points_3d())
                ax.scatter(pts[:, 0], pts[:, 1], s=1.5, color="tab:red", alpha=0.6,
                           label="lidar scans" if j == 0 else None)
                if dyn is not None:
                    d = dyn[k][valid]
                    ax.scatter(pts[d, 0], pts[d, 1], s=6, color="magenta",
                               label="beams on people" if j == 0 else None)
    for k, tr in enumerate(house.get("people_tracks", [])):
        tr = np.asarray(tr)
        if len(tr):
            ax.plot(tr[:, 1], tr[:, 2], ":", color="purple", lw=1,
                    label="people" if k == 0 else None)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{seq.name}: house, path and lidar scans (world frame)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    out_png = Path(out_png)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return out_png
