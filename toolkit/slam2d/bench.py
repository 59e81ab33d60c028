"""Benchmarks of the 2D SLAM on the shipped real logs and simulated corridors.

    python -m toolkit.slam2d.bench killian|intel|aces|corridor|doors [--out DIR] [--set k=v ...]
        [--seeds N]

killian: scans + the sequential EDGE_SE2 odometry of killian.g2o; the Freiburg relations
metric on the relations whose two stamps are scans of the file (658). intel / aces: the
Radish logs scan-only; ATE after SE(2) alignment against the GMapping-corrected poses
stored in the log. corridor: a simulated drive down a 40 m featureless corridor and back
(8 m lidar, 3 % odometry error; ``toolkit.slam2d.corridor``), ATE against the true poses:
the degenerate case. doors: the same corridor with identical door niches every
``--door-spacing`` m (5), whose views repeat (a match one door off scores as well).
One corridor drive's ATE swings with its odometry noise (0.019-0.071 m over seeds 0-7 with
the defaults), so ``--seeds N`` drives seeds 0..N-1 and adds their ATE spread
(``ate_seeds``); the map and the other figures are seed 0's. Writes ``<out>/<log>.json``,
the map (PGM + YAML) and a PNG.
"""

from __future__ import annotations

import argparse
import difflib
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel, ValidationError

from toolkit.geometry import Trajectory, umeyama_alignment
from toolkit.io.atomic import atomic_write_json
from toolkit.io.occupancy import write_occupancy
from toolkit.io.yaml_file import load_yaml
from toolkit.recipe.schema import format_validation_error, read_yaml_value
from toolkit.slam2d.config import Slam2DConfig
from toolkit.slam2d.pipeline import grid_to_occupancy, run_slam
from toolkit.slam2d.plot import save_map_png

if TYPE_CHECKING:
    from toolkit.slam2d.corridor import CorridorDrive

LOGS = ("killian", "intel", "aces", "corridor", "doors")


def shared_data_dir() -> Path:
    """``$TOOLKIT_SHARED_DATA`` or ``../shared/data`` next to the repository."""
    env = os.environ.get("TOOLKIT_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2].parent / "shared" / "data"


def ate_se2(estimate: Trajectory, reference: Trajectory, tol: float = 1e-3) -> dict:
    """ATE (RMSE, mean, max of position errors, m) after the SE(2) alignment of the
    estimate onto the reference, over the estimate's stamps the reference covers (within
    ``tol`` s of its ends), the reference interpolated there: a ground truth on its own
    clock (motion capture at 100 Hz) scores every scan, not the few stamped within ``tol``
    of one of its samples."""
    keep = reference.covers(estimate.stamps, slack_s=tol)
    if keep.sum() < 3:
        raise ValueError(f"the reference covers {int(keep.sum())} of the estimate's "
                         f"{len(estimate)} stamps: at least 3 are needed for an ATE")
    est = estimate.positions[keep, :2]
    ref = reference.interpolate(estimate.stamps[keep], extrapolate_s=tol).positions[:, :2]
    R, t, _ = umeyama_alignment(est, ref)
    err = np.linalg.norm(est @ R.T + t - ref, axis=1)
    return {"ate_rmse_m": float(np.sqrt((err**2).mean())), "ate_mean_m": float(err.mean()),
            "ate_max_m": float(err.max()), "ate_poses": int(keep.sum())}


def _settings(data: object, label: str) -> Slam2DConfig:
    """``data`` validated as ``Slam2DConfig``; a ValueError of the recipe's one-line
    messages otherwise, each starting with ``label`` (the file or the --set that gave it)
    and naming the key, what it needs and what was given, instead of pydantic's dump."""
    try:
        return Slam2DConfig.model_validate(data)
    except ValidationError as exc:
        raise ValueError("\n".join(format_validation_error(exc, label, Slam2DConfig))) from None


def _apply_overrides(config: Slam2DConfig, sets: list[str]) -> Slam2DConfig:
    """``--set a.b=v`` on the settings. Keys are checked against the models' fields, not
    the dump: an option left out of the dump while off (``AddedOptions``) is settable.
    Validated once all are applied (a pair such as scan.min_range / max_range may be valid
    only together); an error names the --set options given."""
    data = config.model_dump()
    for item in sets:
        key, _, value = item.partition("=")
        node, model = data, config
        parts = key.split(".")
        for depth, p in enumerate(parts):
            if not isinstance(model, BaseModel) or p not in type(model).model_fields:
                known = list(type(model).model_fields) if isinstance(model, BaseModel) else []
                close = difflib.get_close_matches(p, known, n=1, cutoff=0.6)
                hint = f" (did you mean {close[0]!r}?)" if close else (
                    f"; settings here: {', '.join(known)}" if known else "")
                raise KeyError(f"--set {key}: unknown setting {p!r}{hint}")
            if depth < len(parts) - 1:
                node, model = node[p], getattr(model, p)
        node[parts[-1]] = read_yaml_value(value)  # as a recipe's --set reads it
    return _settings(data, " ".join(f"--set {item}" for item in sets)) if sets else config


def run_benchmark(name: str, out: Path, config: Slam2DConfig | None = None,
                  data_dir: Path | None = None, corridor_angle_deg: float = 0.0,
                  door_spacing_m: float = 5.0, seeds: int = 1) -> dict:
    """Run one log; write JSON, map and PNG under ``out``; return the figures.
    ``corridor_angle_deg``: the corridor's angle to the SLAM grid (corridor, doors);
    ``door_spacing_m``: the doors' spacing (doors only); ``seeds``: how many simulated
    drives (corridor, doors; seeds 0..seeds-1) to score, summarised in ``ate_seeds``."""
    from toolkit.eval.relations import read_relations, relations_metric, select_relations
    from toolkit.io.carmen import read_carmen, read_g2o

    if problem := _seeds_problem(name, seeds):
        raise ValueError(problem)
    data = data_dir or shared_data_dir()
    config = config or Slam2DConfig()
    out.mkdir(parents=True, exist_ok=True)
    t_read = time.perf_counter()
    figures: dict = {"log": name}
    reference: Trajectory | None = None
    if name == "killian":
        g2o = read_g2o(data / "slam2d" / "killian" / "killian.g2o.zip")
        scans, odom, T_bl = g2o.scans, g2o.odometry(), g2o.T_base_laser
        figures["input"] = "scans + sequential EDGE_SE2 odometry (corrected vertices unused)"
    elif name in ("intel", "aces"):
        log = read_carmen(data / "slam2d" / "radish" / f"{name}-corrected.log.gz")
        scans, odom, T_bl = log.scans, None, log.T_base_laser
        reference = log.reference()
        figures["input"] = "scans only (the log's GMapping poses are the reference)"
    elif name in ("corridor", "doors"):
        spacing = door_spacing_m if name == "doors" else 0.0
        drive = _drive(name, 0, corridor_angle_deg, door_spacing_m)
        scans, odom, T_bl, reference = drive.scans, drive.odometry, None, drive.truth
        what = (f"identical door niches every {spacing:g} m" if spacing
                else "without features")
        figures["input"] = (f"simulated: 40 m x 2 m corridor {what}, down and back, "
                            "8 m lidar, 0.1 m per scan, 3 % odometry error, "
                            f"{corridor_angle_deg:g} deg to the grid")
    else:
        raise ValueError(f"unknown log {name!r}; choose from {LOGS}")
    figures["read_s"] = round(time.perf_counter() - t_read, 3)
    figures["scans"] = len(scans)

    from rich.progress import track

    # Killian takes minutes: show how far the SLAM is (timings are per stage, unaffected).
    result = run_slam(scans, odom, T_bl, config,
                      progress=lambda it: track(it, total=len(scans), description=name,
                                                transient=True))
    figures["slam"] = result.metrics
    if name == "killian":
        rel = read_relations(data / "slam2d" / "killian" / "mit-killian.relations")
        scan_stamps = np.array([s.stamp for s in scans])
        sel = select_relations(rel, scan_stamps)
        from toolkit.eval.relations import Relations

        subset = Relations(rel.t1[sel], rel.t2[sel], rel.delta[sel])
        figures["relations"] = relations_metric(result.trajectory, subset)
        figures["relations"]["relations_in_file"] = len(rel)
        figures["relations"]["selection"] = "both stamps are scans of killian.g2o"
        dr = relations_metric(odom, subset)
        figures["odometry_relations"] = {k: v for k, v in dr.items() if "mean" in k}
    if reference is not None:
        figures["ate"] = ate_se2(result.trajectory, reference)
    if seeds > 1:
        figures["ate_seeds"] = _seed_spread(
            [figures["ate"]] + [_corridor_ate(name, seed, config, corridor_angle_deg,
                                              door_spacing_m) for seed in range(1, seeds)])

    occ = grid_to_occupancy(result.map)
    write_occupancy(out / f"{name}_map.yaml", occ)
    save_map_png(out / f"{name}_map.png", occ, result.trajectory.positions[:, :2],
                 title=f"{name}: {result.metrics['nodes']} nodes, "
                       f"{result.metrics['loop_closures']} loop closures")
    figures["config"] = config.model_dump()
    atomic_write_json(out / f"{name}.json", figures)
    return figures


def _seeds_problem(name: str, seeds: int) -> str | None:
    """Why ``seeds`` drives of ``name`` cannot be run (None: they can)."""
    if seeds < 1 or (seeds > 1 and name not in ("corridor", "doors")):
        return (f"seeds={seeds}: the corridor and doors drives take 1 or more seeds; "
                f"{name!r} is a recording, run it once (seeds=1)")
    return None


def _drive(name: str, seed: int, angle_deg: float,
           door_spacing_m: float) -> CorridorDrive:
    """The simulated drive of benchmark ``name`` (corridor, doors) with noise ``seed``."""
    from toolkit.slam2d.corridor import corridor_drive

    return corridor_drive(angle_deg=angle_deg, seed=seed,
                          door_spacing=door_spacing_m if name == "doors" else 0.0)


def _corridor_ate(name: str, seed: int, config: Slam2DConfig, angle_deg: float,
                  door_spacing_m: float) -> dict:
    from rich.progress import track

    drive = _drive(name, seed, angle_deg, door_spacing_m)
    result = run_slam(drive.scans, drive.odometry, None, config,
                      progress=lambda it: track(it, total=len(drive.scans),
                                                description=f"{name} seed {seed}",
                                                transient=True))
    return ate_se2(result.trajectory, drive.truth)


def _seed_spread(ates: list[dict]) -> dict:
    """Per-seed ATE RMSE / max (seed order) and the RMSE's median, mean, min and max."""
    rmse = np.array([a["ate_rmse_m"] for a in ates])
    return {"seeds": len(ates), "ate_rmse_m": rmse.tolist(),
            "ate_max_m": [a["ate_max_m"] for a in ates],
            "ate_rmse_median_m": float(np.median(rmse)), "ate_rmse_mean_m": float(rmse.mean()),
            "ate_rmse_min_m": float(rmse.min()), "ate_rmse_max_m": float(rmse.max())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m toolkit.slam2d.bench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", choices=LOGS)
    ap.add_argument("--out", type=Path, default=Path("runs/bench_slam2d"))
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a setting, e.g. --set loop_closure.min_score=0.6")
    ap.add_argument("--config", type=Path, help="YAML file of settings (Slam2DConfig)")
    ap.add_argument("--corridor-angle", type=float, default=0.0, metavar="DEG",
                    help="corridor, doors: its angle to the SLAM grid (walls as stair-steps)")
    ap.add_argument("--door-spacing", type=float, default=5.0, metavar="M",
                    help="doors: metres between the door niches (default: 5)")
    ap.add_argument("--seeds", type=int, default=1, metavar="N",
                    help="corridor, doors: score drives of seeds 0..N-1 (default: 1); the "
                         "ATE's spread lands in ate_seeds")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    config = Slam2DConfig()
    try:
        if args.config:
            config = _settings(
                load_yaml(args.config, ValueError, "settings file not found (--config)") or {},
                str(args.config))
        config = _apply_overrides(config, args.set)
    except (ValueError, KeyError) as e:  # pydantic's ValidationError is a ValueError
        print(f"error: {e.args[0] if isinstance(e, KeyError) else e}", file=sys.stderr)
        return 2
    if not args.door_spacing > 0:
        print(f"error: --door-spacing must be > 0 m, got {args.door_spacing:g}",
              file=sys.stderr)
        return 2
    if problem := _seeds_problem(args.log, args.seeds):
        print(f"error: --{problem}", file=sys.stderr)
        return 2
    figures = run_benchmark(args.log, args.out, config, corridor_angle_deg=args.corridor_angle,
                            door_spacing_m=args.door_spacing, seeds=args.seeds)
    show = {k: v for k, v in figures.items() if k != "config"}
    json.dump(show, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
