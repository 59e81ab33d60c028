"""Command line: ``python -m calibration intrinsics|extrinsic|check|time-offset ...``.

Errors a user can fix (a board that is not found, images without scans, a camera file
for another resolution) print one message saying what to change and exit with code 2;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from calibration.board import BoardError, BoardSpec
from calibration.check import CheckError
from calibration.extrinsic import ExtrinsicError, SolverOptions
from calibration.files import CalibrationFileError
from calibration.intrinsics import IntrinsicsError
from calibration.scans import PairingError, ScanFormatError
from calibration.time_offset import TimeOffsetError
from toolkit.cli_types import (
    INTERRUPTED,
    positive_float,
    positive_int,
    sigterm_as_interrupt,
)

if TYPE_CHECKING:
    from calibration.pipeline import ExtrinsicRun
    from toolkit.camera import PinholeCamera

# The extrinsic was estimated but the views do not pin it down (scripts must not go on).
EXIT_UNRELIABLE = 3

USER_ERRORS: tuple[type[BaseException], ...] = (
    BoardError, CheckError, ExtrinsicError, CalibrationFileError, IntrinsicsError, PairingError,
    ScanFormatError, TimeOffsetError, FileNotFoundError, IsADirectoryError, NotADirectoryError,
    FileExistsError, PermissionError,
)


def _file_outputs(*paths: str | None) -> None:
    """Refuse output files that cannot be written before any work (a folder in the way,
    a file where a folder must be): nothing is written in part."""
    for p in paths:
        if not p:
            continue
        path = Path(p)
        if path.is_dir():
            raise CalibrationFileError(f"{path}: is a folder; give a file name to write")
        parent = next((q for q in path.parents if q.exists()), None)
        if parent is not None and not parent.is_dir():
            raise CalibrationFileError(f"{path}: {parent} is a file, not a folder")


def _dir_output(p: str | None) -> None:
    if p and Path(p).exists() and not Path(p).is_dir():
        raise CalibrationFileError(f"{p}: is a file; give a folder to write into")


def _board(args: argparse.Namespace) -> BoardSpec:
    size = getattr(args, "board_size", None)
    return BoardSpec.parse(args.board, args.square, tuple(size) if size else None)


def _add_board(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board", required=True, metavar="COLSxROWS",
                   help="inner corners of the checkerboard, e.g. 11x8 for 12x9 squares")
    p.add_argument("--square", type=float, required=True, metavar="M",
                   help="side of one square in metres, e.g. 0.019")


def _np(x: Any) -> Any:
    from toolkit.io.atomic import to_jsonable

    return to_jsonable(x)


# ---------------------------------------------------------------------------- intrinsics


def cmd_intrinsics(args: argparse.Namespace) -> int:
    from calibration.files import write_camera
    from calibration.intrinsics import calibrate_intrinsics, detect_folder

    board = _board(args)
    # As extrinsic does: a folder in the way of --out failed only after the calibration.
    _file_outputs(args.out)
    dets, missed = detect_folder(Path(args.images), board)
    res = calibrate_intrinsics(dets, board, args.model, args.max_image_rms)
    # The intrinsics do not depend on the square size, but the file keeps it for the
    # extrinsic step: a size in millimetres is caught here, not there.
    from calibration.pipeline import check_board_distance

    check_board_distance(f"the {len(res.used)} views (median)",
                         float(np.median(list(res.board_distance_m.values()))), board)
    res.rejected = {**missed, **res.rejected}
    cam = res.camera
    print(f"camera {cam.width}x{cam.height}, model {args.model}: fx {cam.fx:.2f} fy {cam.fy:.2f}"
          f" cx {cam.cx:.2f} cy {cam.cy:.2f} dist {np.round(cam.dist, 5).tolist()}")
    print(f"RMS reprojection error {res.rms_px:.3f} px over {len(res.used)} images")
    for name, e in res.per_image_rms_px.items():
        print(f"  {name}: {e:.3f} px")
    for name, why in res.rejected.items():
        print(f"  rejected {name}: {why}")
    info = {**res.info(), "board": {"inner_corners": [board.cols, board.rows],
                                    "square_m": board.square}}
    write_camera(Path(args.out), cam, _np(info))
    print(f"wrote {args.out}")
    return 0


# ---------------------------------------------------------------------------- extrinsic


def _options(args: argparse.Namespace) -> SolverOptions:
    opts = SolverOptions(loss=args.loss)
    if args.no_prior:
        opts.prior_sigma_deg = opts.prior_sigma_m = None
    elif args.prior_sigma is not None:
        opts.prior_sigma_deg, opts.prior_sigma_m = args.prior_sigma
    return opts


def cmd_extrinsic(args: argparse.Namespace) -> int:
    from calibration.files import (
        load_camera,
        load_extrinsic,
        rig_for_extrinsic,
        write_rig_with_calibration,
    )
    from calibration.pipeline import (
        BoardSearch,
        load_candidates,
        load_candidates_from_sequence,
        run_extrinsic,
    )

    board = _board(args)
    _file_outputs(args.out, args.json)
    _dir_output(args.overlays)
    camera = load_camera(Path(args.camera)) if args.camera else None
    if args.sequence:
        cands, skipped, camera = load_candidates_from_sequence(
            Path(args.sequence), board, args.max_dt, args.skip_unpaired, camera,
            str(args.camera) if args.camera else None)
    else:
        if not (args.images and args.scans and camera is not None):
            raise CalibrationFileError("give --images, --scans and --camera, or --sequence")
        cands, skipped = load_candidates(Path(args.images), Path(args.scans), board, camera,
                                         str(args.camera), args.max_dt, args.skip_unpaired,
                                         args.stamp_unit)
    assert camera is not None
    search = BoardSearch(
        angle_window_deg=tuple(args.angle_window) if args.angle_window else None,
        max_offset_m=args.max_offset,
        mount=args.mount, seed=args.seed, range_noise_m=args.range_noise)
    init = load_extrinsic(Path(args.init)) if args.init else None
    if init is not None and np.linalg.norm(init[:3, 3]) > args.max_offset:
        # The solve refuses a result beyond --max-offset: such a start only fails later,
        # as "board found in only 0 views", with a hint to pass --init.
        raise CalibrationFileError(
            f"{args.init}: the --init extrinsic puts the laser "
            f"{np.linalg.norm(init[:3, 3]):.3g} m from the camera, beyond --max-offset "
            f"{args.max_offset:g} m: is its translation in millimetres (it is read in "
            "metres)? If the sensors are that far apart, raise --max-offset")
    # Read before the solve: a wrong --rig path failed only after it.
    base = None
    if args.out and args.rig:
        from toolkit.io.sequence import read_rig

        base = read_rig(Path(args.rig))
    run = run_extrinsic(cands, board, camera, search, _options(args), init, loo=not args.no_loo)
    run.skipped = {**skipped, **run.skipped}
    summary = run.summary()
    _print_extrinsic(run.result.T_camera_laser, summary, args.allow_unreliable)
    if args.out and args.json:
        # Written second, an earlier run's JSON would stand beside this rig if the run
        # stopped between the two: gone first, a stop leaves the rig without a JSON.
        Path(args.json).unlink(missing_ok=True)
    if args.out:
        rig = rig_for_extrinsic(camera, run.result.T_camera_laser, base)
        out_path = Path(args.out)
        if not summary["reliable"] and not args.allow_unreliable:
            # --out is what the rest of a workflow reads: an unreliable result goes beside
            # it, so that it never replaces a good one.
            out_path = unreliable_path(out_path)
        write_rig_with_calibration(out_path, rig, _np(summary))
        print(f"wrote {out_path}" + (
            "" if summary["reliable"] else " (marked reliable: false, as --allow-unreliable "
            "asked)" if args.allow_unreliable else f" (not {args.out}: the result is "
            "unreliable)"))
    if args.json:
        from calibration.files import extrinsic_to_mapping
        from toolkit.io.atomic import atomic_write_json

        atomic_write_json(Path(args.json), {**extrinsic_to_mapping(run.result.T_camera_laser),
                                            **summary}, clean_stale=True)
        print(f"wrote {args.json}")
    if args.overlays:
        _extrinsic_overlays(Path(args.overlays), run, camera,
                            Path(args.images) if args.images else None, args.sequence)
    return 0 if summary["reliable"] or args.allow_unreliable else EXIT_UNRELIABLE


# What `extrinsic --overlays DIR` wrote into DIR, so that a rerun can remove its own stale
# overlays (check lists its own in check.json).
OVERLAYS_LISTING = "overlays.json"


def _extrinsic_overlays(out: Path, run: ExtrinsicRun, camera: PinholeCamera,
                        img_dir: Path | None, sequence: str | None) -> None:
    """Each pair's scan drawn into its image, in ``out`` as ``<stem>_overlay.png``, listed
    in ``out/overlays.json``. An earlier run's overlays of pairs this run does not have
    stood beside these and looked current: the ones the earlier listing names go, files
    it does not name (a user's, an older version's) stay and are counted."""
    from calibration.check import overlay, project_scan
    from toolkit.io.atomic import atomic_write_json
    from toolkit.sensors import load_rgb

    out.mkdir(parents=True, exist_ok=True)
    listing = out / OVERLAYS_LISTING
    earlier = _earlier_overlays(listing)
    T = run.result.T_camera_laser
    head = {"written_by": "python -m calibration extrinsic", "T_camera_laser": T}
    planned = [_overlay_name(c.name) for c in run.candidates]
    # Listed before they are drawn: a run stopped half way leaves every overlay it wrote
    # named for the next run to remove, not unlisted for good.
    atomic_write_json(listing, {**head, "overlays": sorted(earlier | set(planned))},
                      clean_stale=True)
    written = []
    for c in run.candidates:
        path = img_dir / c.name if img_dir else _sequence_image(Path(str(sequence)), c.name)
        written.append(_save_overlay(out, c.name, overlay(
            load_rgb(path), project_scan(c.scan.points, T, camera))))
    _remove_earlier_overlays(out, earlier, written)
    atomic_write_json(listing, {**head, "overlays": written})
    print(f"wrote {len(written)} overlays and {OVERLAYS_LISTING} to {out}")
    others = sorted(p.name for p in out.glob("*_overlay.png") if p.name not in set(written))
    if others:
        print(f"note: {out} also holds {len(others)} overlay(s) this run did not write and "
              f"no {OVERLAYS_LISTING} listed ({others[0]}{', ...' if len(others) > 1 else ''}"
              "): left in place; delete them if they are an earlier run's")


def unreliable_path(path: Path) -> Path:
    """Where an unreliable extrinsic is written instead of ``path``: rig.yaml ->
    rig.unreliable.yaml."""
    return path.with_name(f"{path.stem}.unreliable{path.suffix}")


def _sequence_image(root: Path, name: str) -> Path:
    return root / "camera" / "images" / name


def _print_extrinsic(T: np.ndarray, s: dict[str, Any], allow_unreliable: bool = False) -> None:
    from calibration.files import extrinsic_to_mapping

    tf = extrinsic_to_mapping(T)["tf"]
    with np.printoptions(precision=5, suppress=True):
        print("T_camera_laser (p_camera_optical = T @ p_laser):")
        print(np.array(T))
    print(f"tf camera_optical -> laser: xyz {np.round(tf['translation'], 4).tolist()} "
          f"quat xyzw {np.round(tf['rotation'], 5).tolist()}")
    print(f"views used {s['views_used']}, board points {s['points_on_board']}, point-to-plane "
          f"RMS {s['residual_rms_m'] * 1000:.1f} mm ({s['refinement']}, start: "
          f"{s['initialisation']})")
    print("std rotation (deg, about camera x y z): "
          f"{np.round(s['std_rotation_deg'], 3).tolist()}; translation (mm, along x y z): "
          f"{np.round(np.array(s['std_translation_m']) * 1000, 1).tolist()}")
    if "lidar_range_noise_m" in s:
        noise = s["lidar_range_noise_m"]
        said = ("not measurable (too few neighbouring beams)" if noise is None
                else f"{noise * 1000:.1f} mm ({s['lidar_range_noise_source']})")
        print(f"lidar range noise {said}: board points within "
              f"{s['board_line_band_m'] * 100:.1f} cm of a line, then "
              f"{s['board_reselect_band_m'] * 100:.1f} cm of the predicted board")
    loo = s.get("leave_one_out")
    if loo:
        print(f"leave-one-view-out: rotation spread {loo['rotation_spread_deg']:.3f} deg, "
              f"translation spread {loo['translation_spread_m'] * 1000:.1f} mm")
    for name, why in {**s["views_rejected"], **s["images_skipped"]}.items():
        print(f"  not used {name}: {why}")
    for w in s["warnings"]:
        print(f"WARNING: {w}")
    # Last, so that it is what a user sees: the numbers above may look fine.
    for why in s["unreliable_because"]:
        print(f"UNRELIABLE: {why}")
    if not s["reliable"] and allow_unreliable:
        print("WARNING: RESULT UNRELIABLE, used anyway (--allow-unreliable): the reasons above "
              "stand; --out gets it, marked 'reliable: false', so that every later read of "
              "it warns. Exit code 0.")
    elif not s["reliable"]:
        print("RESULT UNRELIABLE: do not use this extrinsic as it is (the file written says "
              "'reliable: false', and is not --out itself); see the reasons above. Exit "
              f"code {EXIT_UNRELIABLE} (--allow-unreliable writes --out anyway).")


# ---------------------------------------------------------------------------- check


def cmd_check(args: argparse.Namespace) -> int:
    from calibration.check import SEEN_AXES, overlay, project_scan, sensitivity
    from calibration.files import load_camera, load_extrinsic
    from calibration.pipeline import check_frames_from_pairs, check_frames_from_sequence
    from toolkit.io.atomic import atomic_write_json

    out = Path(args.out)
    _dir_output(args.out)
    if args.sequence:
        from toolkit.io.sequence import read_rig

        root = Path(args.sequence)
        rig = read_rig(Path(args.rig) if args.rig else root / "rig.yaml")
        camera = rig.camera
        T = load_extrinsic(Path(args.extrinsic)) if args.extrinsic else rig.T_camera_laser
        frames, _ = check_frames_from_sequence(
            root, T, args.frames, args.max_dt, Path(args.depth) if args.depth else None,
            use_gt_depth=args.score != "edges", camera=camera,
            camera_source=str(args.rig) if args.rig else str(root / "rig.yaml"))
    else:
        # A rig holds the camera too (the one `extrinsic --out` writes): asking for the
        # same camera again as --camera sent users back to the command with one more flag.
        camera_file = args.camera or args.rig
        missing = [flag for flag, given in (("--images", args.images), ("--scans", args.scans),
                                            ("--camera (or a --rig holding it)", camera_file),
                                            ("--extrinsic (or --rig)",
                                             args.extrinsic or args.rig)) if not given]
        if missing:
            raise CalibrationFileError(f"missing {', '.join(missing)}: give --sequence, or "
                                       "--images, --scans, --camera and --extrinsic (or a "
                                       "--rig, which holds both)")
        camera = load_camera(Path(camera_file))
        T = load_extrinsic(Path(args.extrinsic or args.rig))
        frames = check_frames_from_pairs(Path(args.images), Path(args.scans), camera,
                                         str(camera_file), args.max_dt,
                                         Path(args.depth) if args.depth else None,
                                         args.stamp_unit, args.frames)
    # Scored first: a check that cannot score (no depth maps for --score depth) writes no
    # overlays.
    source = args.extrinsic or args.rig or str(Path(args.sequence) / "rig.yaml")
    scores = sensitivity(frames, T, camera, args.perturb_deg, args.score, source)
    out.mkdir(parents=True, exist_ok=True)
    earlier = _earlier_overlays(out / "check.json")
    written = [_save_overlay(out, f.name, overlay(f.image, project_scan(f.points, T, camera)))
               for f in frames]
    d = scores.to_dict()
    print(f"{len(frames)} frames, {scores.n_points} points; {scores.kind} score "
          f"{scores.score:.4f}")
    for k, v in scores.perturbed.items():
        print(f"  rotated {k}: {v:.4f} ({-scores.drop(k) * 100:+.1f} %)")
    seen = SEEN_AXES[scores.kind]
    better = [k for k in scores.perturbed if k[:2] in seen and scores.drop(k) < -0.02]
    if better:
        print(f"WARNING: the score rises when the extrinsic is rotated ({', '.join(better)}); "
              "the extrinsic may be off about that axis")
    if scores.kind == "edges":
        print("note: the edge score judges rotation about the camera's vertical axis (ry) "
              "only; give depth maps (--depth) to judge tilts too")
    # An earlier run's overlays of other frames stood beside these while check.json listed
    # only these.
    _remove_earlier_overlays(out, earlier, written)
    atomic_write_json(out / "check.json", {"T_camera_laser": T, **d, "overlays": written},
                      clean_stale=True)
    print(f"wrote {len(written)} overlays and check.json to {out}")
    return 0


def _overlay_name(frame: str) -> str:
    return f"{Path(frame).stem}_overlay.png"


def _save_overlay(out: Path, frame: str, rgb: np.ndarray) -> str:
    """Write the overlay ``rgb`` ([H, W, 3] uint8) of image ``frame`` into ``out``; its
    file name."""
    import cv2

    from toolkit.io.atomic import atomic_path

    name = _overlay_name(frame)
    with atomic_path(out / name, clean_stale=True) as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return name


def _remove_earlier_overlays(out: Path, earlier: set[str], written: list[str]) -> None:
    """Delete the overlays an earlier run listed (``earlier``) that this one did not
    write: only files that run's listing names go, never a user's."""
    for name in sorted(earlier - set(written)):
        (out / name).unlink(missing_ok=True)


def _earlier_overlays(path: Path) -> set[str]:
    """Overlay file names an earlier run listed in its ``path`` (check.json, overlays.json):
    plain ``*_overlay.png`` names only; none when the file is missing or not such a listing."""
    try:
        listed = json.loads(path.read_text()).get("overlays", [])
    except (OSError, ValueError, AttributeError):
        return set()
    if not isinstance(listed, list):
        return set()
    return {n for n in listed if isinstance(n, str) and n.endswith("_overlay.png")
            and Path(n).name == n and (path.parent / n).is_file()}


# ---------------------------------------------------------------------------- time offset


def cmd_time_offset(args: argparse.Namespace) -> int:
    from rich.progress import track

    from calibration.time_offset import advice, applied_delay, measure, write_figure
    from toolkit.io.atomic import atomic_write_json
    from toolkit.io.sequence import read_sequence

    out = Path(args.out)
    _dir_output(args.out)
    if not args.search > 0.004:  # two steps of the 2 ms grid either way
        raise CalibrationFileError(f"--search {args.search}: give the largest delay to try "
                                   "in seconds, more than 0.004 (default 0.3)")
    if not args.window > 0:
        raise CalibrationFileError(f"--window {args.window}: give a span in seconds, e.g. 0.5")
    seq = read_sequence(args.sequence)
    if args.trajectory:
        from toolkit.io.tum import read_tum

        try:
            traj = read_tum(args.trajectory)
        except ValueError as e:  # a malformed line: named by the reader
            raise CalibrationFileError(str(e)) from e
        source = args.trajectory
    elif seq.odometry is not None:
        traj, source = seq.odometry, f"{args.sequence} odometry"
    else:
        raise CalibrationFileError(
            f"{args.sequence}: no odometry in the sequence; give --trajectory, the robot's "
            "poses on the lidar's clock (e.g. runs/NAME/slam2d/trajectory_base.tum)")
    if traj.child not in ("base_link", "base", "body", "base_footprint"):
        print(f"note: {source} holds T_{traj.frame}_{traj.child}: its yaw is taken as the "
              "robot's (any frame mounted level on the robot turns alike)")
    strided = seq.frames[::args.stride] if args.stride > 1 else seq.frames
    if len(strided) < 3:  # said with the folder: a lidar-only recording has no images at all
        kept = f" ({len(strided)} with --stride {args.stride})" if args.stride > 1 else ""
        raise CalibrationFileError(
            f"{args.sequence}: {len(seq.frames)} camera frames{kept}; time-offset compares "
            "the camera's turning with the trajectory's and needs at least 3 (a lidar-only "
            "recording, such as a converted CARMEN log, has none: give a sequence with images)")
    m = measure(strided, seq.rig.camera, seq.rig.T_base_camera, traj, source,
                lambda it, total: track(it, total=total, description="camera rotations",
                                        transient=True, disable=not sys.stderr.isatty()),
                args.max_frames, args.search, args.window)
    res, applied = m.result, applied_delay(seq)
    out.mkdir(parents=True, exist_ok=True)
    write_figure(str(out / "time_offset.png"), res, m.stamps, m.dyaw, traj)
    found, measured = int(np.isfinite(m.dyaw).sum()), m.pairs_measured
    atomic_write_json(out / "time_offset.json", {
        **res.to_dict(), "sequence": str(args.sequence), "trajectory": source,
        "frames": len(m.stamps), "frame_pairs_measured": measured,
        "frame_pairs_with_rotation": found,
        "median_inliers": float(np.median(m.inliers)) if len(m.inliers) else 0.0,
        "applied_at_conversion_s": applied,
        "meaning": "image stamp minus exposure time, left after the conversion's "
                   "sync.camera_delay_s (applied_at_conversion_s); the setting to use is "
                   "their sum"}, clean_stale=True)
    ms = res.delay_s * 1000
    print(f"camera delay: {ms:+.1f} ms (+- {res.std_s * 1000:.1f} ms; {res.windows} windows "
          f"of {res.frames_per_window} frames, rotations found in {found} of {measured} "
          f"frame pairs); yaw mismatch {res.residual_at_zero_deg:.3f} -> "
          f"{res.residual_deg:.3f} deg per window")
    print(f"wrote {out / 'time_offset.json'} and {out / 'time_offset.png'}")
    if not res.reliable:
        print("UNRELIABLE: " + "; ".join(res.reasons))
        return EXIT_UNRELIABLE
    print(advice(res, applied))
    return 0


# ---------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m calibration",
        description="Camera intrinsics, camera - 2D lidar extrinsic, and checks. The "
                    "extrinsic is stored as T_camera_laser: p_camera_optical = T @ p_laser.")
    p.add_argument("-v", "--verbose", action="store_true", help="log progress")
    sub = p.add_subparsers(dest="command", required=True)

    pi = sub.add_parser("intrinsics", help="camera intrinsics from checkerboard images",
                        description="Detect the checkerboard (sub-pixel corners), calibrate, "
                                    "reject outlier images, write a camera YAML.")
    pi.add_argument("--images", required=True, help="folder of checkerboard images")
    _add_board(pi)
    pi.add_argument("--model", default="opencv", choices=sorted(_models()),
                    help="distortion model: " + "; ".join(f"{k}: {v}"
                                                          for k, v in _models().items()))
    pi.add_argument("--max-image-rms", type=float, default=None, metavar="PX",
                    help="reject images above this RMS (default: 3x the median, >= 0.5 px)")
    pi.add_argument("--out", default="camera.yaml",
                    help="camera YAML to write (default: %(default)s, in the current folder)")
    pi.set_defaults(func=cmd_intrinsics)

    pe = sub.add_parser(
        "extrinsic", help="camera - 2D lidar extrinsic from board views",
        description="Zhang & Pless (2004) style: board planes from PnP, board points found "
                    "in each scan, linear start, robust joint refinement, outlier views "
                    "rejected, covariance and leave-one-out stability.")
    pe.add_argument("--images", help="folder of images named <stamp>.png (see --stamp-unit)")
    pe.add_argument("--scans", help="folder of scans (.pcd, .csv, .npz) named <stamp>.ext, an "
                                    "npz of many scans, or a sequence folder")
    pe.add_argument("--camera", help="camera YAML (toolkit, rig or ROS camera_info)")
    pe.add_argument("--sequence", help="sequence folder instead of --images/--scans (the camera "
                                       "comes from its rig.yaml unless --camera is given)")
    _add_board(pe)
    pe.add_argument("--out", help="rig YAML to write (with T_camera_laser and the statistics)")
    pe.add_argument("--rig", help="existing rig YAML: keep its camera mount, move the laser")
    pe.add_argument("--json", help="write the full result as JSON")
    pe.add_argument("--overlays", metavar="DIR", help="write scan-on-image overlays here")
    pe.add_argument("--max-dt", type=float, default=0.1, metavar="S",
                    help="largest image-scan time difference to pair (default 0.1 s)")
    pe.add_argument("--skip-unpaired", action="store_true",
                    help="use the paired images only instead of failing on unpaired ones")
    _add_stamp_unit(pe)
    pe.add_argument("--angle-window", type=float, nargs=2, metavar=("MIN", "MAX"),
                    help="laser bearings (degrees, counter-clockwise from laser +x) where the "
                         "board is; overrides the automatic search direction")
    pe.add_argument("--max-offset", type=float, default=0.5, metavar="M",
                    help="how far apart camera and laser can be (default 0.5 m)")
    pe.add_argument("--board-size", type=float, nargs=2, metavar=("W", "H"),
                    help="whole board in metres, width along the first corner count, pattern "
                         "centred: the scan's end points on the board then constrain the "
                         "extrinsic too (and the segment search is tighter)")
    pe.add_argument("--mount", default="forward", choices=("forward", "any"),
                    help="without --init: 'forward' assumes the laser looks where the camera "
                         "looks (search direction and weak prior); 'any' assumes nothing")
    pe.add_argument("--init", help="extrinsic guess YAML (T_camera_laser, T_laser_camera, rig or "
                                   "tf-style); centre of the weak prior")
    pe.add_argument("--prior-sigma", type=float, nargs=2, metavar=("DEG", "M"),
                    help="strength of the prior towards the guess (default 20 deg, 0.5 m)")
    pe.add_argument("--no-prior", action="store_true", help="no prior at all")
    pe.add_argument("--loss", default="soft_l1",
                    choices=("linear", "soft_l1", "huber", "cauchy", "arctan"),
                    help="robust loss of the refinement (default soft_l1)")
    pe.add_argument("--seed", type=int, default=0, help="RANSAC seed (default 0)")
    pe.add_argument("--range-noise", type=positive_float, metavar="M",
                    help="the lidar's range noise (1 sigma, metres): board points are taken "
                         "within 2 sigma of a line and 3 sigma of the predicted board (at "
                         "least 2 and 3 cm); default: measured from the scans")
    pe.add_argument("--no-loo", action="store_true", help="skip the leave-one-out runs")
    pe.add_argument("--allow-unreliable", action="store_true",
                    help="write --out even when the checks call the result unreliable (it is "
                         "still marked reliable: false, and readers of it warn) and exit 0")
    pe.set_defaults(func=cmd_extrinsic)

    pc = sub.add_parser(
        "check", help="overlay scans on images and score the extrinsic",
        description="Project scan points into camera images coloured by range (PNG per "
                    "frame) and score the extrinsic: agreement with depth maps when known, "
                    "else alignment of range discontinuities with image edges; the score is "
                    "also given with the extrinsic rotated about each camera axis.")
    pc.add_argument("--sequence", help="sequence folder")
    pc.add_argument("--rig", help="rig YAML with the extrinsic (default: the sequence's)")
    pc.add_argument("--extrinsic", help="extrinsic YAML overriding the rig's")
    pc.add_argument("--images", help="image folder (instead of --sequence)")
    pc.add_argument("--scans", help="scan folder (instead of --sequence)")
    pc.add_argument("--camera", help="camera YAML (with --images; default: the --rig's)")
    pc.add_argument("--depth", help="folder of metric depth maps (<index:06d> or image stem, "
                                    ".npy or .png)")
    pc.add_argument("--score", default="auto", choices=("auto", "depth", "edges"),
                    help="auto: depth when every frame has a depth map, else edges")
    pc.add_argument("--frames", type=positive_int, default=12,
                    help="frames (or image/scan pairs) to use, spread evenly (default 12)")
    pc.add_argument("--max-dt", type=float, default=0.1, metavar="S",
                    help="largest image-scan time difference (default 0.1 s, as extrinsic)")
    _add_stamp_unit(pc)
    pc.add_argument("--perturb-deg", type=float, default=2.0,
                    help="rotation of the sensitivity test (default 2 deg)")
    pc.add_argument("--out", default="calibration_check",
                    help="output folder (default: %(default)s)")
    pc.set_defaults(func=cmd_check)

    pt = sub.add_parser(
        "time-offset", help="camera delay: how much later images are stamped than taken",
        description="The robot's turning seen by the camera (rotations between consecutive "
                    "images) against a trajectory on the lidar's clock (lidar SLAM or "
                    "odometry): the shift that lines them up is the camera's stamp delay. "
                    "The recording must turn.")
    pt.add_argument("--sequence", required=True, help="sequence folder")
    pt.add_argument("--trajectory", help="TUM file of T_world_base on the lidar's clock, e.g. "
                                         "runs/NAME/slam2d/trajectory_base.tum (default: the "
                                         "sequence's odometry)")
    pt.add_argument("--search", type=float, default=0.3, metavar="S",
                    help="largest delay tried either way (default 0.3 s)")
    pt.add_argument("--window", type=float, default=0.5, metavar="S",
                    help="span of consecutive frames compared at once (default 0.5 s)")
    pt.add_argument("--stride", type=positive_int, default=1,
                    help="use every n-th frame (default 1). Rotations are found between "
                         "frames close in time: at 10 Hz keep it at 1 or 2")
    pt.add_argument("--max-frames", type=positive_int, default=3000,
                    help="read at most this many frames, in runs of 100 spread along a "
                         "longer recording (default 3000)")
    pt.add_argument("--out", default="time_offset", help="output folder (default: %(default)s)")
    pt.set_defaults(func=cmd_time_offset)
    return p


def _add_stamp_unit(p: argparse.ArgumentParser) -> None:
    p.add_argument("--stamp-unit", default="auto", choices=("auto", "s", "ms", "us", "ns"),
                   help="unit of the stamps in image and scan file names; auto (default): "
                        "integers of 10, 13, 16 or 19 digits are Unix times in s, ms, us or "
                        "ns, decimals and shorter integers are seconds; <sec>_<nsec> names "
                        "take auto or s")


def _models() -> dict[str, str]:
    from calibration.intrinsics import MODELS

    return MODELS


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("calibration.progress").setLevel(logging.INFO)
    previous = sigterm_as_interrupt()
    try:
        if getattr(args, "sequence", None):
            # Before any of the sequence's files is read, so that a run or stage folder
            # is answered with the sequence in it, not with "rig.yaml not found".
            from toolkit.io.sequence import check_sequence_folder

            check_sequence_folder(Path(args.sequence))
        return int(args.func(args))
    except KeyboardInterrupt:
        # Every file is written whole or not at all (the one in flight was removed): no
        # traceback, and no temporary left beside the outputs by a kill.
        print("interrupted: the files written so far are whole, the one being written was "
              "not kept; run the command again to write them all", file=sys.stderr)
        return INTERRUPTED
    except USER_ERRORS as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except Exception as e:
        # Errors of the sequence reader name the file and field: show them the same way.
        if type(e).__name__ == "SequenceFormatError":
            print(f"error: {e}", file=sys.stderr)
            return 2
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
