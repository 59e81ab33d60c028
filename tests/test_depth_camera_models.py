"""Metric networks that depend on the camera: a letterbox into a fixed input (Metric3D's
616x1064), a canonical focal length (Metric3D), an intrinsics input (UniDepth exports).
Each on a model built node by node whose answer is known."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from onnx_graphs import save_graph  # the tests folder is on sys.path

from toolkit.camera import PinholeCamera

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from onnx import TensorProto, helper  # noqa: E402

from toolkit.depth.onnx_backend import OnnxDepthBackend  # noqa: E402
from toolkit.depth.onnx_backend import OnnxDepthConfig as C  # noqa: E402


def _mean_model(path: Path, shape: list) -> Path:
    """depth = softplus(mean over the channels): [1, 1, h, w]."""
    return save_graph(path, [helper.make_node("ReduceMean", ["image"], ["m"], axes=[1], keepdims=1),
                        helper.make_node("Softplus", ["m"], ["depth"])],
                 [helper.make_tensor_value_info("image", TensorProto.FLOAT, shape)])


def _intrinsics_model(path: Path, k_shape: list, pick: np.ndarray, elem: int,
                      nhwc_k_first: bool = False) -> Path:
    """depth = sum(K * pick) at every pixel (plus 0 x the image, so the output has the
    input's size): one intrinsic, where the network put it. ``nhwc_k_first``: the image
    channels last, listed after the intrinsics."""
    w = helper.make_tensor("w", elem, list(pick.shape), pick.reshape(-1).tolist())
    image = helper.make_tensor_value_info(
        "image", TensorProto.FLOAT, [1, 28, 42, 3] if nhwc_k_first else [1, 3, "h", "w"])
    k_input = helper.make_tensor_value_info("K", elem, k_shape)
    first = [helper.make_node("Transpose", ["image"], ["chw"], perm=[0, 3, 1, 2])]
    nodes = (first if nhwc_k_first else []) + [
             helper.make_node("ReduceMean", ["chw" if nhwc_k_first else "image"], ["m"],
                              axes=[1], keepdims=1),
             helper.make_node("Constant", [], ["zero"],
                              value=helper.make_tensor("z", TensorProto.FLOAT, [], [0.0])),
             helper.make_node("Mul", ["m", "zero"], ["m0"]),
             helper.make_node("Constant", [], ["pick"], value=w),
             helper.make_node("Mul", ["K", "pick"], ["kp"]),
             helper.make_node("ReduceSum", ["kp"], ["ks"], keepdims=0),
             helper.make_node("Cast", ["ks"], ["ksf"], to=TensorProto.FLOAT),
             helper.make_node("Add", ["m0", "ksf"], ["depth"])]
    return save_graph(path, nodes, [k_input, image] if nhwc_k_first else [image, k_input])


@pytest.fixture
def rgb() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (45, 61, 3), dtype=np.uint8)


def test_letterbox_fits_the_image_and_cuts_the_fill(tmp_path: Path, rgb: np.ndarray) -> None:
    path = _mean_model(tmp_path / "fixed.onnx", [1, 3, 28, 42])
    be = OnnxDepthBackend(C(model=path, kind="metric_depth", resize="letterbox",
                            interpolation="linear", threads=1))
    # 45x61 into 28x42 at its own aspect: 28 x 38, centred (2 columns of fill each side).
    assert be.placement((45, 61)) == (0, 2, 28, 38)
    x = be.preprocess(rgb)
    assert x.shape == (1, 3, 28, 42)
    assert np.all(x[..., :2] == 0) and np.all(x[..., 40:] == 0)  # the mean colour
    small = cv2.resize(rgb, (38, 28), interpolation=cv2.INTER_LINEAR)
    ref_in = (small.astype(np.float32) / 255 - be.mean) / be.std  # [28, 38, 3]
    np.testing.assert_allclose(x[0].transpose(1, 2, 0)[:, 2:40], ref_in, rtol=1e-6, atol=1e-6)
    # The output loses the fill before it is resized back: no column of the image takes
    # the fill's depth.
    out = be.predict(rgb).values
    ref = cv2.resize(np.log1p(np.exp(ref_in.mean(axis=2))), (61, 45),
                     interpolation=cv2.INTER_LINEAR)
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-6)
    assert be.describe()["placement"] == [0, 2, 28, 38]
    # A wider image is filled above and below; a square input from one number.
    assert be.placement((20, 84)) == (9, 0, 10, 42)
    dyn = OnnxDepthBackend(C(model=_mean_model(tmp_path / "dyn.onnx", [1, 3, "h", "w"]),
                             kind="metric_depth", resize="letterbox", input_size=56))
    assert dyn.placement((45, 61)) == (7, 0, 41, 56)


def test_canonical_focal_gives_the_cameras_metric_depth(tmp_path: Path,
                                                         rgb: np.ndarray) -> None:
    """Metric3D predicts depth z * f_c / f for a camera of focal f at the network input:
    the output times f / f_c is z, whatever the resize did to f."""
    path = _mean_model(tmp_path / "m.onnx", [1, 3, "h", "w"])
    cam = PinholeCamera(61, 45, 500.0, 480.0, 30.0, 22.0)
    plain = OnnxDepthBackend(C(model=path, kind="metric_depth", input_size=(28, 42),
                               multiple_of=1, threads=1)).predict(rgb).values
    be = OnnxDepthBackend(C(model=path, kind="metric_depth", input_size=(28, 42),
                            multiple_of=1, canonical_focal=1000.0, threads=1))
    got = be.predict(rgb, camera=cam).values
    f_in = np.sqrt(500.0 * 42 / 61 * 480.0 * 28 / 45)  # a stretch scales fx and fy apart
    np.testing.assert_allclose(got, plain * f_in / 1000.0, rtol=1e-5)
    assert be.describe()["focal_factor"] == pytest.approx(f_in / 1000.0)
    # Letterboxed, the camera keeps one scale: 28 / 45 on both axes (38 / 61 across).
    box = OnnxDepthBackend(C(model=path, kind="metric_depth", input_size=(28, 42),
                             multiple_of=1, canonical_focal=1000.0, resize="letterbox"))
    fx, fy, cx, cy = box.network_intrinsics(cam, (45, 61))
    assert (fx, fy) == pytest.approx((500.0 * 38 / 61, 480.0 * 28 / 45))
    assert (cx, cy) == pytest.approx((30.5 * 38 / 61 - 0.5 + 2, 22.5 * 28 / 45 - 0.5))
    box.predict(rgb, camera=cam)
    assert box.last_focal_factor == pytest.approx(np.sqrt(fx * fy) / 1000.0)
    with pytest.raises(ValueError, match="need the camera's intrinsics: pass camera="):
        be.predict(rgb)
    with pytest.raises(ValueError, match="the camera is 640x480 but the image is 61x45"):
        be.predict(rgb, camera=PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0))
    with pytest.raises(ValueError, match="output is relative_disparity.*drop it"):
        OnnxDepthBackend(C(model=path, kind="relative_disparity", canonical_focal=1000.0))
    with pytest.raises(ValueError, match="canonical_focal must be a positive"):
        C(model=path, canonical_focal=0.0)


@pytest.mark.parametrize("k_shape,flat_index,elem,name", [
    ([1, 3, 3], 2, TensorProto.FLOAT, "cx"),    # K[0, 2]
    ([3, 3], 5, TensorProto.DOUBLE, "cy"),      # K[1, 2]
    (["batch", 4], 2, TensorProto.FLOAT, "cx"),  # fx, fy, cx, cy
    ([4], 1, TensorProto.FLOAT16, "fy")])
def test_intrinsics_input_takes_the_camera_at_the_network_input(
        tmp_path: Path, rgb: np.ndarray, k_shape: list, flat_index: int, elem: int,
        name: str) -> None:
    dims = [1 if isinstance(d, str) else d for d in k_shape]
    pick = np.zeros(int(np.prod(dims)))
    pick[flat_index] = 1.0
    path = _intrinsics_model(tmp_path / "uni.onnx", k_shape, pick.reshape(dims), elem)
    cam = PinholeCamera(61, 45, 500.0, 480.0, 30.0, 22.0)
    be = OnnxDepthBackend(C(model=path, kind="metric_depth", input_size=(28, 42),
                            resize="letterbox", intrinsics_input="K", threads=1))
    fx, fy, cx, cy = be.network_intrinsics(cam, (45, 61))
    want = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}[name]
    out = be.predict(rgb, camera=cam).values
    np.testing.assert_allclose(out, want, rtol=2e-3 if elem == TensorProto.FLOAT16 else 1e-5)


def test_intrinsics_inputs_are_checked_when_loaded(tmp_path: Path) -> None:
    pick = np.zeros((1, 3, 3), np.float32)
    path = _intrinsics_model(tmp_path / "uni.onnx", [1, 3, 3], pick, TensorProto.FLOAT)
    with pytest.raises(ValueError, match=r"takes 2 inputs \('image'.*'K'.*intrinsics_input"):
        OnnxDepthBackend(C(model=path, kind="metric_depth"))
    with pytest.raises(ValueError, match=r"intrinsics_input 'cam' is not an input.*'K'"):
        OnnxDepthBackend(C(model=path, kind="metric_depth", intrinsics_input="cam"))
    bad = _intrinsics_model(tmp_path / "bad.onnx", [1, 3, 4], np.zeros((1, 3, 4), np.float32),
                            TensorProto.FLOAT)
    with pytest.raises(ValueError, match=r"intrinsics input 'K' is tensor\(float\) \[1, 3, 4\]"):
        OnnxDepthBackend(C(model=bad, kind="metric_depth", intrinsics_input="K"))


def test_channels_last_image_after_the_intrinsics(tmp_path: Path, rgb: np.ndarray) -> None:
    """The image's fixed size is read from the image input, not from the first one (K's
    [1, 3, 3] was taken for a 3x3 image)."""
    pick = np.zeros((1, 3, 3), np.float32)
    pick[0, 0, 0] = 1.0
    path = _intrinsics_model(tmp_path / "k.onnx", [1, 3, 3], pick, TensorProto.FLOAT,
                             nhwc_k_first=True)
    be = OnnxDepthBackend(C(model=path, kind="metric_depth", layout="nhwc",
                            intrinsics_input="K", threads=1))
    assert be.input_hw((45, 61)) == (28, 42)
    cam = PinholeCamera(61, 45, 500.0, 480.0, 30.0, 22.0)
    np.testing.assert_allclose(be.predict(rgb, camera=cam).values, 500.0 * 42 / 61, rtol=1e-5)


@pytest.mark.parametrize("pool", [2, 4])
def test_letterbox_of_a_coarser_output_keeps_the_pixels_in_place(tmp_path: Path,
                                                                 pool: int) -> None:
    """A network whose output is 1/2 or 1/4 of its input: the fill is cut at the input's
    resolution. Image: a horizontal ramp; network: mean over the channels, average-pooled.
    The depth at each image column is that column's ramp value (cut at whole output
    pixels, it was up to 2.7 columns off)."""
    H, W = 45, 61
    rgb = np.repeat((np.arange(W) * 4).astype(np.uint8)[None, :, None], H, 0).repeat(3, 2)
    one = helper.make_tensor("o", TensorProto.FLOAT, [], [1.0])
    path = save_graph(tmp_path / "pool.onnx", [
        helper.make_node("ReduceMean", ["image"], ["m"], axes=[1], keepdims=1),
        helper.make_node("Constant", [], ["one"], value=one),
        helper.make_node("Add", ["m", "one"], ["a"]),
        helper.make_node("AveragePool", ["a"], ["depth"], kernel_shape=[pool, pool],
                         strides=[pool, pool])],
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 32, 64])])
    be = OnnxDepthBackend(C(model=path, kind="metric_depth", resize="letterbox",
                            mean=(0, 0, 0), std=(1, 1, 1), interpolation="linear", threads=1))
    column = (be.predict(rgb).values[H // 2] - 1) * 255 / 4  # [W] the column each came from
    np.testing.assert_allclose(column[8:W - 8], np.arange(8, W - 8), atol=0.15)


def test_letterbox_fill_in_pixel_units(tmp_path: Path, rgb: np.ndarray) -> None:
    """Metric3D's own export takes raw pixels (mean 0, std 1/255) and is padded with its
    mean colour: the fill is given in 0-255 units and normalised like the image."""
    path = _mean_model(tmp_path / "fixed.onnx", [1, 3, 28, 42])
    fill = (123.675, 116.28, 103.53)
    be = OnnxDepthBackend(C(model=path, kind="metric_depth", resize="letterbox",
                            mean=(0.0, 0.0, 0.0), std=(1 / 255,) * 3, fill=fill))
    x = be.preprocess(rgb)[0]  # [3, 28, 42]
    np.testing.assert_allclose(x[:, :, 0], np.broadcast_to(np.array(fill)[:, None], (3, 28)),
                               rtol=1e-6)
    np.testing.assert_allclose(x[:, :, 2:40].transpose(1, 2, 0),
                               cv2.resize(rgb, (38, 28), interpolation=cv2.INTER_CUBIC)
                               .astype(np.float32), rtol=1e-5)


def test_depth_stage_gives_the_network_its_camera(tmp_path: Path) -> None:
    """The stage passes the sequence's camera: an output of fx at the network input, times
    the canonical-focal factor, is the camera's fx scaled to it, stored for every frame."""
    import json

    from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

    from toolkit.depth.stage import DepthStage
    from toolkit.depth.store import DepthStore
    from toolkit.fusion.synthetic import write_box_room
    from toolkit.io.sequence import read_sequence

    path = _intrinsics_model(tmp_path / "uni.onnx", [1, 3, 3],
                             np.array([[[1, 0, 0], [0, 0, 0], [0, 0, 0]]], np.float32),
                             TensorProto.FLOAT)
    seq_dir = write_box_room(tmp_path / "seq", n_frames=2)  # 160x120 images
    res = run_stages(tmp_path, [{"stage": "t_sequence", "path": str(seq_dir)},
                                {"stage": "depth", "model": str(path), "threads": 1,
                                 "output": "metric_depth", "input_size": [60, 100],
                                 "resize": "letterbox", "multiple_of": 1,
                                 "intrinsics_input": "K", "canonical_focal": 100.0}],
                     {"t_sequence": SequenceFolder, "depth": DepthStage})
    assert res.ok, res.error
    fx = read_sequence(seq_dir).rig.camera.fx
    fy = read_sequence(seq_dir).rig.camera.fy
    factor = np.sqrt(fx * 0.5 * fy * 0.5) / 100.0  # 160x120 fits 60x100 as 80x60
    store = DepthStore(tmp_path / "run" / "depth" / "depth")
    for i in (0, 1):
        np.testing.assert_allclose(store.read(i).values, fx * 0.5 * factor, rtol=1e-5)
    # meta.json says where the image lay and the factor, written before any frame
    meta = json.loads((tmp_path / "run" / "depth" / "depth" / "meta.json").read_text())
    assert meta["placement"] == [0, 10, 60, 80] and meta["input_hw"] == [60, 100]
    assert meta["focal_factor"] == pytest.approx(factor)
    assert f"times {factor:.4f}" in (tmp_path / "run" / "report.md").read_text()


def test_depth_stage_takes_a_calibrated_camera_from_upstream(tmp_path: Path) -> None:
    """A calibrate stage's rig replaces the sequence's camera in fuse; the depth stage gave
    a camera-input network the sequence's own intrinsics all the same."""
    from dataclasses import replace

    from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

    from toolkit.depth.stage import DepthStage
    from toolkit.depth.store import DepthStore
    from toolkit.fusion.synthetic import write_box_room
    from toolkit.io.sequence import read_sequence, write_rig
    from toolkit.recipe.stage import Stage, StageConfig

    seq_dir = write_box_room(tmp_path / "seq", n_frames=2)  # 160x120 images
    rig = read_sequence(seq_dir).rig
    calibrated = replace(rig, camera=replace(rig.camera, fx=rig.camera.fx * 1.5))

    class RigConfig(StageConfig):
        pass

    class RigStage(Stage):
        name = "t_rig"
        Config = RigConfig
        provides = ("rig",)

        def run(self, ctx: object) -> None:
            path = ctx.stage_dir / "rig.yaml"  # type: ignore[attr-defined]
            write_rig(path, calibrated)
            ctx.provide("rig", path)  # type: ignore[attr-defined]

    path = _intrinsics_model(tmp_path / "uni.onnx", [1, 3, 3],
                             np.array([[[1, 0, 0], [0, 0, 0], [0, 0, 0]]], np.float32),
                             TensorProto.FLOAT)
    res = run_stages(tmp_path, [{"stage": "t_sequence", "path": str(seq_dir)},
                                {"stage": "t_rig"},
                                {"stage": "depth", "model": str(path), "threads": 1,
                                 "output": "metric_depth", "input_size": [60, 80],
                                 "multiple_of": 1, "intrinsics_input": "K"}],
                     {"t_sequence": SequenceFolder, "t_rig": RigStage, "depth": DepthStage})
    assert res.ok, res.error
    store = DepthStore(tmp_path / "run" / "depth" / "depth")
    np.testing.assert_allclose(store.read(0).values, calibrated.camera.fx * 0.5, rtol=1e-5)


def _confidence_model(path: Path, shape: list) -> Path:
    """UniDepth V2's export layout: out_K, depth, depth_ssi, confidence. depth =
    softplus(mean over the channels), confidence = the first input channel."""
    k = helper.make_tensor("k", TensorProto.FLOAT, [1, 3, 3], np.eye(3).reshape(-1).tolist())
    starts = helper.make_tensor("s0", TensorProto.INT64, [1], [0])
    ends = helper.make_tensor("s1", TensorProto.INT64, [1], [1])
    axes = helper.make_tensor("ax", TensorProto.INT64, [1], [1])
    nodes = [helper.make_node("Constant", [], ["out_K"], value=k),
             helper.make_node("ReduceMean", ["image"], ["m"], axes=[1], keepdims=1),
             helper.make_node("Softplus", ["m"], ["depth"]),
             helper.make_node("Identity", ["depth"], ["depth_ssi"])] + [
             helper.make_node("Constant", [], [t.name], value=t) for t in (starts, ends, axes)
             ] + [helper.make_node("Slice", ["image", "s0", "s1", "ax"], ["confidence"])]
    outputs = [helper.make_tensor_value_info("out_K", TensorProto.FLOAT, [1, 3, 3])] + [
        helper.make_tensor_value_info(n, TensorProto.FLOAT, None)
        for n in ("depth", "depth_ssi", "confidence")]
    return save_graph(path, nodes, [helper.make_tensor_value_info(
        "image", TensorProto.FLOAT, shape)], outputs)


def test_low_confidence_pixels_are_dropped(tmp_path: Path, rgb: np.ndarray) -> None:
    path = _confidence_model(tmp_path / "conf.onnx", [1, 3, "h", "w"])
    be = OnnxDepthBackend(C(model=path, kind="metric_depth", output_index=1,
                            confidence_index=3, min_confidence=0.5, mean=(0, 0, 0),
                            std=(1, 1, 1), input_size=(45, 61), multiple_of=1, threads=1))
    pred = be.predict(rgb)
    sure = rgb[..., 0] / 255.0 >= 0.5  # the confidence, at the image's own size
    assert np.isfinite(pred.values[sure]).all() and np.isnan(pred.values[~sure]).all()
    assert pred.extra["confident_fraction"] == pytest.approx(sure.mean())
    assert be.describe()["confidence_output"] == "confidence"
    # Letterboxed into a fixed input, the confidence is placed as the depth is: a dark
    # left half is dropped, the bright right half kept (one column of blend between).
    half = np.zeros((45, 61, 3), np.uint8)
    half[:, 31:] = 255
    box = OnnxDepthBackend(C(model=_confidence_model(tmp_path / "f.onnx", [1, 3, 28, 42]),
                             kind="metric_depth", output_index=1, confidence_index=3,
                             min_confidence=0.5, mean=(0, 0, 0), std=(1, 1, 1),
                             resize="letterbox", interpolation="linear"))
    kept = np.isfinite(box.predict(half).values)
    assert not kept[:, :30].any() and kept[:, 32:].all()
    # A frame without depth has no share to tell: not recorded as "all dropped".
    nothing = OnnxDepthBackend(C(model=path, kind="metric_depth", output_index=1,
                                 confidence_index=3, min_confidence=0.5, mean=(0, 0, 0),
                                 std=(1, 1, 1), input_size=(45, 61), multiple_of=1,
                                 output_scale=-1.0))  # every depth negative: none valid
    assert "confident_fraction" not in nothing.predict(rgb).extra
    with pytest.raises(ValueError, match="min_confidence needs confidence_index"):
        C(model=path, min_confidence=0.5)
    for bad in (1, 4):
        with pytest.raises(ValueError, match=f"confidence_index {bad} is not another output"):
            OnnxDepthBackend(C(model=path, kind="metric_depth", output_index=1,
                               confidence_index=bad))
    with pytest.raises(ValueError, match=r"output 0 \('out_K'\) has shape \[1, 3, 3\], not "
                       "one confidence image"):
        OnnxDepthBackend(C(model=path, kind="metric_depth", output_index=1,
                           confidence_index=0))


def test_depth_stage_records_what_the_confidence_kept(tmp_path: Path) -> None:
    import csv

    from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

    from toolkit.depth.stage import DepthStage
    from toolkit.fusion.synthetic import write_box_room

    path = _confidence_model(tmp_path / "conf.onnx", [1, 3, "h", "w"])
    seq_dir = write_box_room(tmp_path / "seq", n_frames=2)  # 160x120 images
    res = run_stages(tmp_path, [{"stage": "t_sequence", "path": str(seq_dir)},
                                {"stage": "depth", "model": str(path), "threads": 1,
                                 "output": "metric_depth", "output_index": 1,
                                 "confidence_index": 3, "min_confidence": 0.5,
                                 "mean": [0, 0, 0], "std": [1, 1, 1],
                                 "input_size": [120, 160], "multiple_of": 1}],
                     {"t_sequence": SequenceFolder, "depth": DepthStage})
    assert res.ok, res.error
    folder = tmp_path / "run" / "depth"
    with open(folder / "depth" / "index.csv") as f:
        rows = list(csv.DictReader(f))
    fractions = [float(r["confident_fraction"]) for r in rows]
    assert len(fractions) == 2 and all(0.0 <= v <= 1.0 for v in fractions)
    assert res.metrics["depth"]["confident_fraction_mean"] == pytest.approx(np.mean(fractions))
    report = (tmp_path / "run" / "report.md").read_text()
    assert f"kept {100 * np.mean(fractions):.1f} % of the pixels with depth" in report
