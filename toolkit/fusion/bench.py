"""Fusion throughput at 640x480, network and file reading excluded.

    python -m toolkit.fusion.bench --sequence PATH --frames 150 --out runs/bench/fusion.json
    python -m toolkit.fusion.bench --recipe recipes/paper_benchmark.yaml --stage fuse_net

Each configuration runs ``--repeat`` times (3) and the fastest run's figures are reported,
with every run's frames/s beside them.

Predictions come from the ``simulated`` backend (computed before the clock starts) on a
simulator sequence, or on the synthetic box room rendered at 640x480 when no sequence is
given: preset ``paper``, or ``scale_only`` for a stage with ``ramp_threshold`` (smooth
predictions, as a network's: the ramp test drops most of ``paper``'s noisy pixels);
``--preset`` chooses. The timed part is what the ``fuse`` stage does per frame - lidar
projection, scale estimation, the exposure gains (``exposure: gain``), scaling, shape
correction (``--refine``), flying-pixel filtering, back-projection, voxel integration (and
the consensus TSDF, ``--consensus``) - plus, separately, the end-of-run work (carving
moving obstacles, outlier removal).

``--recipe`` with ``--stage`` takes every fusion setting from that ``fuse`` stage of the
recipe (its refine grid and gates, smoothing, consensus, ...), so a recipe's row is timed
as it runs; ``--scale``, ``--stride``, ``--refine`` and ``--consensus`` given beside them
override the stage's values.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

# OpenBLAS's idle threads spin ~0.1 s after each product it splits (toolkit.recipe's
# __main__ says more): as in the fuse stage, before numpy loads it.
os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")

import numpy as np  # noqa: E402

from toolkit.cli_types import positive_int  # noqa: E402
from toolkit.depth.simulated import PRESETS  # noqa: E402
from toolkit.errors import InputError
from toolkit.fusion.exposure import frames_to_solve, solve_exposure  # noqa: E402
from toolkit.fusion.pipeline import FusionConfig  # noqa: E402

if TYPE_CHECKING:
    from toolkit.sensors import Sequence


def run_bench(seq_path: Path, frames: int, method: str = "clustered", stride: int = 2,
              refine: str = "none", consensus: bool = False, repeat: int = 1,
              config: FusionConfig | None = None, preset: str = "paper") -> dict:
    """Figures of the best of ``repeat`` timed runs (each with a fresh fusion) and every
    run's frames/s: on a shared machine neighbours only ever slow a run down, so the
    fastest is the least disturbed estimate (what ``timeit`` reports too).

    ``config``: every fusion setting (``method``, ``stride``, ``refine`` and ``consensus``
    are then ignored); None builds one from those four and the defaults. ``preset``: the
    ``simulated`` backend's."""
    from toolkit.depth.simulated import SimulatedDepthBackend, SimulatedDepthParams
    from toolkit.deskew import deskew_sequence
    from toolkit.fusion.pipeline import pose_arrays, scans_covered
    from toolkit.io.sequence import read_sequence

    seq = read_sequence(seq_path)
    problem = ground_truth_problem(seq)
    if problem:
        raise InputError(f"{seq_path}: {problem}")
    gt = seq.groundtruth
    n = min(frames, len(seq.frames))
    idx = np.arange(n)  # consecutive frames, as the stage sees them
    backend = SimulatedDepthBackend(SimulatedDepthParams(**PRESETS[preset]))
    preds, imgs = {}, {}
    for i in idx:
        imgs[i] = seq.frames[i].image
        preds[i] = backend.predict(imgs[i], gt_depth=gt.depth(i), frame_index=int(i))
    seq = deskew_sequence(seq, gt.poses_base)
    fp, sp, _ = pose_arrays(seq, gt.poses_base)
    covered = scans_covered(seq, gt.poses_base)
    if config is None:
        config = FusionConfig(scale=method, stride=stride, refine=refine,  # type: ignore[arg-type]
                              consensus=consensus)
    runs = [_timed_run(seq, fp, sp, covered, idx, preds, imgs, config)
            for _ in range(max(1, repeat))]
    best = max(runs, key=lambda r: r["fps_including_finish"])
    h, w = seq.rig.camera.height, seq.rig.camera.width
    return {
        "sequence": str(seq_path), "image": f"{w}x{h}", "frames": int(n),
        "scale": config.scale, "refine": config.refine, "consensus": config.consensus,
        "exposure": config.exposure, "preset": preset,
        "stride": config.stride, "repeat": len(runs),
        "fusion_config": config.model_dump(mode="json"),
        **best,
        "runs_fps_per_frame_work": [r["fps_per_frame_work"] for r in runs],
        "runs_fps_including_finish": [r["fps_including_finish"] for r in runs],
    }


def ground_truth_problem(seq: Sequence) -> str | None:
    """Why ``seq`` cannot be benchmarked (None: it can). The predictions are made from its
    ground-truth depth and the map is built at its ground-truth poses; a recording without
    them (a user's own bag) failed with a bare AttributeError or TypeError deep inside."""
    gt = seq.groundtruth
    missing = [what for what, absent in (
        ("ground-truth poses (groundtruth/poses_base.tum)", gt is None or gt.poses_base is None),
        ("ground-truth depth (frames.csv's gt_depth)", gt is None or gt.depth_paths is None))
        if absent]
    if not missing:
        return None
    return (f"the fusion bench needs {' and '.join(missing)}, which this sequence lacks: give "
            "a simulator sequence (a recipe's simulate stage), or leave --sequence out for "
            "the synthetic box room")


def _timed_run(seq: object, fp: np.ndarray, sp: np.ndarray, covered: np.ndarray,
               idx: np.ndarray, preds: dict, imgs: dict, cfg: FusionConfig) -> dict:
    from toolkit.fusion.pipeline import Fusion

    n = len(idx)
    fusion = Fusion(seq, cfg, fp, sp, scan_covered=covered)  # type: ignore[arg-type]
    fusion.frame_pairs(int(idx[0]), preds[idx[0]])  # warm caches outside the clock
    # Wall clock and CPU time: on a shared machine the wall clock measures the neighbours.
    t0, c0 = time.perf_counter(), time.process_time()
    pairs = {i: fusion.frame_pairs(int(i), preds[i]) for i in idx}
    sm = fusion.smooth([pairs[i].estimate for i in idx], [pairs[i] for i in idx],
                       preds[idx[0]].is_disparity)
    te, ce = time.perf_counter(), time.process_time()
    used = [(j, int(i)) for j, i in enumerate(idx) if sm.used[j]]
    if not used:
        raise ValueError(f"no frame of the {n} was fused (none got a scale): a throughput of "
                         "nothing; check the recording's lidar pairs (min_pairs)")
    # Rates per fused frame, as the fuse stage counts them (Table II): frames left out
    # by the scale smoothing are not fusion work.
    nu = len(used)
    gains: dict[int, np.ndarray] = {}
    if cfg.exposure == "gain" and used:
        opts = cfg.exposure_options()
        at, cells = frames_to_solve(len(used), opts)
        g, _, _ = solve_exposure(
            (fusion.exposure_observations(used[k][1], preds[used[k][1]].as_depth(
                sm.scale[used[k][0]], sm.shift[used[k][0]]), imgs[used[k][1]], cells)
             for k in at), at, len(used), opts)
        gains = {i: g[k] for k, (_, i) in enumerate(used)}
    t1, c1 = time.perf_counter(), time.process_time()
    points = 0
    for j, i in used:
        depth, _ = fusion.refine(i, preds[i].as_depth(sm.scale[j], sm.shift[j]), pairs[i])
        points += fusion.integrate(i, depth, imgs[i], gain=gains.get(i))
    t2, c2 = time.perf_counter(), time.process_time()
    raw, masks = fusion.finish()
    t3, c3 = time.perf_counter(), time.process_time()
    return {
        "frames": n, "frames_fused": nu,
        "points_per_frame": points / nu, "map_voxels": len(raw),
        "scale_ms_per_frame": 1000 * (te - t0) / n,  # every frame gets a scale estimate
        "exposure_ms_per_frame": 1000 * (t1 - te) / nu,
        "integrate_ms_per_frame": 1000 * (t2 - t1) / nu,
        "finish_s": t3 - t2, "finish_ms_per_frame": 1000 * (t3 - t2) / nu,
        "fps_per_frame_work": nu / (t2 - t0), "fps_including_finish": nu / (t3 - t0),
        "cpu_scale_ms_per_frame": 1000 * (ce - c0) / n,
        "cpu_exposure_ms_per_frame": 1000 * (c1 - ce) / nu,
        "cpu_integrate_ms_per_frame": 1000 * (c2 - c1) / nu,
        "cpu_finish_s": c3 - c2,
        "cpu_fps_per_frame_work": nu / (c2 - c0), "cpu_fps_including_finish": nu / (c3 - c0),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m toolkit.fusion.bench",
                                 description="fusion throughput (network excluded)")
    ap.add_argument("--sequence", type=Path, default=None,
                    help="a simulated sequence folder (its ground-truth depth is made into "
                         "monocular-like predictions); default: a synthetic box room")
    ap.add_argument("--frames", type=positive_int, default=300,
                    help="frames fused per timed run (default %(default)s)")
    ap.add_argument("--scale", default=None, choices=["ratio", "clustered", "robust"],
                    help="scale estimator (default: the --stage's, else clustered)")
    ap.add_argument("--stride", type=positive_int, default=None,
                    help="pixel stride of the map (default: the --stage's, else 2)")
    ap.add_argument("--refine", default=None, choices=["none", "floor_lidar", "lidar"],
                    help="shape correction (default: the --stage's, else none)")
    ap.add_argument("--consensus", action=argparse.BooleanOptionalAction, default=None,
                    help="multi-view consensus filter (default: the --stage's, else off)")
    ap.add_argument("--exposure", choices=["none", "gain"], default=None,
                    help="exposure gains solved and divided out (default: the --stage's, "
                    "else gain)")
    ap.add_argument("--preset", default=None, choices=sorted(PRESETS),
                    help="the simulated predictions' preset (default paper; scale_only for a "
                         "stage with ramp_threshold)")
    ap.add_argument("--recipe", type=Path, default=None,
                    help="take the fusion settings from a fuse stage of this recipe")
    ap.add_argument("--stage", default=None, help="id of that fuse stage (with --recipe)")
    ap.add_argument("--repeat", type=positive_int, default=3,
                    help="timed runs; the figures are the fastest run's")
    ap.add_argument("--out", type=Path, default=Path("runs/bench/fusion.json"),
                    help="JSON figures written here, replacing the file (default "
                         "%(default)s, under the current folder)")
    a = ap.parse_args(argv)
    if a.out.is_dir():
        ap.error(f"--out {a.out} is a folder; give the JSON file to write")
    if a.sequence is not None and not (a.sequence / "meta.yaml").is_file():
        ap.error(f"--sequence {a.sequence}: no sequence folder (meta.yaml) there")
    if a.sequence is not None:
        from toolkit.io.sequence import read_sequence

        problem = ground_truth_problem(read_sequence(a.sequence))
        if problem:
            ap.error(f"--sequence {a.sequence}: {problem}")
    if (a.recipe is None) != (a.stage is None):
        ap.error("--recipe and --stage go together: the recipe file and the id of its fuse "
                 "stage (for example --recipe recipes/paper_benchmark.yaml --stage fuse_net)")
    config = _config_from(a, ap)
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        seq = a.sequence
        if seq is None:
            from toolkit.fusion.synthetic import write_box_room

            seq = write_box_room(Path(tmp) / "box", n_frames=min(a.frames, 60), width=640,
                                 height=480)
        preset = a.preset or ("scale_only" if config.ramp_threshold > 0 else "paper")
        res = run_bench(seq, a.frames, repeat=a.repeat, config=config, preset=preset)
    if a.recipe is not None:
        res.update({"recipe": str(a.recipe), "stage": a.stage})
    res.update({"cores": os.cpu_count(), "loadavg_before": load0,
                "loadavg_after": os.getloadavg()})
    for k, v in res.items():
        print(f"{k}: {v}")
    from toolkit.io.atomic import atomic_write_json

    atomic_write_json(a.out, res)
    return 0


def _config_from(a: argparse.Namespace, ap: argparse.ArgumentParser) -> FusionConfig:
    """The fusion settings: the recipe stage's (or the defaults), then the flags given."""
    flags = {k: v for k, v in (("scale", a.scale), ("stride", a.stride),
                               ("refine", a.refine), ("consensus", a.consensus),
                               ("exposure", a.exposure))
             if v is not None}
    base: dict = {}
    if a.recipe is not None:
        from toolkit.fusion.stage import FuseConfig
        from toolkit.recipe.schema import RecipeError, load_recipe

        try:
            recipe = load_recipe(a.recipe)
            spec = recipe.stages[recipe.index_of(a.stage, "--stage")]
        except RecipeError as exc:
            ap.error(str(exc))
        if not isinstance(spec.config, FuseConfig):
            fuse_ids = [s.id for s in recipe.stages if isinstance(s.config, FuseConfig)]
            ap.error(f"--stage {a.stage}: a {spec.type} stage of {a.recipe}, not a fuse stage; "
                     f"its fuse stages: {', '.join(fuse_ids) or 'none'}")
        base = {k: getattr(spec.config, k) for k in FusionConfig.model_fields}
    return FusionConfig(**{**base, **flags})


if __name__ == "__main__":
    raise SystemExit(main())
