"""What the runner's per-file output digests cost on a stage's folder.

The folder: a synthetic finished stage (N files of 1 KiB, all different, 1000 to a
subfolder: an hour's ``simulate/`` at 10 Hz holds ~110,000), or a copy (``cp -a``) of a
finished stage's folder of a run (``runs/quickstart/depth``). Times, in this process:

- ``finish``: the finish-time read (``_digest_output``: content token, manifest, each
  file's mtime and SHA-256) and the marker written with them, as ``digest_outputs`` does;
- ``first_check``: ``cp -r`` of the folder (new mtimes), then ``_read_marker`` on the copy
  (every file hashed, the new mtimes stored);
- ``next_check``: ``_read_marker`` again (nothing hashed).

Prints one JSON object: seconds per step, files hashed, the marker's bytes and the
process's peak-RSS growth over each step (``ru_maxrss``: growth above every earlier
step's peak, so a lower bound for the later steps; run one size per process).

    python benchmarks/runner_digest_cost.py 120000 --work /tmp/digest_cost
    python benchmarks/runner_digest_cost.py runs/quickstart/depth --work /tmp/digest_cost
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

from toolkit.recipe import runner


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def make_stage(folder: Path, n: int) -> None:
    """The output of a stage: ``sequence/`` of ``n`` different 1 KiB files."""
    shutil.rmtree(folder, ignore_errors=True)
    out = folder / "sequence"
    for i in range(n):
        f = out / f"{i // 1000:03d}" / f"{i:07d}.bin"
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(i.to_bytes(8, "little") * 128)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", help="how many 1 KiB files, or a finished stage's folder")
    parser.add_argument("--work", type=Path, default=Path("digest_cost"),
                        help="scratch folder (emptied first)")
    args = parser.parse_args(argv)
    src, copy = args.work / "stage", args.work / "stage_copy"
    if args.source.isdigit():
        make_stage(src, int(args.source))
        provides = {"sequence": "sequence"}
    else:
        stage = Path(args.source)
        if not (stage / runner.STAGE_FILE).is_file():
            raise SystemExit(f"{stage} holds no {runner.STAGE_FILE}: not a finished stage")
        shutil.rmtree(src, ignore_errors=True)
        src.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(["cp", "-a", str(stage), str(src)], check=True)
        provides = json.loads((src / runner.STAGE_FILE).read_text())["provides"]
    result: dict[str, Any] = {"source": args.source}

    rss, t0 = _rss_mib(), time.perf_counter()
    outputs = {name: runner._digest_output(src / rel) for name, rel in provides.items()}
    marker = {"key": "k", "token": "t", "stage": "measured", "provides": provides,
              "output_tokens": {n: o[0] for n, o in outputs.items()},
              "manifest": {n: o[1] for n, o in outputs.items()},
              "manifest_digests": {n: o[2] for n, o in outputs.items()}}
    runner.atomic_write_json(src / runner.STAGE_FILE, marker, fsync=True, compact=True)
    result["files"] = sum(len(o[1]) for o in outputs.values())  # hidden files left out
    result["finish_seconds"] = round(time.perf_counter() - t0, 3)
    result["finish_rss_growth_mib"] = round(_rss_mib() - rss, 1)
    result["marker_bytes"] = (src / runner.STAGE_FILE).stat().st_size

    shutil.rmtree(copy, ignore_errors=True)
    subprocess.run(["cp", "-r", str(src), str(copy)], check=True)
    hashed: list[Path] = []
    real = runner._file_sha256

    def counting(path: Path) -> str:
        hashed.append(path)
        return real(path)

    runner._file_sha256 = counting  # type: ignore[assignment]
    try:
        for step in ("first_check", "next_check"):
            hashed.clear()
            rss, t0 = _rss_mib(), time.perf_counter()
            stored, reason = runner._read_marker(copy, "k", tuple(provides))
            result[f"{step}_seconds"] = round(time.perf_counter() - t0, 3)
            result[f"{step}_rss_growth_mib"] = round(_rss_mib() - rss, 1)
            result[f"{step}_files_hashed"] = len(hashed)
            if stored is None:
                raise SystemExit(f"the copy was not taken as finished: {reason}")
    finally:
        runner._file_sha256 = real  # type: ignore[assignment]
    result["marker_bytes_after_check"] = (copy / runner.STAGE_FILE).stat().st_size
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
