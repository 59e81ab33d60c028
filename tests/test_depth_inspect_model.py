"""`python -m toolkit.depth.inspect_model`: the layouts of known exports are recognised and
the depth stage it prints runs; unknown settings are said, not guessed silently."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

pytest.importorskip("onnxruntime")
onnx = pytest.importorskip("onnx")

from onnx import TensorProto, helper  # noqa: E402
from onnx_graphs import save_graph  # noqa: E402  (the tests folder is on sys.path)

from toolkit.depth.inspect_model import TensorInfo, main, suggest  # noqa: E402

SHIPPED = Path(__file__).resolve().parents[1] / "datasets" / "models" / "small-depth.onnx"


def _stage(out: str) -> dict:
    """The depth stage printed after 'depth stage:' (comments and all), parsed."""
    return yaml.safe_load(out.split("depth stage:\n", 1)[1].split("\nran on")[0])[0]


def test_metric3d_export_is_recognised() -> None:
    sug = suggest([TensorInfo("image", [1, 3, 616, 1064])],
                  [TensorInfo("pred_depth", [1, 1, 616, 1064])], {})
    assert sug.recognised == "Metric3D"
    s = sug.settings
    assert s["resize"] == "letterbox" and s["canonical_focal"] == 1000.0
    assert s["output"] == "metric_depth" and s["std"] == pytest.approx([1 / 255] * 3)
    assert s["fill"] == [123.675, 116.28, 103.53] and "output_index" not in s


def test_unidepth_export_is_recognised() -> None:
    ins = [TensorInfo("image", ["batch", 3, 462, 616]), TensorInfo("K", ["batch", 3, 3])]
    outs = [TensorInfo("out_K", ["batch", 3, 3]), TensorInfo("depth", ["batch", 1, 462, 616]),
            TensorInfo("depth_ssi", ["batch", 1, 462, 616]),
            TensorInfo("confidence", ["batch", 1, 462, 616])]
    sug = suggest(ins, outs, {})
    assert sug.recognised == "UniDepth V2"
    assert sug.settings == {"intrinsics_input": "K", "output_index": 1,
                            "confidence_index": 3, "output": "metric_depth"}
    assert any("min_confidence" in n for n in sug.notes)
    # its batch axis is symbolic, its size fixed: said so, not "free" (input_size 518
    # would then be refused)
    assert any("fixed input 462x616" in n for n in sug.notes)
    assert not any("input size is free" in n for n in sug.notes)


def test_unknown_settings_are_said() -> None:
    # A Depth Anything export: dynamic size, output named for what it is
    sug = suggest([TensorInfo("pixel_values", [1, 3, "height", "width"])],
                  [TensorInfo("predicted_disparity", [1, "height", "width"])], {})
    assert sug.settings == {"output": "relative_disparity"}
    assert any("guessed from the output's name" in n for n in sug.notes)
    assert any("set input_size" in n for n in sug.notes)
    # nothing to go on: the kind is asked for; channels last and an extra input are named
    sug = suggest([TensorInfo("x", [1, 240, 320, 3]), TensorInfo("scale", [1])],
                  [TensorInfo("y", [1, 240, 320, 1])], {})
    assert sug.settings == {"layout": "nhwc"}
    assert any("say what the network outputs" in n for n in sug.notes)
    assert any("'scale' [1] is neither the image nor intrinsics" in n for n in sug.notes)
    assert any("fixed input 240x320" in n for n in sug.notes)
    assert "no input looks like an image" in suggest(
        [TensorInfo("tokens", [1, 77])], [TensorInfo("y", [1, 512])], {}).notes[0]


def test_cli_prints_a_stage_that_runs_on_an_image(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    if not SHIPPED.is_file():
        pytest.skip("the shipped model is not in this checkout")
    img = tmp_path / "frame.png"
    rng = np.random.default_rng(0)
    cv2.imwrite(str(img), rng.integers(0, 256, (120, 160, 3), dtype=np.uint8))
    assert main([str(SHIPPED), "--image", str(img), "--png", str(tmp_path / "d.png")]) == 0
    out = capsys.readouterr().out
    stage = _stage(out)
    assert stage["model"] == str(SHIPPED) and stage["backend"] == "onnx"
    assert "depth_kind='relative_depth'" in out  # its metadata, listed
    assert "ran on" in out and "100.0 % of pixels have a value" in out
    assert (tmp_path / "d.png").stat().st_size > 0
    # --set overrides a suggestion; a model that needs the camera asks for it
    path = save_graph(tmp_path / "m3d.onnx", [
        helper.make_node("ReduceMean", ["image"], ["m"], axes=[1], keepdims=1),
        helper.make_node("Softplus", ["m"], ["pred_depth"])],
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 616, 1064])],
        [helper.make_tensor_value_info("pred_depth", TensorProto.FLOAT, None)])
    assert main([str(path), "--image", str(img), "--set", "interpolation=cubic"]) == 2
    captured = capsys.readouterr()
    assert _stage(captured.out)["interpolation"] == "cubic"
    assert "give --camera fx,fy,cx,cy" in captured.err
    assert main([str(path), "--image", str(img), "--camera", "150,150,79.5,59.5"]) == 0
    assert "ran on" in capsys.readouterr().out


def test_cli_names_a_bad_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main([str(tmp_path / "none.onnx")]) == 2
    assert "none.onnx" in capsys.readouterr().err
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    assert main([str(bad)]) == 2
    assert "bad.onnx" in capsys.readouterr().err
    # A missing --image is named as missing, before the model is read or printed.
    assert main([str(bad), "--image", str(tmp_path / "f.png")]) == 2
    out, err = capsys.readouterr()
    assert "f.png: no such file" in err and "bad.onnx" not in err + out, err
    for arg in ("no-equals-sign", "output=["):  # not KEY=VALUE, not YAML: usage, no trace
        with pytest.raises(SystemExit):
            main([str(bad), "--set", arg])
        assert "--set" in capsys.readouterr().err
    # values read as a recipe reads them (YAML 1.2: 0240 is 240, not octal 160)
    from toolkit.depth.inspect_model import _set_value

    assert _set_value("input_size=[0240,0320]") == ("input_size", [240, 320])
    # a misspelt key is refused before it is printed into a stage
    if SHIPPED.is_file():
        assert main([str(SHIPPED), "--set", "min_confidense=0.5"]) == 2
        err = capsys.readouterr().err
        assert "not a valid depth stage" in err and "min_confidense" in err
        # One line naming the option, the rule and a close name; not pydantic's dump.
        assert "unknown key 'min_confidense' (did you mean 'min_confidence'?)" in err, err
        assert main([str(SHIPPED), "--set", "multiple_of=0"]) == 2
        err = capsys.readouterr().err
        assert ("--set multiple_of: multiple_of: Input should be greater than or equal to 1 "
                "(got 0)") in err and "pydantic" not in err, err
