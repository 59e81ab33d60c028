"""``python -m calibration``: end to end on a rendered capture, and the errors users see."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration.cli import main
from calibration.extrinsic import transform_error
from calibration.synthetic import _rays, board_outline, make_capture, write_capture
from toolkit.io.depth import write_depth
from toolkit.io.sequence import SequenceWriter, read_rig
from toolkit.sensors import LaserScan, Rig

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    cap = make_capture(8, seed=11)
    out = write_capture(cap, tmp_path_factory.mktemp("capture"))
    return out, cap


def _args(cap_dir: Path, *extra: str) -> list[str]:
    return ["extrinsic", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
            "--camera", str(cap_dir / "camera.yaml"), "--board", "11x8", "--square", "0.05",
            *extra]


def test_help_of_every_command() -> None:
    for cmd in ([], ["intrinsics"], ["extrinsic"], ["check"]):
        r = subprocess.run([sys.executable, "-m", "calibration", *cmd, "--help"], cwd=ROOT,
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and "usage: python -m calibration" in r.stdout


def test_help_names_where_output_goes_by_default(capsys: pytest.CaptureFixture[str]) -> None:
    """intrinsics wrote camera.yaml into the current folder (check and time-offset their
    folders) while --help said only "camera YAML to write" / "output folder"."""
    helps = {}
    for cmd in ("intrinsics", "check", "time-offset"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        helps[cmd] = " ".join(capsys.readouterr().out.split())
    assert "(default: camera.yaml, in the current folder)" in helps["intrinsics"]
    assert "(default: calibration_check)" in helps["check"]
    assert "(default: time_offset)" in helps["time-offset"]


def test_extrinsic_end_to_end(capture: tuple[Path, object], tmp_path: Path,
                              capsys: pytest.CaptureFixture[str]) -> None:
    cap_dir, cap = capture
    rc = main(_args(cap_dir, "--out", str(tmp_path / "rig.yaml"), "--json",
                    str(tmp_path / "r.json"), "--overlays", str(tmp_path / "ov"), "--no-loo"))
    assert rc == 0
    out = capsys.readouterr().out
    assert "T_camera_laser (p_camera_optical = T @ p_laser)" in out
    rig = read_rig(tmp_path / "rig.yaml")  # the toolkit's own reader takes it
    rot, tra = transform_error(rig.T_camera_laser, cap.T_camera_laser)  # type: ignore[attr-defined]
    assert rot < 0.5 and tra < 0.01
    d = yaml.safe_load((tmp_path / "rig.yaml").read_text())
    assert "maps laser points into the camera" in d["direction"]
    assert d["tf"]["parent"] == "camera_optical" and d["tf"]["child"] == "laser"
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["views_used"] == 8 and res["residual_rms_m"] < 0.012
    # 1 cm of lidar noise, measured: the 2 / 3 cm bands it always had.
    assert res["lidar_range_noise_m"] == pytest.approx(0.01, rel=0.1)
    assert res["board_line_band_m"] == pytest.approx(0.02, rel=0.1)
    assert "lidar range noise 10." in out and "(measured)" in out
    assert len(list((tmp_path / "ov").glob("*_overlay.png"))) == 8
    # The written extrinsic is accepted back by check (rig with T_camera_laser).
    rc = main(["check", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
               "--camera", str(cap_dir / "camera.yaml"), "--rig", str(tmp_path / "rig.yaml"),
               "--out", str(tmp_path / "chk")])
    assert rc == 0
    chk = json.loads((tmp_path / "chk" / "check.json").read_text())
    assert chk["kind"] == "edges" and len(chk["overlays"]) == 8
    # That rig holds the camera: --camera is not needed beside it (it was refused).
    rc = main(["check", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
               "--rig", str(tmp_path / "rig.yaml"), "--out", str(tmp_path / "chk2")])
    assert rc == 0
    again = json.loads((tmp_path / "chk2" / "check.json").read_text())
    assert again["score"] == chk["score"]
    capsys.readouterr()
    rc = main(["check", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
               "--extrinsic", str(tmp_path / "rig.yaml"), "--out", str(tmp_path / "chk3")])
    assert rc == 2 and "missing --camera" in capsys.readouterr().err


def test_extrinsic_is_deterministic(capture: tuple[Path, object], tmp_path: Path) -> None:
    """Same input, same output: RANSAC is seeded and nothing depends on the clock."""
    cap_dir, _ = capture
    for k in range(2):
        assert main(_args(cap_dir, "--json", str(tmp_path / f"r{k}.json"), "--no-loo")) == 0
    a, b = (json.loads((tmp_path / f"r{k}.json").read_text()) for k in range(2))
    assert a["T_camera_laser"] == b["T_camera_laser"]
    assert a["residual_rms_m"] == b["residual_rms_m"]


def test_intrinsics_command(capture: tuple[Path, object], tmp_path: Path) -> None:
    cap_dir, cap = capture
    rc = main(["intrinsics", "--images", str(cap_dir / "images"), "--board", "11x8", "--square",
               "0.05", "--model", "radial", "--out", str(tmp_path / "cam.yaml")])
    assert rc == 0
    d = yaml.safe_load((tmp_path / "cam.yaml").read_text())
    true = cap.camera  # type: ignore[attr-defined]
    assert abs(d["fx"] / true.fx - 1) < 0.01 and abs(d["cx"] - true.cx) < 5
    assert d["calibration"]["rms_px"] < 0.3 and d["calibration"]["images_used"] == 8
    # A square size in millimetres is refused with the fix, and the file is not written.
    rc = main(["intrinsics", "--images", str(cap_dir / "images"), "--board", "11x8", "--square",
               "50", "--model", "radial", "--out", str(tmp_path / "mm.yaml")])
    assert rc == 2 and not (tmp_path / "mm.yaml").exists()


def test_sequence_folder_input(capture: tuple[Path, object], tmp_path: Path) -> None:
    """The same views as a sequence folder (images + scans.npz + rig.yaml)."""
    cap_dir, cap = capture
    w = SequenceWriter(tmp_path / "seq", Rig(cap.camera), name="calib")  # type: ignore
    images = sorted((cap_dir / "images").glob("*.png"))
    for p in images:
        w.add_frame(int(p.stem) * 1e-9, None, image_path=p)  # type: ignore[arg-type]
    step = np.radians(0.25)
    for v in cap.views:  # type: ignore[attr-defined]
        r = np.linalg.norm(v.scan_points, axis=1)
        w.add_scan(LaserScan(v.stamp + cap.scan_dt, r, -np.radians(135.0), step))  # type: ignore
    w.close()
    rc = main(["extrinsic", "--sequence", str(tmp_path / "seq"), "--board", "11x8", "--square",
               "0.05", "--json", str(tmp_path / "r.json"), "--no-loo"])
    assert rc == 0
    T = np.array(json.loads((tmp_path / "r.json").read_text())["T_camera_laser"])
    rot, tra = transform_error(T, cap.T_camera_laser)  # type: ignore[attr-defined]
    assert rot < 0.5 and tra < 0.01


def test_bad_inputs_give_clear_errors(capture: tuple[Path, object], tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    cap_dir, _ = capture
    # No board anywhere (wrong grid size given), with a hint at the right one.
    assert main(_args(cap_dir)[:-4] + ["--board", "12x9", "--square", "0.05"]) == 2
    err = capsys.readouterr().err
    assert "no 12x9 checkerboard" in err and "--board 11x8" in err
    # Unpaired scans: the images and their nearest scans are named, and the fix.
    assert main(_args(cap_dir, "--max-dt", "0.001")) == 2
    err = capsys.readouterr().err
    assert "no scan within 1 ms" in err and ".png: nearest scan 12.0 ms away" in err
    assert "--max-dt" in err and "--skip-unpaired" in err
    # A camera YAML for another resolution.
    cam = yaml.safe_load((cap_dir / "camera.yaml").read_text())
    cam["width"], cam["height"] = 1280, 960
    (tmp_path / "cam.yaml").write_text(yaml.safe_dump(cam))
    args = _args(cap_dir)
    args[args.index("--camera") + 1] = str(tmp_path / "cam.yaml")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "image is 640x480" in err and "width/height say 1280x960" in err
    # A camera YAML missing a field.
    del cam["fx"]
    (tmp_path / "cam2.yaml").write_text(yaml.safe_dump(cam))
    args[args.index("--camera") + 1] = str(tmp_path / "cam2.yaml")
    assert main(args) == 2
    assert "cam2.yaml: missing field" in capsys.readouterr().err
    # An empty scan folder.
    (tmp_path / "empty").mkdir()
    args = _args(cap_dir)
    args[args.index("--scans") + 1] = str(tmp_path / "empty")
    assert main(args) == 2
    assert "no scan files" in capsys.readouterr().err


def test_skip_unpaired_uses_the_rest(capture: tuple[Path, object], tmp_path: Path) -> None:
    cap_dir, _ = capture
    scans = tmp_path / "lasers"
    shutil.copytree(cap_dir / "lasers", scans)
    for p in sorted(scans.glob("*.pcd"))[:2]:
        p.unlink()
    args = _args(cap_dir, "--skip-unpaired", "--no-loo", "--json", str(tmp_path / "r.json"))
    args[args.index("--scans") + 1] = str(scans)
    assert main(args) == 0
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["views_used"] == 6 and len(res["images_skipped"]) == 2


def test_extrinsic_overlays_of_a_rerun_leave_no_stale_ones(
        capture: tuple[Path, object], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """extrinsic --overlays DIR kept an earlier run's overlays of pairs a rerun does not
    have, looking current beside the new ones (no listing to clean by): now overlays.json
    lists what a run wrote, and the next run removes those of its listing it does not
    write again. Files no listing names (a user's, of the same pattern too) stay."""
    cap_dir, _ = capture
    ov = tmp_path / "ov"
    ov.mkdir()
    (ov / "mine_overlay.png").write_bytes(b"a user's")
    assert main(_args(cap_dir, "--no-loo", "--overlays", str(ov))) == 0
    first = [f"{p.stem}_overlay.png" for p in sorted((cap_dir / "images").glob("*.png"))]
    said = capsys.readouterr().out
    scans = tmp_path / "lasers"
    shutil.copytree(cap_dir / "lasers", scans)
    for p in sorted(scans.glob("*.pcd"))[:3]:
        p.unlink()
    args = _args(cap_dir, "--skip-unpaired", "--no-loo", "--overlays", str(ov))
    args[args.index("--scans") + 1] = str(scans)
    assert main(args) == 0
    assert sorted(p.name for p in ov.glob("*_overlay.png")) == sorted(
        ["mine_overlay.png", *first[3:]])
    assert sorted(p.name for p in ov.iterdir()) == sorted(
        ["overlays.json", "mine_overlay.png", *first[3:]])
    assert json.loads((ov / "overlays.json").read_text())["overlays"] == first[3:]
    # The file no listing names is counted, so that an older version's overlays are not
    # taken for this run's.
    assert "also holds 1 overlay(s) this run did not write" in said
    assert (ov / "mine_overlay.png").read_bytes() == b"a user's"


def _renamed(src: Path, dst: Path, scale: int) -> Path:
    """A copy of a capture folder with the nanosecond file names divided by ``scale``."""
    for sub in ("images", "lasers"):
        (dst / sub).mkdir(parents=True)
        for p in (src / sub).iterdir():
            shutil.copy(p, dst / sub / f"{round(int(p.stem) / scale)}{p.suffix}")
    shutil.copy(src / "camera.yaml", dst / "camera.yaml")
    return dst


def test_millisecond_file_names(capture: tuple[Path, object], tmp_path: Path,
                                capsys: pytest.CaptureFixture[str]) -> None:
    """13-digit names are milliseconds: the scans stay 12 ms from their images (read as
    nanoseconds they were 12 ns away and any offset passed)."""
    cap_dir, _ = capture
    ms = _renamed(cap_dir, tmp_path / "ms", 1_000_000)
    args = [a.replace(str(cap_dir), str(ms)) for a in _args(cap_dir, "--no-loo")]
    assert main([*args, "--max-dt", "0.005"]) == 2
    assert ".png: nearest scan 12.0 ms away" in capsys.readouterr().err
    assert main(args) == 0
    assert main([*args, "--stamp-unit", "ns", "--max-dt", "0.005"]) == 0  # told: ns
    # Centiseconds (12 digits) name no unit by themselves.
    cs = _renamed(cap_dir, tmp_path / "cs", 10_000_000)
    assert main([a.replace(str(cap_dir), str(cs)) for a in _args(cap_dir, "--no-loo")]) == 2
    assert "12 digits" in capsys.readouterr().err


def test_too_few_views_and_square_in_millimetres(capture: tuple[Path, object], tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    cap_dir, _ = capture
    few = tmp_path / "few"
    for sub in ("images", "lasers"):
        (few / sub).mkdir(parents=True)
        for p in sorted((cap_dir / sub).iterdir())[:3]:
            shutil.copy(p, few / sub / p.name)
    args = [a.replace(str(cap_dir / "images"), str(few / "images"))
            .replace(str(cap_dir / "lasers"), str(few / "lasers")) for a in _args(cap_dir)]
    assert main([*args, "--out", str(tmp_path / "rig.yaml")]) == 2
    err = capsys.readouterr().err
    # "only 3 of the 3" read as a garbled count
    assert "found in all 3 images" in err and "at least 4 views" in err
    assert "capture more views" in err and not (tmp_path / "rig.yaml").exists()
    args = _args(cap_dir, "--no-loo")
    args[args.index("--square") + 1] = "50"
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--square 50" in err and "in metres" in err and "--square 0.05?" in err


def test_untilted_boards_print_unreliable(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    cap = make_capture(6, seed=3, min_tilt_deg=0.0, max_tilt_deg=0.01)
    cap_dir = write_capture(cap, tmp_path / "cap")
    # estimated but unreliable: exit 3, so that a script does not go on with it
    assert main(_args(cap_dir, "--no-loo", "--json", str(tmp_path / "r.json"))) == 3
    out = capsys.readouterr().out
    assert "UNRELIABLE: the 6 board normals all lie within" in out
    assert "RESULT UNRELIABLE" in out.splitlines()[-2]  # last before "wrote"
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["reliable"] is False and res["board_normal_spread_deg"] < 3.0


def _board_depth_maps(cap: object, cap_dir: Path, out: Path) -> None:
    """Exact depth of the board plane per image (0 off the board), named by image stem."""
    camera = cap.camera  # type: ignore[attr-defined]
    rays = _rays(camera, 1)  # [H*W, 3], z = 1: the distance along a ray is the depth
    lo, hi = board_outline(cap.board, 0.08)  # type: ignore[attr-defined]
    out.mkdir()
    for v in cap.views:  # type: ignore[attr-defined]
        R, t = v.T_camera_board[:3, :3], v.T_camera_board[:3, 3]
        lam = (R[:, 2] @ t) / (rays @ R[:, 2])
        local = (rays * lam[:, None] - t) @ R
        on = (lam > 0) & np.all((local[:, :2] >= lo) & (local[:, :2] <= hi), axis=1)
        depth = np.where(on, lam, 0.0).reshape(camera.height, camera.width)
        write_depth(out / f"{round(v.stamp * 1e9)}.npy", depth)


def test_check_with_depth_maps_on_image_folders(capture: tuple[Path, object], tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    cap_dir, cap = capture
    rig = tmp_path / "true.yaml"
    rig.write_text(yaml.safe_dump({"T_camera_laser": cap.T_camera_laser.tolist()}))  # type: ignore
    base = ["check", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
            "--camera", str(cap_dir / "camera.yaml"), "--extrinsic", str(rig), "--out",
            str(tmp_path / "chk")]
    assert main([*base, "--score", "depth"]) == 2  # once a bare AssertionError
    assert "--depth DIR" in capsys.readouterr().err
    assert main([*base, "--depth", str(tmp_path / "missing")]) == 2  # once silently ignored
    assert "missing: depth folder (--depth) not found" in capsys.readouterr().err
    _board_depth_maps(cap, cap_dir, tmp_path / "depth")
    assert main([*base, "--depth", str(tmp_path / "depth")]) == 0
    chk = json.loads((tmp_path / "chk" / "check.json").read_text())
    # The true extrinsic puts the board's scan points at the board's depth.
    assert chk["kind"] == "depth" and chk["score"] > 0.9
    assert chk["relative_drop"]["ry+2deg"] > 0.3


def test_malformed_depth_file_is_a_one_line_error(capture: tuple[Path, object],
                                                   tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """An 8-bit depth PNG or an [H, W, 3] .npy under --depth gave a traceback and exit 1;
    now exit 2 naming the file and what a depth map is (PNG at TUM's 5000 per metre)."""
    import cv2

    cap_dir, cap = capture
    ext = tmp_path / "true.yaml"
    ext.write_text(yaml.safe_dump({"T_camera_laser": cap.T_camera_laser.tolist()}))  # type: ignore
    w, h = cap.camera.size  # type: ignore[attr-defined]
    for name, write in (("000000.png", lambda f: cv2.imwrite(str(f), np.full((h, w), 100,
                                                                               np.uint8))),
                        ("000000.npy", lambda f: np.save(f, np.ones((h, w, 3), np.float32)))):
        depth = tmp_path / Path(name).suffix[1:]
        depth.mkdir()
        write(depth / name)
        assert main(["check", "--images", str(cap_dir / "images"), "--scans",
                     str(cap_dir / "lasers"), "--camera", str(cap_dir / "camera.yaml"),
                     "--extrinsic", str(ext), "--depth", str(depth), "--out",
                     str(tmp_path / "chk")]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {depth / name}: depth ") and "5000 per metre" in err
        assert len(err.strip().splitlines()) == 1, err


def test_wrong_paths_stop_before_any_output(capture: tuple[Path, object], tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A folder given for a YAML file, a folder in the way of an output file, a check that
    cannot score: exit 2 with the path named, and nothing written in part."""
    cap_dir, _ = capture
    rc = main(["extrinsic", "--images", str(cap_dir / "images"), "--scans",
               str(cap_dir / "lasers"), "--camera", str(cap_dir), "--board", "11x8",
               "--square", "0.05"])
    assert rc == 2 and "is a folder; give the YAML file" in capsys.readouterr().err
    (tmp_path / "j").mkdir()
    rc = main(_args(cap_dir, "--out", str(tmp_path / "rig.yaml"), "--json", str(tmp_path / "j")))
    assert rc == 2 and not (tmp_path / "rig.yaml").exists()
    assert "is a folder; give a file name" in capsys.readouterr().err
    rc = main(["check", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
               "--camera", str(cap_dir / "camera.yaml"), "--extrinsic", str(tmp_path / "no.yaml"),
               "--out", str(tmp_path / "chk")])
    assert rc == 2 and not (tmp_path / "chk").exists()
    with pytest.raises(SystemExit) as e:
        main(["check", "--frames", "0", "--sequence", str(tmp_path)])
    assert e.value.code == 2


def test_intrinsics_refuses_a_folder_as_out_before_calibrating(
        capture: tuple[Path, object], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """intrinsics --out <folder> calibrated every image, printed the result, and then
    failed on the atomic rename ('[Errno 21] Is a directory'); extrinsic checked first."""
    cap_dir, _ = capture
    (tmp_path / "cam").mkdir()
    rc = main(["intrinsics", "--images", str(cap_dir / "images"), "--board", "11x8",
               "--square", "0.05", "--out", str(tmp_path / "cam")])
    out = capsys.readouterr()
    assert rc == 2 and out.err == f"error: {tmp_path / 'cam'}: is a folder; give a file name " \
        "to write\n"
    assert "RMS reprojection" not in out.out


def test_bench_without_anything_to_measure_fails() -> None:
    from calibration.bench import main as bench_main

    assert bench_main(["--no-sweep", "--acfr", "/nonexistent/acfr"]) == 2


def test_unreliable_result_never_replaces_a_good_rig(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    good = write_capture(make_capture(8, seed=1), tmp_path / "good")
    rig = tmp_path / "rig.yaml"
    assert main(_args(good, "--no-loo", "--out", str(rig))) == 0
    before = rig.read_bytes()
    flat = write_capture(make_capture(6, seed=3, min_tilt_deg=0.0, max_tilt_deg=0.01),
                         tmp_path / "flat")
    assert main(_args(flat, "--no-loo", "--out", str(rig))) == 3
    assert rig.read_bytes() == before
    side = tmp_path / "rig.unreliable.yaml"
    assert yaml.safe_load(side.read_text())["calibration"]["reliable"] is False
    assert "not " + str(rig) in capsys.readouterr().out


def test_wrong_square_size_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The boards' distances scale with --square: 10 % off moved the extrinsic 0.2 m with a
    5 mm residual, marked reliable."""
    cap_dir = write_capture(make_capture(10, seed=2), tmp_path / "cap")
    args = _args(cap_dir, "--no-loo", "--json", str(tmp_path / "r.json"))
    assert main(args) == 0
    assert json.loads((tmp_path / "r.json").read_text())["reliable"] is True
    args[args.index("--square") + 1] = "0.045"  # the true squares are 0.05 m
    assert main(args) == 3
    out = capsys.readouterr().out
    assert "square size (--square) is probably 1.1" in out


def test_cli_names_units_sizes_and_a_missing_rig_first(
        capture: tuple[Path, object], tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Millimetre scans said only 'no segment matches the board'; a missing --rig failed
    after the whole solve; mixed image sizes named no image."""
    import shutil

    import cv2

    from calibration.scans import read_pcd
    from calibration.synthetic import write_pcd

    cap_dir, _ = capture
    mm = tmp_path / "mm"
    mm.mkdir()
    for p in sorted((cap_dir / "lasers").glob("*.pcd")):
        write_pcd(mm / p.name, read_pcd(p) * 1000.0)
    args = _args(cap_dir, "--no-loo")
    args[args.index("--scans") + 1] = str(mm)
    assert main(args) == 2
    assert "are they in millimetres?" in capsys.readouterr().err
    # Before the solve: a solve that runs fails the test (a wall-clock bound on the
    # refusal failed on a loaded 2-core machine, reading the images alone took longer).
    import calibration.pipeline

    def no_solve(*args: object, **kwargs: object) -> None:
        raise AssertionError("the missing --rig must be found before the solve")

    monkeypatch.setattr(calibration.pipeline, "run_extrinsic", no_solve)
    assert main(_args(cap_dir, "--no-loo", "--out", str(tmp_path / "r.yaml"), "--rig",
                      str(tmp_path / "missing.yaml"))) == 2
    assert "missing.yaml: rig file not found" in capsys.readouterr().err
    monkeypatch.undo()
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for i, p in enumerate(sorted((cap_dir / "images").glob("*.png"))[:6]):
        shutil.copy(p, mixed / f"{i}.png")
    img = cv2.imread(str(mixed / "4.png"))
    cv2.imwrite(str(mixed / "4.png"), cv2.resize(img, (800, 600)))
    assert main(["intrinsics", "--images", str(mixed), "--board", "11x8", "--square", "0.05",
                 "--out", str(tmp_path / "c.yaml")]) == 2
    assert "1 not 640x480 (4.png)" in capsys.readouterr().err


def test_allow_unreliable_writes_out_marked(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """--allow-unreliable: --out gets the result anyway (the CLI had no such switch, only
    the recipe stage), still marked reliable: false so that readers warn, and exit 0."""
    flat = write_capture(make_capture(6, seed=3, min_tilt_deg=0.0, max_tilt_deg=0.01),
                         tmp_path / "flat")
    rig = tmp_path / "rig.yaml"
    assert main(_args(flat, "--no-loo", "--out", str(rig), "--allow-unreliable")) == 0
    out = capsys.readouterr().out
    assert "RESULT UNRELIABLE, used anyway (--allow-unreliable)" in out
    assert not (tmp_path / "rig.unreliable.yaml").exists()
    d = yaml.safe_load(rig.read_text())
    assert d["calibration"]["reliable"] is False and d["calibration"]["unreliable_because"]


def test_max_offset_error_names_views_not_in_the_solve(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """Two scans swapped and one scan without the board: the fit of the other five puts
    the laser 1.1 m out. The error named none of the six images the user gave."""
    from calibration.scans import read_pcd
    from calibration.synthetic import write_pcd

    cap = make_capture(6, seed=0)
    cap_dir = write_capture(cap, tmp_path / "cap")
    pcds = sorted((cap_dir / "lasers").glob("*.pcd"))
    a, b = read_pcd(pcds[1]), read_pcd(pcds[2])
    write_pcd(pcds[1], b)
    write_pcd(pcds[2], a)
    last = cap.views[-1]
    write_pcd(pcds[-1], last.scan_points[~last.on_board])  # the board left the scan
    assert main(_args(cap_dir, "--no-loo")) == 2
    err = capsys.readouterr().err
    image = sorted((cap_dir / "images").glob("*.png"))[-1].name
    assert "laser 1.12 m from the camera" in err
    assert f"Not in the solve: {image}: scan {pcds[-1].name}: no segment matches" in err
    # The board distance scale fitted at that wrong solution is 0.876 +- 0.006, but scaling
    # the distances leaves the laser 1 m out: the square size is not what to check.
    assert "--square" not in err


def test_extrinsic_on_one_image_says_the_board_is_in_it(capture: tuple[Path, object],
                                                       tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """A folder of one image, the board in it: extrinsic said "found in only 1 of the 1
    images"; with no board in it, "in any of the 1 images"."""
    from calibration.board import found_in

    cap_dir, _ = capture
    one = tmp_path / "one"
    for sub in ("images", "lasers"):
        (one / sub).mkdir(parents=True)
        shutil.copy(sorted((cap_dir / sub).iterdir())[0], one / sub)
    args = [a.replace(str(cap_dir / "images"), str(one / "images"))
            .replace(str(cap_dir / "lasers"), str(one / "lasers")) for a in _args(cap_dir)]
    assert main([*args, "--out", str(tmp_path / "rig.yaml")]) == 2
    err = capsys.readouterr().err
    name = next((one / "images").iterdir()).name
    assert f"was found in the only image in {one / 'images'} ({name}); at least 4 views" in err
    assert "1 of the 1" not in err and not (tmp_path / "rig.yaml").exists()
    assert [found_in(f, n) for f, n in [(0, 1), (0, 3), (2, 2), (2, 5), (4, 4)]] == [
        "in the only image", "in any of the 3 images", "in both images",
        "in only 2 of the 5 images", "in all 4 images"]


def test_intrinsics_names_images_without_the_board(capture: tuple[Path, object], tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Two images of the given 11x8 board and three of a 12x9 one: the error said only '2
    usable views ... Rejected: {}', hiding the images without the board and the grid that
    was there (extrinsic names both)."""
    from calibration.board import BoardSpec

    cap_dir, _ = capture
    folder = tmp_path / "images"
    folder.mkdir()
    for i, p in enumerate(sorted((cap_dir / "images").glob("*.png"))[:2]):
        shutil.copy(p, folder / f"a{i}.png")
    other = write_capture(make_capture(3, seed=4, board=BoardSpec(12, 9, 0.04)), tmp_path / "o")
    for i, p in enumerate(sorted((other / "images").glob("*.png"))):
        shutil.copy(p, folder / f"b{i}.png")
    assert main(["intrinsics", "--images", str(folder), "--board", "11x8", "--square", "0.05",
                 "--out", str(tmp_path / "cam.yaml")]) == 2
    err = capsys.readouterr().err
    assert "found in only 2 of the 5 images" in err and "at least 3 are needed" in err
    assert "no board found in b0.png, b1.png, b2.png" in err
    assert "grid was found in b0.png; pass --board 12x9" in err and "Rejected: {}" not in err
    assert not (tmp_path / "cam.yaml").exists()


def test_intrinsics_on_too_few_images_names_the_folder(capture: tuple[Path, object],
                                                      tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """A folder of one image, the board found in it: the error said only '1 usable views;
    at least 3 are needed', naming neither the folder nor its image."""
    cap_dir, _ = capture
    folder = tmp_path / "one"
    folder.mkdir()
    shutil.copy(sorted((cap_dir / "images").glob("*.png"))[0], folder / "only.png")
    assert main(["intrinsics", "--images", str(folder), "--board", "11x8", "--square", "0.05",
                 "--out", str(tmp_path / "cam.yaml")]) == 2
    err = capsys.readouterr().err
    assert f"board (inner corners, 50 mm squares) was found in the only image in {folder} " \
        "(only.png)" in err
    assert "at least 3 views are needed; capture more" in err
    assert not (tmp_path / "cam.yaml").exists()


def test_check_on_image_folders_takes_frames_spread_evenly(capture: tuple[Path, object],
                                                           tmp_path: Path) -> None:
    """check --images/--scans --frames 3 scored and drew all 8 pairs (--frames applied to
    --sequence only): now 3, spread as on a sequence (pairs 0, 4 and 7)."""
    cap_dir, cap = capture
    ext = tmp_path / "true.yaml"
    ext.write_text(yaml.safe_dump({"T_camera_laser": cap.T_camera_laser.tolist()}))  # type: ignore
    assert main(["check", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
                 "--camera", str(cap_dir / "camera.yaml"), "--extrinsic", str(ext), "--frames",
                 "3", "--out", str(tmp_path / "chk")]) == 0
    images = sorted((cap_dir / "images").glob("*.png"))
    chk = json.loads((tmp_path / "chk" / "check.json").read_text())
    assert chk["overlays"] == [f"{images[k].stem}_overlay.png" for k in (0, 4, 7)]
    # Again into the same folder with other frames: the first run's overlays of frames
    # this one does not draw stood beside the new ones, which check.json alone listed.
    # Files check.json does not list (a user's, even of the same pattern) stay.
    (tmp_path / "chk" / "mine_overlay.png").write_bytes(b"a user's")
    assert main(["check", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
                 "--camera", str(cap_dir / "camera.yaml"), "--extrinsic", str(ext), "--frames",
                 "2", "--out", str(tmp_path / "chk")]) == 0
    chk = json.loads((tmp_path / "chk" / "check.json").read_text())
    assert chk["overlays"] == [f"{images[k].stem}_overlay.png" for k in (0, 7)]
    assert sorted(p.name for p in (tmp_path / "chk").iterdir()) == sorted(
        ["check.json", "mine_overlay.png", *chk["overlays"]])


def test_check_that_scores_no_point_fails_naming_the_slip(capture: tuple[Path, object],
                                                          tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    """An extrinsic that puts no scan point into any image (translation in millimetres, the
    inverse stored) printed "0 points; score nan" and exited 0; now exit 2 naming the slip,
    and --init so far off is refused before the board search."""
    from toolkit.geometry import inv_se3

    cap_dir, cap = capture
    T = np.asarray(cap.T_camera_laser)  # type: ignore[attr-defined]
    T_mm = T.copy()
    T_mm[:3, 3] *= 1000.0
    base = ["check", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
            "--camera", str(cap_dir / "camera.yaml"), "--out", str(tmp_path / "chk")]
    for name, M, says in (("mm", T_mm, "is its translation in millimetres"),
                          ("inv", inv_se3(T), "is T_laser_camera stored under the key")):
        ext = tmp_path / f"{name}.yaml"
        ext.write_text(yaml.safe_dump({"T_camera_laser": M.tolist()}))
        assert main([*base, "--extrinsic", str(ext)]) == 2, name
        err = capsys.readouterr().err
        assert f"{ext}: only 0 scan points" in err and says in err, err
        assert not (tmp_path / "chk" / "check.json").exists()
    assert main(_args(cap_dir, "--init", str(tmp_path / "mm.yaml"))) == 2
    err = capsys.readouterr().err
    assert "beyond --max-offset 0.5 m" in err and "millimetres" in err, err


def test_scans_of_only_nan_points_are_named_not_the_extrinsic(
        capture: tuple[Path, object], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Scan files of only NaN points: check blamed the extrinsic's file ("ext.yaml: only 0
    scan points ... hold no points") and extrinsic advised --angle-window, --mount and the
    rest for "no segment matches the board"; both now name the scan files."""
    from calibration.synthetic import write_pcd

    src, cap = capture
    cap_dir = Path(shutil.copytree(src, tmp_path / "cap"))
    lasers = sorted((cap_dir / "lasers").glob("*.pcd"))
    for p in lasers:
        write_pcd(p, np.full((50, 3), np.nan))
    ext = tmp_path / "ext.yaml"
    ext.write_text(yaml.safe_dump({"T_camera_laser": np.asarray(
        cap.T_camera_laser).tolist()}))  # type: ignore[attr-defined]
    assert main(["check", "--images", str(cap_dir / "images"), "--scans",
                 str(cap_dir / "lasers"), "--camera", str(cap_dir / "camera.yaml"),
                 "--extrinsic", str(ext), "--out", str(tmp_path / "chk")]) == 2
    err = capsys.readouterr().err
    assert "hold no finite points" in err and str(lasers[0]) in err and str(ext) not in err, err
    assert main(_args(cap_dir)) == 2
    err = capsys.readouterr().err
    assert f"none of the 8 paired scans holds a finite point ({lasers[0].name}" in err, err
    assert "--angle-window" not in err, err
    # One such scan among good ones: the view is left out saying why (it said "no segment
    # matches the board", or "no scan points near the predicted board plane").
    shutil.rmtree(cap_dir / "lasers")
    shutil.copytree(src / "lasers", cap_dir / "lasers")
    write_pcd(lasers[2], np.full((50, 3), np.nan))
    assert main(_args(cap_dir, "--no-loo", "--json", str(tmp_path / "r.json"))) == 0
    skipped = json.loads((tmp_path / "r.json").read_text())["images_skipped"]
    assert list(skipped.values()) == [f"scan {lasers[2].name}: no finite points in the file"]


def test_a_stop_between_rig_and_json_leaves_no_earlier_json_beside_the_new_rig(
        capture: tuple[Path, object], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """--out then --json: a run stopped between the two writes left the previous run's JSON
    beside the new rig, a pair that disagrees."""
    import toolkit.io.atomic

    cap_dir, _ = capture
    rig, js = tmp_path / "rig.yaml", tmp_path / "r.json"
    js.write_text(json.dumps({"T_camera_laser": "of an earlier run"}))

    def stopped(*_: object, **__: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(toolkit.io.atomic, "atomic_write_json", stopped)
    assert main(_args(cap_dir, "--no-loo", "--out", str(rig), "--json", str(js))) != 0
    assert rig.exists() and not js.exists()


def test_bench_markdown_says_the_real_result_is_unreliable() -> None:
    """bench.md's ACFR paragraph gave the residual and spread but not the verdict that
    bench.json holds (reliable: false)."""
    from calibration.bench import markdown

    why = "the 5 board normals all lie within 1.3 degrees (RMS) of one plane"
    text = markdown({"acfr": {"residual_rms_m": 0.0039, "views_used": 5, "weak_directions": [],
                              "reliable": False, "unreliable_because": [why]}})
    assert f"RESULT UNRELIABLE: {why}" in text


@pytest.mark.parametrize("command", ["check", "time-offset", "extrinsic"])
def test_a_run_folder_given_as_sequence_names_the_sequence_in_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    # The docs' paths are runs/NAME/simulate/sequence; "runs/NAME" is the usual slip.
    inner = tmp_path / "run" / "simulate" / "sequence"
    inner.mkdir(parents=True)
    (inner / "rig.yaml").write_text("placeholder: the folder check reads no file\n")
    extra = ["--board", "11x8", "--square", "0.02"] if command == "extrinsic" else []
    code = main([command, "--sequence", str(tmp_path / "run"), "--out",
                 str(tmp_path / "out"), *extra])
    assert code == 2
    err = capsys.readouterr().err
    assert "not a sequence folder" in err and str(inner) in err


_KILL_AT_SECOND_OVERLAY = """
import os, signal, sys
import cv2
from calibration.cli import main
# Ctrl-C as in a terminal: a job started in the background by a non-interactive shell
# (nohup, `cmd &`) inherits SIGINT ignored, and the signal below did nothing.
signal.signal(signal.SIGINT, signal.default_int_handler)
real, written = cv2.imwrite, []
def imwrite(path, img, *args):
    ok = real(path, img, *args)  # the temporary of an atomic write, whole on disk
    written.append(path)
    if len(written) == 2:
        os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    return ok
cv2.imwrite = imwrite
sys.exit(main(sys.argv[2:]))
"""


def _check_args(capture: tuple[Path, object], tmp_path: Path) -> tuple[Path, Path, list[str]]:
    """The capture folder, the output folder and the arguments of a check of the true
    extrinsic on the capture's 8 pairs."""
    cap_dir, cap = capture
    ext = tmp_path / "true.yaml"
    ext.write_text(yaml.safe_dump({"T_camera_laser": cap.T_camera_laser.tolist()}))  # type: ignore
    out = tmp_path / "chk"
    return cap_dir, out, [
        "check", "--images", str(cap_dir / "images"), "--scans", str(cap_dir / "lasers"),
        "--camera", str(cap_dir / "camera.yaml"), "--extrinsic", str(ext), "--out", str(out)]


def test_a_temporary_a_sigkill_left_goes_on_the_next_run(
        capture: tuple[Path, object], tmp_path: Path) -> None:
    """SIGKILL runs no handler: the overlay being written stayed beside the outputs as a
    hidden temporary, and no later run removed it (outside run folders nothing did). The
    next write of that output removes it (its writer's process is gone)."""
    cap_dir, out, args = _check_args(capture, tmp_path)
    r = subprocess.run([sys.executable, "-c", _KILL_AT_SECOND_OVERLAY, "SIGKILL", *args],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == -9, (r.returncode, r.stderr[-2000:])
    left = [p.name for p in out.iterdir() if p.name.startswith(".")]
    assert len(left) == 1 and left[0].endswith(".tmp.png"), left
    (out / ".notes").write_text("a user's")
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == [".notes"]
    assert len(list(out.glob("*_overlay.png"))) == 8


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_check_stopped_while_it_writes_leaves_no_temporary(
        capture: tuple[Path, object], tmp_path: Path, sig: str) -> None:
    """SIGTERM (kill, a scheduler) ended the command at once: the overlay being written
    stayed beside the outputs as a hidden temporary for good; Ctrl-C printed Python's
    traceback. Now both end as the recipe runner's do: the write in flight removed, one
    line saying what was written, exit 130; a rerun writes everything."""
    cap_dir, out, args = _check_args(capture, tmp_path)
    r = subprocess.run([sys.executable, "-c", _KILL_AT_SECOND_OVERLAY, sig, *args], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 130, (r.returncode, r.stderr[-2000:])
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    assert r.stderr.strip().splitlines()[-1].startswith("interrupted:"), r.stderr
    assert sorted(p.name for p in out.iterdir()) == [
        f"{Path(n).stem}_overlay.png" for n in sorted(p.name for p in
                                                      (cap_dir / "images").iterdir())[:1]]
    assert main(args) == 0
    assert not [p for p in out.iterdir() if p.name.startswith(".")]
    assert len(list(out.glob("*_overlay.png"))) == 8 and (out / "check.json").exists()
