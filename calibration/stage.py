"""The recipe stage ``calibrate``: camera - 2D lidar extrinsic into a rig.

```yaml
- stage: calibrate
  source: simulate          # simulate | files
  views: 10                 # simulate: board views of the capture
  seed: 0
  board: 11x8               # inner corners
  square_m: 0.05
  # files: images / scans / camera (or capture: a folder with images/, lasers/, camera.yaml)

- stage: calibrate          # check only: no board, the upstream sequence's extrinsic
  mode: check
  check_frames: 6
```

With ``source: simulate`` the simulator renders a calibration capture of the upstream
sequence's rig (or its default rig) and the result is compared with the exact answer.
The calibrated rig is published as artifact ``rig`` (the upstream sequence's rig with the
laser moved to the calibrated pose), the full result as ``calibration``; with an upstream
sequence, ``check`` overlays its scans on its images and scores the extrinsic.

``mode: check`` calibrates nothing: it checks the upstream sequence's extrinsic (or the one
in ``extrinsic``, any file ``python -m calibration check --extrinsic`` reads) on the
sequence, draws the overlays, scores it and the same extrinsic turned by 2 degrees about
each camera axis, and passes the rig on unchanged. On a simulated sequence the rig is the
exact one, so this shows what the score makes of a right and of a 2-degree-wrong extrinsic.
The check also measures the camera's stamp delay against the wheel odometry
(``calibration.time_offset``; ``time_offset: false`` skips it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import Field

from toolkit.recipe.stage import Stage, StageConfig, StageContext, StageError


class CalibrateConfig(StageConfig):
    """Settings of ``calibrate``."""

    # calibrate: estimate the extrinsic from board views (and check it on the sequence);
    # check: only check an existing extrinsic on the upstream sequence
    mode: Literal["calibrate", "check"] = "calibrate"
    source: Literal["simulate", "files"] = "files"
    # files: a capture folder (images/, lasers/, camera.yaml[, groundtruth.yaml]) or the
    # three paths; camera defaults to the upstream sequence's
    capture: str | None = None
    images: str | None = None
    scans: str | None = None
    camera: str | None = None
    # simulate
    views: int = Field(10, ge=4)  # calibration.extrinsic.MIN_VIEWS: fewer are refused
    seed: int = 0
    lidar_noise_m: float = Field(0.01, ge=0)
    lidar_beams: int | None = Field(None, gt=1)  # None: the simulator's lidar
    # board and search
    board: str = "11x8"
    square_m: float = Field(0.05, gt=0)
    board_size_m: tuple[float, float] | None = None
    max_dt_s: float = Field(0.1, gt=0)
    # unit of the stamps in file names; auto: 10/13/16/19 digits are Unix s/ms/us/ns
    stamp_unit: Literal["auto", "s", "ms", "us", "ns"] = "auto"
    angle_window_deg: tuple[float, float] | None = None
    max_offset_m: float = Field(0.5, gt=0)
    mount: Literal["forward", "any"] = "forward"
    loss: Literal["linear", "soft_l1", "huber", "cauchy", "arctan"] = "soft_l1"
    ransac_seed: int = 0
    # the lidar's range noise (1 sigma, m) that sets the bands the board's points are taken
    # in (2 and 3 sigma, at least 2 and 3 cm); None: measured from the scans
    range_noise_m: float | None = Field(None, gt=0)
    leave_one_out: bool = True
    # check on the upstream sequence
    check: bool = True
    check_frames: int = Field(6, ge=1)
    # With the check: the camera's stamp delay against the sequence's wheel odometry
    # (python -m calibration time-offset; up to 3000 frames are read, ~11 s for 644 at
    # 640x480).
    time_offset: bool = True
    # mode check: the extrinsic to check (T_camera_laser, a rig, a tf mapping); None: the
    # upstream sequence's rig
    extrinsic: str | None = None
    # An extrinsic the checks call unreliable stops the stage (as the CLI exits 3), its
    # result kept in calibration.unreliable.yaml; so does, in mode check, an extrinsic file
    # marked reliable: false. true passes it on as the rig anyway, the mark kept in it.
    allow_unreliable: bool = False


class CalibrateStage(Stage):
    """Calibrate the camera - 2D lidar extrinsic from board views and write it into a rig."""

    name = "calibrate"
    Config = CalibrateConfig
    optional_requires = ("sequence",)
    provides = ("rig", "calibration")
    # 2: mode check; overlays of the extrinsic turned by 2 degrees next to the checked one
    # 3: at least 4 views, the max-offset limit, outlier rule for 5 views, 'reliable'
    # 4: an unreliable extrinsic stops the stage (allow_unreliable); segments compared with
    #    the laser plane's cut of the board
    # 5: the check measures the camera's time offset
    # 6: the check de-skews scans with per-beam timing along the sequence's poses (the
    #    exact extrinsic scored 0.42 on a robot turning at 1 rad/s, 0.98 now) and refuses
    #    them without poses; a check that scores no point stops (it reported a NaN score);
    #    the board's points are taken in bands of 2 and 3 range-noise sigmas (measured; were
    #    2 and 3 cm: a 3 cm lidar's board was found in 1 of 10 views)
    # 7: images are read as stored, a JPEG's EXIF orientation tag not applied (intrinsics
    #    from rotated pixels did not fit the frames the sequence reader gives)
    # 8: a board distance scale that makes every view agree is fitted before any view is
    #    left out (a focal length 3.5 % off left 3 good views out and hid the scale)
    # 9: a board distance scale 0.4-1.5 % off and sure (5 sd) is a warning (a focal length
    #    1 % long moved the extrinsic 1 cm without a word)
    # 10: a view whose scan holds no finite point is skipped as such (the summary said "no
    #     segment matches the board")
    # 11: the check de-skews swept scans with the odometry's poses inside each sweep, beam
    #     by beam (constant velocity between the sweep's ends where it has none)
    version = 11

    config: CalibrateConfig

    def external_inputs(self) -> list[Path]:
        cfg = self.config
        # Missing paths are listed too: `validate` and `run` then name them before any
        # stage starts.
        if cfg.mode == "check":
            return [Path(cfg.extrinsic)] if cfg.extrinsic else []
        if cfg.source == "simulate":
            return []
        # Folders as they are: the runner fingerprints every file under them, through
        # linked folders too.
        return [Path(p) for p in (cfg.capture, cfg.images, cfg.scans, cfg.camera)
                if p is not None]

    # ------------------------------------------------------------------ inputs
    def _inputs(self, ctx: StageContext, base_rig: Any) -> tuple[Path, Path, Path | None,
                                                                  Path | None]:
        """(images, scans, camera YAML or None for the rig's, ground truth or None)."""
        cfg = self.config
        if cfg.source == "simulate":
            try:
                from toolkit.sim.calib_capture import capture_calibration
            except ImportError as e:  # pragma: no cover - the simulator ships with the toolkit
                raise StageError(f"calibrate: source 'simulate' needs toolkit.sim ({e})") from e
            from toolkit.sim.sensors import LidarSpec

            cap = ctx.stage_dir / "capture"
            if not (cap / "groundtruth.yaml").exists():
                cols, rows = (int(v) for v in cfg.board.lower().split("x"))
                capture_calibration(
                    cap, cfg.views, seed=cfg.seed, board=(cols, rows), square=cfg.square_m,
                    lidar_noise=cfg.lidar_noise_m,
                    camera=base_rig.camera if base_rig is not None else None,
                    T_camera_laser=base_rig.T_camera_laser if base_rig is not None else None,
                    lidar=LidarSpec(beams=cfg.lidar_beams) if cfg.lidar_beams else None)
            return cap / "images", cap / "lasers", cap / "camera.yaml", cap / "groundtruth.yaml"
        if cfg.capture:
            cap = Path(cfg.capture)
            gt = cap / "groundtruth.yaml"
            cam = Path(cfg.camera) if cfg.camera else cap / "camera.yaml"
            return (cap / "images", cap / "lasers", cam if cam.exists() else None,
                    gt if gt.exists() else None)
        if not (cfg.images and cfg.scans):
            raise StageError("calibrate: give 'capture' (a folder with images/ and lasers/), "
                             "or 'images' and 'scans', or source: simulate")
        return Path(cfg.images), Path(cfg.scans), Path(cfg.camera) if cfg.camera else None, None

    # ------------------------------------------------------------------ run
    def run(self, ctx: StageContext) -> None:
        from calibration.board import BoardSpec
        from calibration.cli import USER_ERRORS
        from calibration.extrinsic import SolverOptions, transform_error
        from calibration.files import (
            extrinsic_to_mapping,
            load_camera,
            rig_for_extrinsic,
            write_rig_with_calibration,
        )
        from calibration.pipeline import BoardSearch, load_candidates, run_extrinsic
        from toolkit.io.atomic import atomic_write_text, to_jsonable

        cfg = self.config
        seq_dir = ctx.artifact("sequence") if ctx.has_artifact("sequence") else None
        base_rig = None
        if seq_dir is not None:
            from toolkit.io.sequence import read_rig

            base_rig = read_rig(seq_dir / "rig.yaml")
        if cfg.mode == "check":
            self._run_check_only(ctx, seq_dir, base_rig)
            return
        try:
            board = BoardSpec.parse(cfg.board, cfg.square_m, cfg.board_size_m)
            images, scans, cam_path, gt_path = self._inputs(ctx, base_rig)
            if cam_path is not None:
                camera, cam_src = load_camera(cam_path), str(cam_path)
            elif base_rig is not None:
                camera, cam_src = base_rig.camera, str(seq_dir / "rig.yaml")
            else:
                raise StageError("calibrate: no camera: give 'camera' (a camera YAML) or run "
                                 "after a stage that provides a sequence")
            cands, skipped = load_candidates(images, scans, board, camera, cam_src,
                                             cfg.max_dt_s, stamp_unit=cfg.stamp_unit)
            search = BoardSearch(angle_window_deg=cfg.angle_window_deg,
                                 max_offset_m=cfg.max_offset_m, mount=cfg.mount,
                                 seed=cfg.ransac_seed, range_noise_m=cfg.range_noise_m)
            run = run_extrinsic(cands, board, camera, search, SolverOptions(loss=cfg.loss),
                                loo=cfg.leave_one_out)
        except USER_ERRORS as e:
            raise StageError(f"calibrate: {e}") from e
        run.skipped = {**skipped, **run.skipped}
        res = run.result
        T = res.T_camera_laser
        summary = run.summary()
        metrics: dict[str, Any] = {
            "views_used": len(res.views_used),
            "residual_rms_m": res.residual_rms_m,
            "rotation_std_deg": float(np.linalg.norm(res.std_rotation_deg)),
            "translation_std_m": float(np.linalg.norm(res.std_translation_m)),
            "weak_directions": len(res.weak_directions),
            "reliable": res.reliable,
        }
        if run.loo is not None:
            metrics["loo_rotation_spread_deg"] = run.loo.rotation_spread_deg
            metrics["loo_translation_spread_m"] = run.loo.translation_spread_m
        T_true = None
        if gt_path is not None:
            T_true = np.asarray(yaml.safe_load(gt_path.read_text())["T_camera_laser"], float)
            rot, tra = transform_error(T, T_true)
            metrics["rotation_error_deg"] = rot
            metrics["translation_error_m"] = tra
            summary["error_vs_ground_truth"] = {"rotation_deg": rot, "translation_m": tra}

        calib_text = yaml.safe_dump(to_jsonable({**extrinsic_to_mapping(T), **summary}),
                                    sort_keys=False)
        if not res.reliable and not cfg.allow_unreliable:
            # The later stages would place every lidar point with it.
            atomic_write_text(ctx.stage_dir / "calibration.unreliable.yaml", calib_text)
            raise StageError(
                f"calibrate: the extrinsic from {len(res.views_used)} views is unreliable: "
                f"{'; '.join(r.rstrip('.') for r in res.unreliable)}. It is in "
                f"{ctx.stage_dir / 'calibration.unreliable.yaml'}; capture more views (boards "
                "tilted differently, nearer), or set allow_unreliable: true to use it anyway")
        calib_path = ctx.stage_dir / "calibration.yaml"
        atomic_write_text(calib_path, calib_text)
        rig = rig_for_extrinsic(camera, T, base_rig)
        rig_path = ctx.stage_dir / "rig.yaml"
        write_rig_with_calibration(rig_path, rig, to_jsonable(summary))

        lines = [
            f"Extrinsic from {len(res.views_used)} board views ({res.n_points} scan points on "
            f"the board): point-to-plane RMS {res.residual_rms_m * 1000:.1f} mm; std "
            f"{np.round(res.std_rotation_deg, 3).tolist()} deg about camera x y z, "
            f"{np.round(res.std_translation_m * 1000, 1).tolist()} mm along x y z.",
        ]
        if run.loo is not None:
            lines.append(f"Leave-one-view-out spread: {run.loo.rotation_spread_deg:.3f} deg, "
                         f"{run.loo.translation_spread_m * 1000:.1f} mm.")
        if T_true is not None:
            lines.append(f"Error against the simulator's ground truth: "
                         f"{metrics['rotation_error_deg']:.3f} deg, "
                         f"{metrics['translation_error_m'] * 1000:.1f} mm.")
        lines += [f"**Warning:** {w}" for w in res.warnings]
        lines += [f"**Unreliable:** {w}" for w in res.unreliable]
        if seq_dir is not None and cfg.check:
            try:
                lines += self._check(ctx, seq_dir, T, T_true, metrics)
            except USER_ERRORS as e:
                # The extrinsic stands on the board views; a sequence it cannot be checked
                # on (swept scans without poses) is said, not a lost calibration.
                ctx.log.warning("calibrate: the check on the sequence was not run: %s", e)
                lines.append(f"**Check not run:** {e}")
        ctx.add_metrics(metrics)
        ctx.report("\n\n".join(lines))
        ctx.provide("rig", rig_path)
        ctx.provide("calibration", calib_path)

    def _run_check_only(self, ctx: StageContext, seq_dir: Path | None, base_rig: Any) -> None:
        """``mode: check``: score an existing extrinsic on the sequence, pass the rig on."""
        from calibration.cli import USER_ERRORS
        from calibration.extrinsic import transform_error
        from calibration.files import (
            extrinsic_to_mapping,
            read_extrinsic,
            rig_for_extrinsic,
            write_rig_with_calibration,
        )
        from toolkit.io.atomic import atomic_write_text, to_jsonable
        from toolkit.io.sequence import write_rig

        cfg = self.config
        if seq_dir is None or base_rig is None:
            raise StageError("calibrate: mode 'check' needs a sequence from an earlier stage "
                             "(simulate or ingest) to check the extrinsic on")
        marks = None
        if cfg.extrinsic:
            try:
                T, marks = read_extrinsic(Path(cfg.extrinsic))
            except USER_ERRORS as e:
                raise StageError(f"calibrate: {e}") from e
            what = f"the extrinsic of {cfg.extrinsic}"
            if marks is not None and marks["reliable"] is False and not cfg.allow_unreliable:
                # Passed on, it is what the later stages place every lidar point with.
                why = [str(r).rstrip(".") for r in marks.get("unreliable_because") or []]
                raise StageError(
                    f"calibrate: {cfg.extrinsic} is marked reliable: false (field "
                    "'reliable' of its calibration): "
                    f"{'; '.join(why) or 'no reason'}"
                    ". Calibrate again with more varied board views, or set allow_unreliable: "
                    "true to check it and pass it on as the rig anyway")
        else:
            T = base_rig.T_camera_laser
            what = "the sequence's extrinsic"
        # A simulated sequence's rig is the exact one the simulator rendered with.
        meta_path = seq_dir / "meta.yaml"
        meta = yaml.safe_load(meta_path.read_text()) if meta_path.exists() else {}
        simulated = isinstance(meta, dict) and "simulator" in meta
        T_true = base_rig.T_camera_laser if simulated else None
        if simulated and not cfg.extrinsic:
            what += " (the simulator's exact rig)"
        metrics: dict[str, Any] = {}
        if isinstance(meta, dict) and meta.get("has_camera") is False:
            # A lidar-only recording (a CARMEN log, a bag without images) goes on to the
            # SLAM: there is no image to check the extrinsic or the camera's clock on.
            lines = [f"No camera in this recording (lidar only): {what} is not checked and "
                     "the rig passes on unchanged."]
        else:
            try:
                lines = [f"Check of {what}, no calibration."]
                lines += self._check(ctx, seq_dir, T, T_true, metrics)
            except USER_ERRORS as e:
                raise StageError(f"calibrate: {e}") from e
        if T_true is not None:
            rot, tra = transform_error(T, T_true)
            metrics["rotation_error_deg"], metrics["translation_error_m"] = rot, tra
        rig = rig_for_extrinsic(base_rig.camera, T, base_rig) if cfg.extrinsic else base_rig
        rig_path = ctx.stage_dir / "rig.yaml"
        if marks is not None:
            # The mark travels with the extrinsic, so that every later reader warns.
            metrics["reliable"] = bool(marks["reliable"])
            write_rig_with_calibration(rig_path, rig, to_jsonable(marks))
            if marks["reliable"] is False:
                lines.append(f"**Unreliable:** {cfg.extrinsic} is marked reliable: false ("
                             + "; ".join(map(str, marks.get("unreliable_because") or []))
                             + "); passed on as the rig because allow_unreliable: true.")
        else:
            write_rig(rig_path, rig)
        calib_path = ctx.stage_dir / "calibration.yaml"
        atomic_write_text(calib_path, yaml.safe_dump(
            to_jsonable({**extrinsic_to_mapping(T), "mode": "check", "checked": what,
                         **(marks or {}), "check": metrics}), sort_keys=False))
        ctx.add_metrics(metrics)
        ctx.report("\n\n".join(lines))
        ctx.provide("rig", rig_path)
        ctx.provide("calibration", calib_path)

    def _check(self, ctx: StageContext, seq_dir: Path, T: np.ndarray, T_true: np.ndarray | None,
               metrics: dict[str, Any]) -> list[str]:
        import cv2

        from calibration.check import (
            SEEN_AXES,
            overlay,
            perturbed,
            project_scan,
            score_frames,
            sensitivity,
        )
        from calibration.pipeline import check_frames_from_sequence
        from toolkit.io.atomic import atomic_path

        frames, seq = check_frames_from_sequence(seq_dir, T, self.config.check_frames)
        camera = seq.rig.camera
        out = ctx.stage_dir / "check"
        out.mkdir(parents=True, exist_ok=True)

        def write(name: str, img: np.ndarray) -> str:
            with atomic_path(out / name) as tmp:
                cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            return name

        for k, f in enumerate(frames[:4]):
            write(f"overlay_{k}.png", overlay(f.image, project_scan(f.points, T, camera)))
        cfg = self.config
        source = ("the calibrated extrinsic" if cfg.mode == "calibrate" else cfg.extrinsic
                  or f"{seq_dir / 'rig.yaml'}")
        sc = sensitivity(frames, T, camera, 2.0, source=source)
        metrics["check_score"] = sc.score
        metrics["check_kind"] = sc.kind
        metrics["check_points"] = sc.n_points
        metrics["check_drop_at_2deg_max"] = max(sc.drop(k) for k in sc.perturbed)
        metrics["check_drop_at_2deg_min"] = min(sc.drop(k) for k in sc.perturbed)
        metrics["check_scores_rotated_2deg"] = dict(sc.perturbed)
        seen = SEEN_AXES[sc.kind]
        table = ["| extrinsic | score | change |", "|---|---|---|",
                 f"| checked | {sc.score:.3f} | |"]
        for k, v in sc.perturbed.items():
            note = "" if k[:2] in seen else " (not judged by this score)"
            table.append(f"| rotated {k} | {v:.3f} | {-sc.drop(k) * 100:+.0f} %{note} |")
        meaning = ("the fraction of projected lidar points whose depth agrees with the "
                   "depth map's within 3 %" if sc.kind == "depth" else
                   "the image edge strength at the lidar's range jumps over the image's "
                   "mean: 1 is chance")
        lines = [f"Check on {len(frames)} frames of the sequence ({sc.kind} score: "
                 f"{meaning}; {sc.n_points} projected points): {sc.score:.3f}.",
                 "\n".join(table)]
        # A side-by-side picture: the extrinsic (the true one when known) and the same turned
        # 2 degrees about the camera's vertical axis, the rotation a 2D scan sees best.
        ref = T if T_true is None else T_true
        wrong = perturbed(ref, 1, 2.0)
        pairs = []
        for k, f in enumerate(frames[:2]):
            pa = project_scan(f.points, ref, camera)
            # The same range colours in both panels, so that only the positions differ.
            lim = ((float(np.percentile(pa.range_m, 2)), float(np.percentile(pa.range_m, 98)))
                   if len(pa.range_m) else None)
            a = overlay(f.image, pa, lim)
            b = overlay(f.image, project_scan(f.points, wrong, camera), lim)
            for img, text in ((a, "true" if T_true is not None else "checked"),
                              (b, "rotated 2 deg (yaw)")):
                (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 1)
                cv2.rectangle(img, (4, 4), (16 + tw, 14 + th), (0, 0, 0), -1)
                cv2.putText(img, text, (10, 9 + th), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                            (255, 255, 255), 1, cv2.LINE_AA)
            pairs.append(write(f"overlay_vs_rotated_{k}.png", np.hstack([a, b])))
        if T_true is not None:
            same = np.allclose(T_true, T, atol=1e-12)
            s_true = sc.score if same else score_frames(frames, T_true, camera, sc.kind)[0]
            true_perturbed = dict(sc.perturbed) if same else sensitivity(
                frames, T_true, camera, 2.0, sc.kind).perturbed
            s_wrong = true_perturbed["ry+2deg"]
            metrics["check_score_true"] = s_true
            metrics["check_score_true_rotated_2deg"] = s_wrong
            # Does the score rank the true extrinsic above every 2-degree rotation of it?
            metrics["check_true_beats_rotated_2deg"] = bool(
                all(s_true > v for v in true_perturbed.values()))
            lines.append(f"Ground-truth extrinsic: score {s_true:.3f}; rotated 2 deg about "
                         f"the camera's vertical axis: {s_wrong:.3f} "
                         f"({(s_wrong - s_true) / max(abs(s_true), 1e-9) * 100:+.0f} %); "
                         "the true one scores above every 2-degree rotation: "
                         f"{'yes' if metrics['check_true_beats_rotated_2deg'] else 'no'}.")
        rel = ctx.stage_id
        lines += [f"![lidar points on the image coloured by range: left the "
                  f"{'true' if T_true is not None else 'checked'} extrinsic, right turned by 2 "
                  f"degrees]({rel}/check/{n})" for n in pairs]
        if self.config.time_offset:
            lines += self._time_offset(ctx, seq, out, metrics)
        return lines

    @staticmethod
    def _time_offset(ctx: StageContext, seq: Any, out: Path, metrics: dict[str, Any]) -> (
            list[str]):
        """The camera's stamp delay against the wheel odometry (``calibration.time_offset``);
        a recording it cannot judge says so and the stage goes on."""
        from calibration.time_offset import (
            TimeOffsetError,
            advice,
            applied_delay,
            measure,
            needs_correction,
            write_figure,
        )

        head = "**Camera time offset** (images stamped after they are taken): "
        traj = seq.odometry
        if traj is None:
            return [head + "not measured: the sequence has no wheel odometry (`python -m "
                    "calibration time-offset --trajectory` takes the slam2d trajectory)."]
        try:
            m = measure(seq.frames, seq.rig.camera, seq.rig.T_base_camera, traj,
                        "the wheel odometry", lambda it, total: ctx.progress(
                            it, total=total, description="camera rotations"))
        except TimeOffsetError as e:
            return [head + f"not measured: {e}."]
        res = m.result
        write_figure(str(out / "time_offset.png"), res, m.stamps, m.dyaw, traj)
        applied = applied_delay(seq)
        metrics["camera_delay_s"] = res.delay_s
        metrics["camera_delay_std_s"] = res.std_s
        metrics["camera_delay_reliable"] = res.reliable
        metrics["camera_delay_applied_at_conversion_s"] = applied
        ms, sd = res.delay_s * 1000, res.std_s * 1000
        text = (f"{ms:+.1f} ms (+- {sd:.1f} ms) against the wheel odometry's turning "
                f"({res.windows} windows of {res.frames_per_window} frames; yaw mismatch "
                f"{res.residual_at_zero_deg:.3f} -> {res.residual_deg:.3f} deg per window). ")
        if needs_correction(res):
            text += (f"**{advice(res, applied)}** Every stage places the lidar at the "
                     "image's stamp.")
        else:
            text += advice(res, applied)
        return [head + text, f"![yaw rates of the camera and the odometry, and the mismatch "
                             f"against the delay tried]({ctx.stage_id}/check/time_offset.png)"]
