"""Report figures of the fusion: lidar overlay, scaled vs unscaled depth, map views, scales.

Open3D's offscreen renderer needs EGL/OSMesa, which headless CPU machines often lack, so
the map is drawn by projecting its points into a virtual camera with a z-buffer here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from toolkit.camera import PinholeCamera, pixel_index
from toolkit.geometry import inv_se3, se3, transform_points
from toolkit.io.atomic import atomic_path


def _plt():  # noqa: ANN202 - matplotlib's pyplot module
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: object, path: Path) -> None:
    plt = _plt()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")  # type: ignore[attr-defined]
    plt.close(fig)


def lidar_overlay(path: Path, rgb: np.ndarray, uv: np.ndarray, z: np.ndarray,
                  title: str = "") -> None:
    """The image with the projected lidar points coloured by depth."""
    plt = _plt()
    h, w = rgb.shape[:2]
    fig, ax = plt.subplots(figsize=(7, 7 * h / w + 0.5))
    ax.imshow(rgb)
    sc = ax.scatter(uv[:, 0], uv[:, 1], c=z, s=6, cmap="turbo")
    fig.colorbar(sc, ax=ax, fraction=0.035, label="lidar z-depth (m)")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_title(title or "lidar projected into the image")
    ax.axis("off")
    fig.tight_layout()
    _save(fig, path)


def depth_panel_images(unscaled: np.ndarray, scaled: np.ndarray, gt: np.ndarray | None,
                       refined: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The depth and error panels [H, W] of ``depth_panels`` by title, in drawing order.

    ``scaled`` is the per-frame lidar scale alone, what "scaled" means in every table;
    ``refined`` (None: no shape correction, or it changed nothing) gets a panel and an error
    map of its own: drawn as "scaled" it showed about half the error of the paper's method.
    """
    panels = {"unscaled": unscaled, "scaled": scaled}
    if refined is not None:
        panels["after shape correction"] = refined
    if gt is not None:
        panels["ground truth"] = np.where(gt > 0, gt, np.nan)
        for name, d in (("scaled", scaled), ("corrected", refined)):
            if d is not None:
                panels[f"|{name} - truth|"] = np.where((gt > 0) & np.isfinite(d),
                                                       np.abs(d - gt), np.nan)
    return panels


def depth_panels(path: Path, rgb: np.ndarray, unscaled: np.ndarray, scaled: np.ndarray,
                 gt: np.ndarray | None, title: str = "",
                 refined: np.ndarray | None = None) -> None:
    """Image, unscaled and scaled depth on one colour scale (and the depth after the shape
    correction when ``refined`` is given), and the ground truth with each one's error when
    there is one (``depth_panel_images``)."""
    plt = _plt()
    panels = depth_panel_images(unscaled, scaled, gt, refined)
    ref = gt if gt is not None else scaled
    finite = ref[np.isfinite(ref) & (ref > 0)]
    vmax = float(np.percentile(finite, 98)) if len(finite) else 5.0
    n = 1 + len(panels)
    # Seven panels in one row were too small to read: two rows of four then.
    cols = n if n <= 5 else 4
    rows = -(-n // cols)
    fig, ax = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.0 * rows), squeeze=False)
    ax = ax.reshape(-1)
    ax[0].imshow(rgb)
    ax[0].set_title("image")
    depth_im = err_im = None
    depth_ax = err_ax = ax[0]
    for a, (name, img) in zip(ax[1:], panels.items(), strict=False):
        if name.startswith("|"):
            err_im, err_ax = a.imshow(img, cmap="magma", vmin=0, vmax=max(0.05, 0.1 * vmax)), a
        else:
            depth_im, depth_ax = a.imshow(img, cmap="turbo", vmin=0, vmax=vmax), a
        a.set_title(name)
    if depth_im is not None:
        fig.colorbar(depth_im, ax=depth_ax, fraction=0.046, label="m")
    if err_im is not None:
        fig.colorbar(err_im, ax=err_ax, fraction=0.046, label="m")
    for a in ax:
        a.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    _save(fig, path)


def render_points(points: np.ndarray, colors: np.ndarray, camera: PinholeCamera,
                  T_camera_world: np.ndarray, splat: int = 2,
                  background: int = 255) -> np.ndarray:
    """[H, W, 3] uint8 z-buffered rendering of coloured points [N, 3] from a pinhole view."""
    pc = transform_points(T_camera_world, points)
    front = pc[:, 2] > 0.05
    uv, z = camera.project(pc[front])
    col = colors[front]
    img = np.full((camera.height, camera.width, 3), background, np.uint8)
    zbuf = np.full((camera.height, camera.width), np.inf)
    px = pixel_index(uv)  # [M, 2]
    for dy in range(splat):
        for dx in range(splat):
            u, v = px[:, 0] + dx, px[:, 1] + dy
            ok = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
            lin = v[ok] * camera.width + u[ok]
            zz, cc = z[ok], col[ok]
            order = np.lexsort((zz, lin))
            first = np.r_[True, lin[order][1:] != lin[order][:-1]]
            sel = order[first]
            flat_z = zbuf.reshape(-1)
            closer = zz[sel] < flat_z[lin[sel]]
            tgt = lin[sel][closer]
            flat_z[tgt] = zz[sel][closer]
            img.reshape(-1, 3)[tgt] = cc[sel][closer]
    return img


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> (
    np.ndarray
):
    """``T_camera_world`` of an optical camera at ``eye`` looking at ``target``."""
    f = np.asarray(target, float) - np.asarray(eye, float)
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-6:
        r = np.cross(f, [0.0, 1.0, 0.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)  # optical y points down
    R_wc = np.stack([r, d, f], 1)
    return inv_se3(se3(R_wc, eye))


def map_views(path: Path, points: np.ndarray, colors: np.ndarray,
              trajectory_xy: np.ndarray | None = None, title: str = "",
              removed: np.ndarray | None = None) -> None:
    """Two renderings of the coloured map: a perspective view from above and behind, and a
    top-down view (ceiling points cut away) with the camera path."""
    plt = _plt()
    if len(points) == 0:
        fig, ax = plt.subplots()
        ax.text(0.5, 0.5, "empty map", ha="center")
        _save(fig, path)
        return
    lo, hi = np.percentile(points, 1, axis=0), np.percentile(points, 99, axis=0)
    centre = (lo + hi) / 2
    extent = float(np.max(hi[:2] - lo[:2]))
    cam = PinholeCamera.from_fov(800, 600, 60)
    eye = centre + np.array([-0.55 * extent, -0.75 * extent, 0.9 * extent])
    persp = render_points(points, colors, cam, look_at(eye, centre))
    fig, ax = plt.subplots(1, 2, figsize=(13, 5.2))
    ax[0].imshow(persp)
    ax[0].set_title("coloured map (z-buffered point render)")
    ax[0].axis("off")
    # Top-down: drop points near the ceiling so rooms are visible.
    zcut = lo[2] + 0.8 * (hi[2] - lo[2])
    sel = points[:, 2] < zcut
    order = np.argsort(points[sel, 2])  # higher points drawn last
    p, c = points[sel][order], colors[sel][order]
    step = max(1, len(p) // 300_000)
    ax[1].scatter(p[::step, 0], p[::step, 1], c=c[::step] / 255.0, s=0.3, linewidths=0)
    if removed is not None and len(removed):
        ax[1].scatter(removed[:, 0], removed[:, 1], c="red", s=0.1, linewidths=0,
                      label="removed (seen through by later views)")
        ax[1].legend(loc="upper right", markerscale=10)
    if trajectory_xy is not None and len(trajectory_xy):
        ax[1].plot(trajectory_xy[:, 0], trajectory_xy[:, 1], "k-", lw=0.8)
    ax[1].set_aspect("equal")
    ax[1].set_title("top view (ceiling cut)")
    ax[1].set_xlabel("x (m)")
    ax[1].set_ylabel("y (m)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    _save(fig, path)


def scale_plot(path: Path, frames: np.ndarray, raw: np.ndarray, final: np.ndarray,
               oracle: np.ndarray | None, flags: list[str], kind: str,
               used_label: str = "used (smoothed)") -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10.5, 3.2))
    ax.plot(frames, raw, ".", ms=3, color="0.6", label="per-frame estimate")
    bad = np.array([f != "ok" for f in flags])
    if bad.any():
        ax.plot(frames[bad], raw[bad], "x", ms=4, color="tab:red", label="flagged frame")
    ax.plot(frames, final, "-", color="tab:blue", lw=1.2, label=used_label)
    if oracle is not None and np.isfinite(oracle).any():
        ax.plot(frames, oracle, "-", color="tab:green", lw=0.8, label="oracle (from truth)")
    ax.set_xlabel("frame")
    ax.set_ylabel("scale")
    ax.set_title(f"per-frame scale ({kind.replace('_', ' ')})")
    # Outside the axes: inside, it hid flagged frames.
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    fig.tight_layout()
    _save(fig, path)


def exposure_plot(path: Path, frames: np.ndarray, gains: np.ndarray,
                  truth: np.ndarray | None = None) -> None:
    """Solved exposure gains [U, 3] per frame, with the true gain [U] when known (scaled
    to the same geometric mean: the common factor is not observable)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10.5, 3.2))
    for ch, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax.plot(frames, gains[:, ch], "-", color=colour, lw=1.0, label=f"solved, {'rgb'[ch]}")
    if truth is not None:
        t = truth * np.exp(np.mean(np.log(gains)) - np.mean(np.log(truth)))
        ax.plot(frames, t, "--", color="k", lw=1.0, label="true (simulator)")
    ax.set_xlabel("frame")
    ax.set_ylabel("gain")
    ax.set_title("exposure gain per frame (divided out of the map's colours)")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    fig.tight_layout()
    _save(fig, path)
