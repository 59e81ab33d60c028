"""Depth backends: onnx preprocessing/output handling exact on a tiny model; simulated
predictions follow their documented error model; the depth folder round-trips."""

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from onnx_graphs import save_graph  # the tests folder is on sys.path

from toolkit.depth.protocol import DepthPrediction
from toolkit.depth.simulated import (
    PRESETS,
    SimulatedDepthBackend,
    SimulatedDepthParams,
    low_texture_weight,
)
from toolkit.depth.store import DepthStore, DepthStoreWriter
from toolkit.errors import MissingInputError

pytestmark = pytest.mark.filterwarnings(
    "ignore:You are using the legacy TorchScript:DeprecationWarning",
    "ignore:The feature will be removed:DeprecationWarning")

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")


class Tiny(torch.nn.Module):
    """A 1x1 conv with known weights, then softplus so depth stays positive; the output
    is [1, 1, h, w] or [1, h, w] depending on ``squeeze``."""

    def __init__(self, squeeze: bool = False) -> None:
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 1, 1)
        with torch.no_grad():
            self.conv.weight[:] = torch.tensor([0.5, -0.25, 1.0]).view(1, 3, 1, 1)
            self.conv.bias[:] = 0.1
        self.squeeze = squeeze

    def forward(self, x: "torch.Tensor") -> "torch.Tensor":
        y = torch.nn.functional.softplus(self.conv(x))
        return y[:, 0] if self.squeeze else y


def _export(path: Path, hw: tuple[int, int] | None, squeeze: bool = False,
            props: dict[str, str] | None = None) -> Path:
    import onnx

    model = Tiny(squeeze).eval()
    h, w = hw or (28, 42)
    dyn = None if hw else {"image": {2: "h", 3: "w"}, "depth": {1: "h", 2: "w"} if squeeze
                                     else {2: "h", 3: "w"}}
    torch.onnx.export(model, (torch.zeros(1, 3, h, w),), str(path), input_names=["image"],
                      output_names=["depth"], dynamic_axes=dyn, dynamo=False)
    if props:
        m = onnx.load(str(path))
        onnx.helper.set_model_props(m, props)
        onnx.save(m, str(path))
    return path


def _reference(rgb: np.ndarray, hw: tuple[int, int], mean: np.ndarray, std: np.ndarray,
               bgr: bool, interp: int = cv2.INTER_CUBIC) -> np.ndarray:
    """What the backend must compute, spelled out step by step."""
    img = rgb[..., ::-1] if bgr else rgb
    img = cv2.resize(np.ascontiguousarray(img), (hw[1], hw[0]), interpolation=interp)
    x = (img.astype(np.float32) / 255.0 - mean) / std
    with torch.no_grad():
        y = Tiny()(torch.from_numpy(x.transpose(2, 0, 1)[None].copy())).numpy()[0, 0]
    return cv2.resize(y, (rgb.shape[1], rgb.shape[0]), interpolation=cv2.INTER_LINEAR)


@pytest.fixture
def rgb() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (45, 61, 3), dtype=np.uint8)


def test_onnx_backend_is_exact_on_a_tiny_model(tmp_path: Path, rgb: np.ndarray) -> None:
    from toolkit.depth.onnx_backend import IMAGENET_MEAN, IMAGENET_STD, OnnxDepthBackend
    from toolkit.depth.onnx_backend import OnnxDepthConfig as C

    path = _export(tmp_path / "tiny.onnx", (28, 42))
    be = OnnxDepthBackend(C(model=path, kind="relative_depth", threads=1))
    x = be.preprocess(rgb)
    assert x.shape == (1, 3, 28, 42) and x.dtype == np.float32  # fixed input read from file
    pred = be.predict(rgb)
    assert isinstance(pred, DepthPrediction) and pred.values.shape == rgb.shape[:2]
    assert pred.kind == "relative_depth" and pred.latency_s > 0
    ref = _reference(rgb, (28, 42), np.array(IMAGENET_MEAN, np.float32),
                     np.array(IMAGENET_STD, np.float32), bgr=False)
    np.testing.assert_allclose(pred.values, ref, rtol=1e-5, atol=1e-6)
    # Other normalisation and channel order.
    mean, std = (0.5, 0.5, 0.5), (0.25, 0.5, 1.0)
    be2 = OnnxDepthBackend(C(model=path, kind="metric_depth", mean=mean, std=std,
                             channel_order="bgr", interpolation="linear", threads=1))
    ref2 = _reference(rgb, (28, 42), np.array(mean, np.float32), np.array(std, np.float32),
                      bgr=True, interp=cv2.INTER_LINEAR)
    np.testing.assert_allclose(be2.predict(rgb).values, ref2, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match=r"fixed input of height 28, width 42, but "
                                         r"input_size asks for \[56, 56\]"):
        OnnxDepthBackend(C(model=path, kind="relative_depth", input_size=56)).predict(rgb)
    # A BGR network with the default normalisation: ImageNet's mean and std in its channel
    # order, so an image of the ImageNet mean colour goes in as zeros (they were applied
    # R, G, B to B, G, R channels: -0.34 / +0.36).
    be3 = OnnxDepthBackend(C(model=path, kind="relative_depth", channel_order="bgr",
                             threads=1))
    grey = np.empty_like(rgb)
    grey[:] = np.round(np.array(IMAGENET_MEAN) * 255).astype(np.uint8)
    assert np.abs(be3.preprocess(grey)).max() < 0.01
    ref3 = _reference(rgb, (28, 42), np.array(IMAGENET_MEAN[::-1], np.float32),
                      np.array(IMAGENET_STD[::-1], np.float32), bgr=True)
    np.testing.assert_allclose(be3.predict(rgb).values, ref3, rtol=1e-5, atol=1e-6)



def test_onnx_device_choice(tmp_path: Path, rgb: np.ndarray) -> None:
    import onnxruntime as ort

    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig, execution_providers

    cpu, cuda = "CPUExecutionProvider", "CUDAExecutionProvider"
    assert execution_providers("auto", [cpu]) == [cpu]
    assert execution_providers("auto", [cuda, cpu]) == [cuda, cpu]
    assert execution_providers("cpu", [cuda, cpu]) == [cpu]
    assert execution_providers("cuda", [cuda, cpu]) == [cuda, cpu]
    with pytest.raises(ValueError, match="pip install onnxruntime-gpu"):
        execution_providers("cuda", [cpu])
    path = _export(tmp_path / "tiny.onnx", (28, 42))
    be = OnnxDepthBackend(OnnxDepthConfig(model=path, kind="relative_depth", device="cpu"))
    assert be.providers == [cpu] and be.describe()["providers"] == [cpu]
    if cuda not in ort.get_available_providers():  # this machine's CPU-only build
        with pytest.raises(ValueError, match="no CUDA provider"):
            OnnxDepthBackend(OnnxDepthConfig(model=path, kind="relative_depth", device="cuda"))
        # Through the stage: a clean error naming the fix, before any frame.
        from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

        from toolkit.depth.stage import DepthStage
        from toolkit.fusion.synthetic import write_box_room

        seq = write_box_room(tmp_path / "seq", n_frames=2)
        res = run_stages(tmp_path, [{"stage": "t_sequence", "path": str(seq)},
                                    {"stage": "depth", "model": str(path),
                                     "output": "relative_depth", "device": "cuda"}],
                         {"t_sequence": SequenceFolder, "depth": DepthStage})
        assert not res.ok and "onnxruntime-gpu" in res.error and "device: cpu" in res.error


def test_onnx_dynamic_input_sizes_and_metadata(tmp_path: Path, rgb: np.ndarray) -> None:
    from toolkit.depth.onnx_backend import OnnxDepthBackend
    from toolkit.depth.onnx_backend import OnnxDepthConfig as C

    path = _export(tmp_path / "dyn.onnx", None, squeeze=True,
                   props={"depth_kind": "relative_disparity", "input_height": "56",
                          "input_width": "70", "mean": "0,0,0", "std": "1,1,1"})
    be = OnnxDepthBackend(C(model=path, threads=1))
    assert be.kind == "relative_disparity"  # from the metadata
    assert be.preprocess(rgb).shape == (1, 3, 56, 70)
    ref = _reference(rgb, (56, 70), np.zeros(3, np.float32), np.ones(3, np.float32), False)
    np.testing.assert_allclose(be.predict(rgb).values, ref, rtol=1e-5, atol=1e-6)
    # keep_aspect: height 140 -> width from the 61:45 image, rounded to a multiple of 14.
    be3 = OnnxDepthBackend(C(model=path, input_size=140, resize="keep_aspect", threads=1))
    assert be3.input_hw((45, 61)) == (140, 196)
    assert be3.predict(rgb).values.shape == (45, 61)


def test_onnx_output_handling(tmp_path: Path) -> None:
    from toolkit.depth.onnx_backend import OnnxDepthBackend
    from toolkit.depth.onnx_backend import OnnxDepthConfig as C

    path = _export(tmp_path / "t.onnx", (28, 42))
    raw = np.array([[[[1.0, -2.0], [np.inf, 4.0]]]], np.float32)
    depth = OnnxDepthBackend(C(model=path, kind="metric_depth", output_scale=0.001))
    out = depth.postprocess(raw, (2, 2))
    np.testing.assert_array_equal(np.isnan(out), [[False, True], [True, False]])
    assert out[1, 1] == pytest.approx(0.004)  # millimetres to metres
    disp = OnnxDepthBackend(C(model=path, kind="relative_disparity"))
    out = disp.postprocess(raw, (4, 4))  # resized; negative disparity kept (shift unknown)
    assert out.shape == (4, 4) and (out[np.isfinite(out)] < 0).any()


def test_missing_model_says_where_to_put_it(tmp_path: Path) -> None:
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    missing = tmp_path / "models" / "depth_anything_v2_vits.onnx"
    with pytest.raises(FileNotFoundError) as e:
        OnnxDepthBackend(OnnxDepthConfig(model=missing, kind="relative_disparity"))
    assert str(missing) in str(e.value) and "never downloads" in str(e.value)


def test_missing_relative_model_names_the_absolute_place(tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A recipe's relative 'model' is read from the working directory: the error says
    which folder that is, so a run started outside the repository is told where the file
    must go (it named only 'datasets/models/small-depth.onnx', which exists in the repo)."""
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig, model_problem

    monkeypatch.chdir(tmp_path)
    cfg = OnnxDepthConfig(model=Path("datasets/models/small-depth.onnx"))
    place = str(tmp_path / "datasets" / "models" / "small-depth.onnx")
    with pytest.raises(FileNotFoundError) as e:
        OnnxDepthBackend(cfg)
    assert place in str(e.value) and "working directory" in str(e.value)
    assert place in (model_problem(cfg) or "")  # the depth stage's check before the run


def _onnx_recipe(tmp_path: Path, model: Path | str) -> Path:
    """``tmp_path/r.yaml``: a simulated sequence, then depth by the ONNX network ``model``."""
    recipe = tmp_path / "r.yaml"
    recipe.write_text(f"""name: r
output: {tmp_path / 'run'}
stages:
  - stage: simulate
  - stage: depth
    backend: onnx
    output: relative_disparity
    model: {model}
""")
    return recipe


def test_a_folder_as_model_is_found_before_the_run(tmp_path: Path) -> None:
    from toolkit.recipe.runner import missing_inputs
    from toolkit.recipe.schema import load_recipe

    (tmp_path / "models").mkdir()
    recipe = _onnx_recipe(tmp_path, tmp_path / "models")
    problems = missing_inputs(load_recipe(recipe))
    assert len(problems) == 1 and "is a folder; give the .onnx file in it" in problems[0]
    # A Git LFS pointer or any file that is no ONNX model: found by validate too (it failed
    # in onnxruntime with INVALID_PROTOBUF after the stages before depth had run).
    for text, why in (("version https://git-lfs.github.com/spec/v1\n", "Git LFS pointer"),
                      ("<html>not found</html>", "not an ONNX model")):
        model = tmp_path / "model.onnx"
        model.write_text(text)
        recipe.write_text(recipe.read_text().replace(str(tmp_path / "models"), str(model)))
        problems = missing_inputs(load_recipe(recipe))
        assert len(problems) == 1 and why in problems[0], problems


def test_the_depth_key_holds_the_models_content_not_its_path(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The same model file in another folder (a moved checkout, a git worktree) keeps the
    depth stage cached; other weights copied over it, of the same size and with its mtime
    kept (``cp -p``, ``rsync -a``), rerun it."""
    import os

    from toolkit.recipe import runner
    from toolkit.recipe.schema import load_recipe

    def key(model: Path | str) -> str:
        spec = load_recipe(_onnx_recipe(tmp_path, model)).stages[1]
        return runner._cache_key(spec, spec.cls(spec.config), {"sequence": "token"})

    weights = bytes(range(256)) * 64
    here = tmp_path / "main" / "datasets" / "models" / "small-depth.onnx"
    there = tmp_path / "worktree" / "datasets" / "models" / "small-depth.onnx"
    for path in (here, there):
        path.parent.mkdir(parents=True)
        path.write_bytes(weights)
    assert key(here) == key(there)
    monkeypatch.chdir(tmp_path / "worktree")
    assert key("datasets/models/small-depth.onnx") == key(here)
    before = here.stat()
    here.write_bytes(weights[::-1])  # other weights, the same size
    os.utime(here, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert here.stat().st_size == before.st_size
    assert key(here) != key(there)


def test_a_model_with_external_weights_is_keyed_by_them_too(tmp_path: Path) -> None:
    """A network saved with its weights in a file of its own (``model.onnx.data``, exports
    over 2 GB) is that file too: other weights copied over it rerun the depth stage, and a
    missing one is found before the run."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from toolkit.depth.onnx_backend import external_data_files
    from toolkit.recipe import runner
    from toolkit.recipe.runner import missing_inputs
    from toolkit.recipe.schema import load_recipe

    model_path = tmp_path / "models" / "big.onnx"
    model_path.parent.mkdir()
    weights = numpy_helper.from_array(np.full((1, 3, 1, 1), 0.5, np.float32), "w")
    graph = helper.make_graph(
        [helper.make_node("Mul", ["image", "w"], ["depth"])], "g",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 28, 28])],
        [helper.make_tensor_value_info("depth", TensorProto.FLOAT, None)], [weights])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    onnx.save_model(model, str(model_path), save_as_external_data=True,
                    all_tensors_to_one_file=True, location="big.onnx.data", size_threshold=0)
    data = tmp_path / "models" / "big.onnx.data"
    assert external_data_files(model_path) == [data]
    save_graph(tmp_path / "inside.onnx", [helper.make_node("Identity", ["image"], ["depth"])],
               [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 28, 28])])
    assert external_data_files(tmp_path / "inside.onnx") == []
    assert external_data_files(tmp_path / "r.yaml") == []  # not a model: no error here

    recipe = load_recipe(_onnx_recipe(tmp_path, model_path))
    spec = recipe.stages[1]

    def key() -> str:
        return runner._cache_key(spec, spec.cls(spec.config), {"sequence": "token"})

    before = key()
    data.write_bytes(data.read_bytes()[::-1])  # other weights, the same graph file
    assert key() != before
    data.unlink()
    assert any("big.onnx.data does not exist" in p for p in missing_inputs(recipe))


# ------------------------------------------------------------------ simulated


def _scene() -> tuple[np.ndarray, np.ndarray]:
    h, w = 90, 120
    z = np.full((h, w), 4.0, np.float32)
    z[20:70, 30:60] = 2.0  # a box in front of a wall
    z[:, :5] = 0.0  # invalid ground truth
    rng = np.random.default_rng(1)
    rgb = np.full((h, w, 3), 128, np.uint8)
    rgb[:, w // 2:] = rng.integers(0, 256, (h, w - w // 2, 3), dtype=np.uint8)  # texture
    return rgb, z


def test_simulated_scale_only_is_exact_scale() -> None:
    rgb, z = _scene()
    be = SimulatedDepthBackend(SimulatedDepthParams(**PRESETS["scale_only"], scale=1.7))
    p = be.predict(rgb, gt_depth=z, frame_index=3)
    ok = z > 0
    np.testing.assert_allclose(p.values[ok], 1.7 * z[ok], rtol=1e-6)
    assert p.extra["true_scale"] == pytest.approx(1.7)
    assert np.isnan(p.values[~ok]).all()  # no ground truth, no prediction


def test_simulated_edge_blur_leaves_holes_out_of_their_borders() -> None:
    # A wall at 2 m with a missing pixel and a NaN line: filled with 20 m and blurred, the
    # pixels beside them came out 51 % and 192 % too far.
    z = np.full((40, 60), 2.0, np.float32)
    z[10, 10] = 0.0
    z[25, :] = np.nan
    rgb = np.zeros((40, 60, 3), np.uint8)
    be = SimulatedDepthBackend(SimulatedDepthParams(**{**PRESETS["scale_only"],
                                                       "edge_blur_px": 1.5}, scale=1.0))
    p = be.predict(rgb, gt_depth=z, frame_index=0).values
    ok = np.isfinite(z) & (z > 0)
    np.testing.assert_allclose(p[ok], 2.0, rtol=1e-5)
    assert np.isnan(p[~ok]).all()
    d = SimulatedDepthBackend(SimulatedDepthParams(**PRESETS["scale_only"], scale=1.0,
                                                   shift=0.2, kind="relative_disparity"))
    disp = d.predict(rgb, gt_depth=z, frame_index=0).values
    np.testing.assert_allclose(disp[ok], 0.5 * 1.2, rtol=1e-5)  # median over the valid


def test_simulated_disparity_is_affine_in_inverse_depth() -> None:
    rgb, z = _scene()
    be = SimulatedDepthBackend(SimulatedDepthParams(**PRESETS["scale_only"], scale=0.8,
                                                    shift=0.2, kind="relative_disparity"))
    p = be.predict(rgb, gt_depth=z, frame_index=0)
    ok = z > 0
    A = np.stack([p.values[ok], np.ones(ok.sum())], 1)
    coef, *_ = np.linalg.lstsq(A, 1.0 / z[ok], rcond=None)
    np.testing.assert_allclose(A @ coef, 1.0 / z[ok], rtol=1e-5)
    assert coef[0] == pytest.approx(0.8, rel=1e-5) and coef[1] < 0  # shift to undo


def test_simulated_errors_are_seeded_and_as_documented() -> None:
    rgb, z = _scene()
    params = SimulatedDepthParams(scale=1.0, wander_sigma=0.05, distortion=0.03, noise=0.02,
                                  low_texture_gain=2.0)
    a = SimulatedDepthBackend(params).predict(rgb, gt_depth=z, frame_index=7).values
    b = SimulatedDepthBackend(params).predict(rgb, gt_depth=z, frame_index=7).values
    np.testing.assert_array_equal(a, b)
    c = SimulatedDepthBackend(params.model_copy(update={"seed": 5})).predict(
        rgb, gt_depth=z, frame_index=7).values
    assert not np.allclose(a, c)
    be = SimulatedDepthBackend(params)
    scales = np.array([be.frame_scale(i) for i in range(2000)])
    # Frame i's scale does not depend on which frames were asked for before (a depth stage
    # resumed at frame 300 predicts what an uninterrupted one did).
    resumed = SimulatedDepthBackend(params)
    asked = [300, 0, 1999, 7, 256, 255, 1024, 511]
    assert [resumed.frame_scale(i) for i in asked] == [scales[i] for i in asked]
    assert 0.02 < np.std(np.log(scales)) < 0.1  # wander near its stationary std
    assert abs(np.log(scales[1:] / scales[:-1])).max() < 0.05  # and slow
    # Worse on the flat half than on the textured half (same depth: the wall at 4 m).
    p = be.predict(rgb, gt_depth=z, frame_index=0).values / be.frame_scale(0)
    rel = np.abs(np.log(p / 4.0))
    flat, tex = rel[75:, 5:55], rel[75:, 70:]
    assert np.std(np.log(p[75:, 5:55])) > 1.5 * np.std(np.log(p[75:, 70:]))
    assert flat.mean() > 0 and tex.mean() > 0
    w = low_texture_weight(rgb, 6.0)
    assert w[45, 20] == 1.0 and w[45, 100] < 0.1


@pytest.mark.parametrize("damage, expect", [
    (("meta.json", '{"kind": "relative_disp'), r"meta\.json: not a JSON file"),
    (("meta.json", "[1, 2]"), r"meta\.json: holds list, not a mapping with field 'kind'"),
    (("index.csv", "stamp,file\n1.5,frames/000000.npy\n"), r"index\.csv: no column 'index'"),
    (("index.csv", "index,stamp\n0,1.5\n"), r"index\.csv: no column 'file'"),
    (("index.csv", "index,stamp,file\n0,1.5,frames/000000.npy\nx,1.7,f.npy\n"),
     r"index\.csv:3: field 'index' is 'x', not a frame number"),
    (("index.csv", None), r"index\.csv: not there, but .*meta\.json is"),
])
def test_depth_store_names_the_damaged_file_and_field(tmp_path: Path, damage, expect) -> None:
    """A damaged depth folder is an input error naming the file, the field and the fix;
    a bad meta.json was a JSONDecodeError, an index.csv without its 'index' column a
    KeyError, both shown by the runner as bugs."""
    from toolkit.errors import InputError

    w = DepthStoreWriter(tmp_path / "d", "relative_disparity", {"backend": "test"})
    w.add(0, 1.5, DepthPrediction(np.ones((4, 6), np.float32), "relative_disparity", 0.01))
    w.close()
    name, text = damage
    if text is None:
        (tmp_path / "d" / name).unlink()
    else:
        (tmp_path / "d" / name).write_text(text)
    with pytest.raises((InputError, MissingInputError), match=expect) as err:
        DepthStore(tmp_path / "d")
    assert str(err.value).startswith(str(tmp_path / "d" / name)), err.value
    assert "Fix: run the depth stage again" in str(err.value), err.value


def test_simulated_needs_ground_truth() -> None:
    rgb, _ = _scene()
    with pytest.raises(ValueError, match="ground-truth depth"):
        SimulatedDepthBackend().predict(rgb)


def test_depth_store_round_trip(tmp_path: Path) -> None:
    vals = np.random.default_rng(0).random((6, 8)).astype(np.float32)
    vals[0, 0] = np.nan
    w = DepthStoreWriter(tmp_path / "d", "relative_disparity", {"backend": "test"})
    w.add(0, 1.5, DepthPrediction(vals, "relative_disparity", 0.01, {"true_scale": 2.0}))
    w.add(2, 1.7, DepthPrediction(vals * 2, "relative_disparity", 0.02))
    w.close()
    s = DepthStore(tmp_path / "d")
    assert s.kind == "relative_disparity" and s.indices == [0, 2] and not s.has(1)
    p = s.read(0)
    np.testing.assert_array_equal(p.values, vals)
    assert p.extra["true_scale"] == 2.0 and s.meta["backend"] == "test"
    np.testing.assert_allclose(s.latencies(), [0.01, 0.02])
    z = p.as_depth(2.0, 0.1)
    assert z[1, 1] == pytest.approx(1 / (2 * vals[1, 1] + 0.1))
    # A frame it holds no prediction for: a KeyError naming the folder, shown as a bug.
    with pytest.raises(MissingInputError, match=re.escape(
            f"{tmp_path / 'd' / 'index.csv'}: field 'index' lists no frame 1 (it holds 2 "
            "frames, 0 to 2)") + ".*Fix: run the depth stage again"):
        s.read(1)


def test_depth_store_float16_writes_what_it_cannot_hold_as_invalid_and_counts_it(
        tmp_path: Path) -> None:
    """float16 made values above 65504 inf (a depth, or a disparity of 0, downstream) and
    non-zero values below 2^-24 / 2 zero (no depth), silently: now NaN and counted, and
    +-2^-24, as write_depth's PNG writes 0 beyond its range and one quantum below it."""
    tiny = float(np.finfo(np.float16).smallest_subnormal)  # 2^-24, 5.96e-8
    vals = np.array([[7e4, -1e6, 65504.0, 65519.0, 1.0, 0.0],
                     [1e-9, -1e-9, 2.0**-25, np.nan, np.inf, 2.5]], np.float32)  # [2, 6]
    want = np.array([[np.nan, np.nan, 65504.0, 65504.0, 1.0, 0.0],
                     [tiny, -tiny, tiny, np.nan, np.inf, 2.5]], np.float32)
    root = tmp_path / "d"
    w = DepthStoreWriter(root, "relative_disparity", dtype="float16", resume_key="k")
    assert w.add(0, 0.0, DepthPrediction(vals, "relative_disparity")) == 2
    assert w.add(1, 1.0, DepthPrediction(vals[::-1], "relative_disparity")) == 2
    del w  # killed: the counts of the frames kept come back with them
    w = DepthStoreWriter(root, "relative_disparity", dtype="float16", resume_key="k")
    assert w.resumed == 2 and w.beyond_float16 == 4
    assert w.add(2, 2.0, DepthPrediction(np.ones((2, 6), np.float32), "relative_disparity")) == 0
    w.close()
    s = DepthStore(root)
    np.testing.assert_array_equal(s.read(0).values, want)
    np.testing.assert_array_equal(s.read(1).values, want[::-1])
    assert [r.get("beyond_float16") for r in s.rows] == ["2", "2", ""]
    # float32 keeps every value as given.
    w32 = DepthStoreWriter(tmp_path / "d32", "relative_disparity")
    assert w32.add(0, 0.0, DepthPrediction(vals, "relative_disparity")) == 0
    w32.close()
    np.testing.assert_array_equal(DepthStore(tmp_path / "d32").read(0).values, vals)


def test_depth_stage_reports_the_pixels_float16_could_not_hold(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

    from toolkit.depth.stage import DepthStage
    from toolkit.fusion.synthetic import write_box_room

    predict = SimulatedDepthBackend.predict

    def far_corner(self: SimulatedDepthBackend, rgb: np.ndarray, **kw: object) -> object:
        pred = predict(self, rgb, **kw)  # type: ignore[arg-type]
        pred.values[:3, :4] = 1e5  # [3, 4] beyond float16 in every frame
        return pred

    monkeypatch.setattr(SimulatedDepthBackend, "predict", far_corner)
    seq = write_box_room(tmp_path / "seq", n_frames=2)
    res = run_stages(tmp_path, [{"stage": "t_sequence", "path": str(seq)},
                                {"stage": "depth", "backend": "simulated",
                                 "dtype": "float16"}],
                     {"t_sequence": SequenceFolder, "depth": DepthStage})
    assert res.ok, res.error
    assert res.metrics["depth"]["pixels_beyond_float16"] == 24
    assert "24 pixels beyond float16's range" in (tmp_path / "run/report.md").read_text()
    v = DepthStore(tmp_path / "run/depth/depth").read(1).values
    assert np.isnan(v[:3, :4]).all() and not np.isinf(v).any()


def test_depth_store_keeps_an_interrupted_writers_frames_under_the_same_key(
        tmp_path: Path) -> None:
    vals = np.arange(12, dtype=np.float32).reshape(3, 4)
    root = tmp_path / "d"
    w = DepthStoreWriter(root, "metric_depth", resume_key="k1")
    for i in range(3):
        w.add(i, float(i), DepthPrediction(vals + i, "metric_depth", 0.01))
    del w  # killed before close(): no index, no meta
    (root / "frames" / "000007.npy").write_bytes(b"half a file")  # not journaled
    with (root / "journal.jsonl").open("a") as f:
        f.write('{"index": "3", "sta')  # a line torn by the kill
    w = DepthStoreWriter(root, "metric_depth", resume_key="k1")
    assert w.resumed == 3 and w.done == {0, 1, 2}
    assert not (root / "frames" / "000007.npy").exists()
    w.add(3, 3.0, DepthPrediction(vals + 3, "metric_depth", 0.02))
    w.close()
    s = DepthStore(root)
    assert s.indices == [0, 1, 2, 3] and s.meta["height"] == 3 and s.meta["width"] == 4
    np.testing.assert_array_equal(s.read(2).values, vals + 2)
    # The journal outlives close(): a kill before the stage is recorded finished keeps all.
    assert DepthStoreWriter(root, "metric_depth", resume_key="k1").done == {0, 1, 2, 3}
    # Other settings (another key) start from nothing.
    w = DepthStoreWriter(root, "metric_depth", resume_key="k2")
    assert w.resumed == 0 and not list((root / "frames").glob("*.npy"))


def test_depth_store_predicts_again_a_journaled_frame_cut_short(tmp_path: Path) -> None:
    """A frame file truncated after it was journaled (power loss, a hand) is not kept on
    resume: it used to be, the stage finished, and fuse failed on it naming no file."""
    vals = np.arange(12, dtype=np.float32).reshape(3, 4)
    root = tmp_path / "d"
    w = DepthStoreWriter(root, "metric_depth", resume_key="k1")
    for i in range(4):
        w.add(i, float(i), DepthPrediction(vals + i, "metric_depth", 0.01))
    del w  # killed before close()
    frame = root / "frames" / "000002.npy"
    frame.write_bytes(frame.read_bytes()[:100])  # the header and a few values
    (root / "frames" / "000003.npy").write_bytes(b"")  # a file that never got its data
    w = DepthStoreWriter(root, "metric_depth", resume_key="k1")
    assert w.done == {0, 1} and w.resumed == 2
    assert not frame.exists()
    for i in (2, 3):
        w.add(i, float(i), DepthPrediction(vals + i, "metric_depth", 0.01))
    w.close()
    np.testing.assert_array_equal(DepthStore(root).read(2).values, vals + 2)


def test_depth_stage_records_the_network_input_it_used(tmp_path: Path) -> None:
    """meta.json's input_hw is the input after rounding to whole patches (it was null)."""
    import json

    from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

    from toolkit.depth.stage import DepthStage
    from toolkit.fusion.synthetic import write_box_room

    path = _export(tmp_path / "dyn.onnx", None, squeeze=True)
    seq = write_box_room(tmp_path / "seq", n_frames=2)  # 160x120 images
    res = run_stages(tmp_path, [{"stage": "t_sequence", "path": str(seq)},
                                {"stage": "depth", "model": str(path), "threads": 1,
                                 "output": "relative_depth", "input_size": [120, 160]}],
                     {"t_sequence": SequenceFolder, "depth": DepthStage})
    assert res.ok, res.error
    meta = json.loads((tmp_path / "run" / "depth" / "depth" / "meta.json").read_text())
    assert meta["input_hw"] == [126, 154]  # multiples of 14


def test_depth_stage_resumes_after_an_interruption(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

    from toolkit.depth.stage import DepthStage
    from toolkit.fusion.synthetic import write_box_room

    seq = write_box_room(tmp_path / "seq", n_frames=8)
    stages = [{"stage": "t_sequence", "path": str(seq)},
              {"stage": "depth", "backend": "simulated"}]
    register = {"t_sequence": SequenceFolder, "depth": DepthStage}
    for d in ("full", "cut"):
        (tmp_path / d).mkdir()
    full = run_stages(tmp_path / "full", stages, register)
    assert full.ok, full.error
    calls: list[int] = []
    predict = SimulatedDepthBackend.predict

    def dies_at_frame_5(self: SimulatedDepthBackend, rgb: np.ndarray, **kw: object) -> object:
        if kw["frame_index"] == 5 and not calls.count(-1):
            calls.append(-1)
            raise RuntimeError("killed")
        calls.append(int(kw["frame_index"]))  # type: ignore[call-overload]
        return predict(self, rgb, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(SimulatedDepthBackend, "predict", dies_at_frame_5)
    first = run_stages(tmp_path / "cut", stages, register)
    assert not first.ok and calls == [0, 1, 2, 3, 4, -1]
    calls.clear()
    calls.append(-1)  # no second kill
    again = run_stages(tmp_path / "cut", stages, register)
    assert again.ok, again.error
    assert calls == [-1, 5, 6, 7] and again.metrics["depth"]["frames_resumed"] == 5
    a = DepthStore(tmp_path / "full/run/depth/depth")
    b = DepthStore(tmp_path / "cut/run/depth/depth")
    assert a.indices == b.indices == list(range(8))
    for i in a.indices:
        np.testing.assert_array_equal(a.read(i).values, b.read(i).values)
    assert "5 kept from an interrupted run" in (tmp_path / "cut/run/report.md").read_text()
    # The sample figure shows the first frame either way (a resumed run drew frame 5).
    fig = "run/depth/depth_sample.png"
    assert (tmp_path / "full" / fig).read_bytes() == (tmp_path / "cut" / fig).read_bytes()


def test_depth_stage_killed_after_its_last_frame_predicts_nothing_again(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

    from toolkit.depth.stage import DepthStage
    from toolkit.fusion.synthetic import write_box_room

    seq = write_box_room(tmp_path / "seq", n_frames=4)
    stages = [{"stage": "t_sequence", "path": str(seq)},
              {"stage": "depth", "backend": "simulated"}]
    register = {"t_sequence": SequenceFolder, "depth": DepthStage}
    close = DepthStoreWriter.close

    def killed(self: DepthStoreWriter) -> Path:
        raise RuntimeError("killed before the index was written")

    monkeypatch.setattr(DepthStoreWriter, "close", killed)
    assert not run_stages(tmp_path, stages, register).ok
    monkeypatch.setattr(DepthStoreWriter, "close", close)
    calls: list[int] = []
    predict = SimulatedDepthBackend.predict
    monkeypatch.setattr(SimulatedDepthBackend, "predict",
                        lambda self, rgb, **kw: calls.append(1) or predict(self, rgb, **kw))
    res = run_stages(tmp_path, stages, register)
    assert res.ok, res.error
    assert calls == [] and res.metrics["depth"]["frames_resumed"] == 4
    assert DepthStore(tmp_path / "run/depth/depth").indices == [0, 1, 2, 3]
    assert (tmp_path / "run/depth/depth_sample.png").stat().st_size > 1000

    # Killed after the index was written, before the stage was recorded as finished
    # (drawing its figure): the frames are still kept (the journal was deleted with the
    # index's writing, and every frame predicted again).
    import toolkit.depth.stage as depth_stage

    def killed_figure(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt("killed while drawing the sample figure")

    other = tmp_path / "killed_later"
    other.mkdir()
    with monkeypatch.context() as m:
        m.setattr(depth_stage, "sample_figure", killed_figure)
        with pytest.raises(KeyboardInterrupt):
            run_stages(other, stages, register)
    calls.clear()
    res = run_stages(other, stages, register)
    assert res.ok, res.error
    assert calls == [] and res.metrics["depth"]["frames_resumed"] == 4


# ------------------------------------------------------------------ small network


def test_small_network_loss_is_scale_invariant_and_sees_shape() -> None:
    from toolkit.depth.train_small import si_loss

    g = torch.Generator().manual_seed(0)
    depth = torch.rand(2, 1, 24, 32, generator=g) * 4 + 0.5
    depth[0, 0, :3] = 0  # invalid ground truth is masked out
    exact = torch.log(depth.clamp(min=1e-6))
    assert float(si_loss(exact, depth)) == pytest.approx(0.0, abs=1e-6)
    # Any constant added to the log prediction (a global scale) costs nothing...
    assert float(si_loss(exact + 1.7, depth)) == pytest.approx(0.0, abs=1e-5)
    # ...a wrong shape does, and the gradient term adds to it.
    warped = exact + 0.2 * torch.linspace(0, 1, 32)
    assert float(si_loss(warped, depth, grad_weight=0.0)) > 1e-3
    assert float(si_loss(warped, depth, 0.5)) > float(si_loss(warped, depth, 0.0))


def test_small_network_exports_with_its_preprocessing(tmp_path: Path, rgb: np.ndarray) -> None:
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig
    from toolkit.depth.train_small import TrainConfig, _to_input, export, make_model

    model = make_model((4, 8, 8, 8, 8)).eval()
    # Any input size runs (the stride-2 stages round up; the decoder resizes to each skip).
    with torch.no_grad():
        assert model(torch.zeros(1, 3, 45, 61)).shape == (1, 1, 45, 61)
    cfg = TrainConfig(out=tmp_path / "m.onnx", height=24, width=32)
    export(model, cfg)
    be = OnnxDepthBackend(OnnxDepthConfig(model=cfg.out, threads=1))
    assert be.kind == "relative_depth" and be.input_hw((480, 640)) == (24, 32)
    assert be.warning is None
    small = cv2.resize(rgb, (32, 24), interpolation=cv2.INTER_CUBIC)
    with torch.no_grad():
        ref = torch.exp(model(_to_input(small[None]))).numpy()[0, 0]
    out = be.session.run(None, {be.input_name: be.preprocess(small)})[0][0, 0]
    np.testing.assert_allclose(out, ref, rtol=1e-4)  # the ONNX file outputs exp(log depth)


def test_fine_tuning_starts_from_an_exported_model(tmp_path: Path) -> None:
    """An export's weights (BatchNorm folded into the convolutions) load into the network
    built without BatchNorm and give the same depth; other widths are refused by name."""
    from toolkit.depth.train_small import (
        TrainConfig,
        _training_text,
        export,
        load_onnx_weights,
        make_model,
        write_card,
    )

    torch.manual_seed(0)
    model = make_model((4, 8, 8, 8, 8))
    model.train()
    with torch.no_grad():  # running statistics away from their start: folding matters
        for _ in range(3):
            model(torch.randn(2, 3, 24, 32) * 2 + 0.5)
    model.eval()
    cfg = TrainConfig(out=tmp_path / "m.onnx", height=24, width=32)
    export(model, cfg)
    folded = make_model((4, 8, 8, 8, 8), norm=False)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    load_onnx_weights(folded, cfg.out)
    x = torch.randn(1, 3, 48, 64)
    with torch.no_grad():
        np.testing.assert_allclose(folded(x).numpy(), model(x).numpy(), atol=1e-4)
    with pytest.raises(ValueError, match="--widths"):
        load_onnx_weights(make_model((4, 8, 8, 8, 16), norm=False), cfg.out)
    # The card names both runs, each with its command.
    base = {"config": {"minutes": 45.0, "train_seeds": [101, 102], "threads": 2,
                       "widths": [4, 8, 8, 8, 8], "height": 120, "width": 160, "lr": 0.002},
            "iterations": 900, "train_seconds": 60.0, "train_cpu_seconds": 90.0,
            "data_seconds": 3.0, "validation": {"absrel": 0.05}}
    tuned = TrainConfig(out=tmp_path / "t.onnx", height=240, width=320, lr=3e-4,
                        init=cfg.out, train_seeds=(101, 102), widths=(4, 8, 8, 8, 8))
    text = _training_text(tuned, {"iterations": 50, "train_seconds": 30.0,
                                  "train_cpu_seconds": 50.0, "data_seconds": 2.0,
                                  "base": base}, "")
    flat = " ".join(text.split())  # the card wraps its lines
    assert f"--out {cfg.out}`" in flat and f"--init {cfg.out}" in flat
    assert "--height 240 --width 320 --lr 0.0003" in flat and "900 iterations" in flat
    assert "First from scratch" in flat and "at the larger input" in flat
    # A base that was itself a fine-tune at this size, its .train.json from an older
    # release without the CPU time: said so, and no KeyError after the model is written.
    base["config"].update(height=240, width=320, init="first.onnx")
    del base["train_cpu_seconds"]
    again = " ".join(_training_text(tuned, {"iterations": 50, "train_seconds": 30.0,
                                            "train_cpu_seconds": 50.0, "data_seconds": 2.0,
                                            "base": base}, "").split())
    assert "First a fine-tune of `first.onnx`" in again and "? min CPU" in again
    assert "larger input" not in again
    # Three runs: each named with its command, in order, whatever the chain's length.
    base["config"].update(height=120, width=160, init=None)
    second = {"config": {**base["config"], "height": 240, "width": 320, "lr": 3e-4,
                         "init": "s12.onnx"}, "iterations": 2267, "train_seconds": 1500.0,
              "validation": {"absrel": 0.04}, "base": base}
    third = TrainConfig(out=tmp_path / "t3.onnx", height=240, width=320, lr=2e-4,
                        init=tmp_path / "s17.onnx", train_seeds=(101, 102),
                        widths=(4, 8, 8, 8, 8))
    chain = " ".join(_training_text(third, {"iterations": 3763, "train_seconds": 3000.0,
                                            "base": second}, "").split())
    assert chain.startswith("**Training**, three runs")
    order = [chain.index(t) for t in ("First from scratch", "--out s12.onnx`",
                                      "Then fine-tuned from that file at the larger input",
                                      f"--out {tmp_path / 's17.onnx'}`", "2267 iterations",
                                      "Then fine-tuned from that file:",
                                      f"--out {third.out}`", "3763 iterations")]
    assert order == sorted(order)
    # A run whose file was copied before the next one started from it says where to.
    second["config"]["out"] = "scratch/s17.onnx"
    moved = " ".join(_training_text(third, {"iterations": 3763, "train_seconds": 3000.0,
                                            "base": second}, "").split())
    assert "--out scratch/s17.onnx`" in moved
    assert f"the file copied to `{tmp_path / 's17.onnx'}`" in moved
    assert chain.index("BatchNorm") < chain.index("Then fine-tuned")  # said of run 1's file
    # The card's data line names the first run's input size, not the previous run's.
    third.out.write_bytes(b"onnx")
    write_card(tmp_path / "card.md", third,
               {"iterations": 3763, "train_seconds": 3000.0, "base": second, "params": 1000,
                "images": 300, "validation": {"absrel": 0.04, "rmse_m": 0.2, "delta1": 0.98}})
    card = " ".join((tmp_path / "card.md").read_text().split())
    assert "(160x120 in the first run)" in card
    # The card says its commands do not replay the runs (the iterations and the schedule
    # follow the wall clock), and that the evaluation house is also where runs are chosen.
    assert "do not replay the runs" in card and "training seed 0" in card
    assert "compared and chosen on it" in card
    bad = tmp_path / "m.train.json"
    bad.write_text("{}")
    with pytest.raises(ValueError, match="not an ONNX model"):
        load_onnx_weights(make_model((4, 8, 8, 8, 8), norm=False), bad)


def test_shipped_small_model_fits_the_budget() -> None:
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    path = Path(__file__).resolve().parents[1] / "datasets" / "models" / "small-depth.onnx"
    assert path.stat().st_size <= 20e6  # the repository's limit for the shipped model
    be = OnnxDepthBackend(OnnxDepthConfig(model=path, threads=1))
    size = (int(be.metadata["input_height"]), int(be.metadata["input_width"]))
    assert be.kind == "relative_depth" and be.input_hw((480, 640)) == size
    frame = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    pred = be.predict(frame)
    assert pred.values.shape == (480, 640) and np.isfinite(pred.values).all()
    assert (pred.values > 0).all()


# ------------------------------------------------------------------ DA-V2-Small-sized export


def test_vit_dpt_export_runs_in_the_onnx_backend(tmp_path: Path, rgb: np.ndarray,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    """The bench's ViT/14 + DPT, shrunk so that it exports in a second: the exported file
    carries the metadata the depth stage needs, says it has random weights, and the
    backend resizes frames in and out of its fixed input at the chosen thread count."""
    import logging

    from toolkit.depth.bench_latency import (
        RANDOM_WEIGHTS_WARNING,
        export_onnx,
        quantize_int8,
        vit_s14_dpt,
    )
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    torch.manual_seed(0)
    model = vit_s14_dpt(dim=32, depth=4, heads=2, feats=8, outs=(8, 8, 16, 16)).eval()
    path = tmp_path / "da_tiny.onnx"
    export_onnx(model, path, 28, 42)
    with caplog.at_level(logging.WARNING, logger="toolkit.depth.onnx_backend"):
        be = OnnxDepthBackend(OnnxDepthConfig(model=path, threads=2))
    assert "RANDOM WEIGHTS" in caplog.text
    assert be.describe()["warning"] == RANDOM_WEIGHTS_WARNING and be.config.threads == 2
    assert be.kind == "relative_disparity" and be.input_hw((45, 61)) == (28, 42)
    x = be.preprocess(rgb)
    with torch.no_grad():
        ref = model(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(be.session.run(None, {be.input_name: x})[0], ref,
                               rtol=1e-4, atol=1e-5 * np.abs(ref).max())
    assert be.predict(rgb).values.shape == (45, 61)
    # The int8 copy keeps the metadata (and the warning) and still runs.
    q = tmp_path / "da_tiny_int8.onnx"
    quantize_int8(path, q)
    bq = OnnxDepthBackend(OnnxDepthConfig(model=q, threads=1))
    assert bq.warning == RANDOM_WEIGHTS_WARNING and bq.kind == "relative_disparity"
    assert bq.metadata["quantization"].startswith("dynamic int8")
    assert np.isfinite(bq.predict(rgb).values).any()


@pytest.mark.slow
def test_da_v2_small_sized_export_cli(tmp_path: Path) -> None:
    """Full size (24.7 M parameters, about 100 MB): the file a recipe can point at."""
    from toolkit.depth.bench_latency import main
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    path = tmp_path / "da_small_266x350.onnx"
    assert main(["--export", str(path), "--size", "266x350"]) == 0
    be = OnnxDepthBackend(OnnxDepthConfig(model=path, threads=2))
    assert be.warning and be.input_hw((480, 640)) == (266, 350)
    frame = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    assert be.predict(frame).values.shape == (480, 640)


def test_training_resumes_from_its_checkpoint(tmp_path: Path) -> None:
    """A run that finds ``<out>.ckpt`` continues from its iteration and time used; a
    checkpoint of another configuration is refused; a finished run removes it."""
    import torch

    from toolkit.depth.train_small import (
        TrainConfig,
        checkpoint_path,
        make_model,
        save_checkpoint,
        train,
    )

    cfg = TrainConfig(out=tmp_path / "m.onnx", train_seeds=(101,), images_per_house=3,
                      val_images=2, height=24, width=32, widths=(4, 8), batch=2,
                      minutes=5.0, max_iters=9, threads=1, cache=tmp_path / "cache",
                      checkpoint_minutes=5.0)
    torch.manual_seed(0)
    model = make_model(cfg.widths)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)  # type: ignore[attr-defined]
    rng = np.random.default_rng(3)
    save_checkpoint(checkpoint_path(cfg.out), cfg, model, opt, rng, 7, 60.0, 50.0)
    stats = train(cfg)
    assert stats["iterations"] == 9  # 7 from the checkpoint + 2 here
    assert stats["train_seconds"] >= 60.0  # the time budget counts the first run's minute
    assert not checkpoint_path(cfg.out).exists() and cfg.out.is_file()

    other = TrainConfig(**{**cfg.__dict__, "lr": 1e-3})
    save_checkpoint(checkpoint_path(cfg.out), cfg, model, opt, rng, 7, 60.0, 50.0)
    with pytest.raises(ValueError, match="lr: checkpoint 0.002, now 0.001"):
        train(other)


def test_training_set_is_filled_house_by_house(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The renders of every house in order, as each house's own; more than memory holds
    is refused before any render, naming --houses."""
    import toolkit.depth.train_small as ts

    cfg = ts.TrainConfig(train_seeds=(101, 102), images_per_house=2, height=24, width=32,
                         cache=tmp_path / "cache")
    X, D = ts.load_training_set(cfg)
    assert X.shape == (4, 24, 32, 3) and X.dtype == np.uint8 and D.shape == (4, 24, 32)
    for k, seed in enumerate(cfg.train_seeds):
        imgs, depth = ts.load_or_render(seed, 2, cfg)
        assert np.array_equal(X[2 * k:2 * k + 2], imgs)
        assert np.array_equal(D[2 * k:2 * k + 2], depth)
    assert ts.training_set_bytes(cfg) == 4 * 24 * 32 * 7
    monkeypatch.setattr(ts, "_available_bytes", lambda: 10_000)
    monkeypatch.setattr(ts, "load_or_render", lambda *a: pytest.fail("rendered anyway"))
    with pytest.raises(MemoryError, match=r"2 houses x 2 renders at 32x24 .* fewer --houses"):
        ts.load_training_set(cfg)


def test_training_widths_from_the_command_line() -> None:
    import argparse

    from toolkit.depth.train_small import _widths

    assert _widths("16,32,64,96,128") == (16, 32, 64, 96, 128)
    for bad in ("16,32", "16,32,a,64,96", "16,0,48,64,96"):
        with pytest.raises(argparse.ArgumentTypeError, match="--widths"):
            _widths(bad)


def test_training_refuses_bad_counts_and_sequences_before_training(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    """--houses 0, --every 0 (raw tracebacks after rendering) and a --sequence without
    ground-truth depth (found only after the new model had replaced --out) are refused
    before anything is rendered or trained; a model's card is named after it."""
    import toolkit.depth.train_small as ts

    monkeypatch.setattr(ts, "train", lambda cfg: pytest.fail("trained anyway"))
    for args in (["--houses", "0"], ["--every", "0"], ["--threads", "-1"],
                 ["--images-per-house", "0"], ["--minutes", "0"],
                 ["--sequence", str(tmp_path / "missing")]):
        with pytest.raises(SystemExit) as e:
            ts.main(["--out", str(tmp_path / "m.onnx"), *args])
        assert e.value.code == 2, args
    assert "--sequence" in capsys.readouterr().err
    assert ts.card_path(tmp_path / "experiment.onnx") == tmp_path / "experiment.md"
    # The card's command names a non-default --images-per-house.
    c = {"minutes": 5.0, "train_seeds": [101], "threads": 2, "widths": [4, 8, 8, 8, 8],
         "height": 120, "width": 160, "lr": ts.TrainConfig.lr, "images_per_house": 20}
    assert "--images-per-house 20" in ts._command(c, "m.onnx")


def test_eval_only_refuses_a_missing_model_or_sequence_as_usage(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``train_small --eval-only MODEL --sequence SEQ`` (docs/depth_fusion.md, Reproduce)
    with a wrong path ended in a FileNotFoundError / SequenceFormatError traceback; the
    training path asked both up front. Now a usage error naming the option, exit 2."""
    import toolkit.depth.train_small as ts

    shipped = Path(__file__).resolve().parents[1] / "datasets/models/small-depth.onnx"
    for args, said in (
            (["--eval-only", str(tmp_path / "none.onnx"), "--sequence", str(tmp_path)],
             f"--eval-only {tmp_path / 'none.onnx'}: no such model file"),
            (["--eval-only", str(shipped), "--sequence", str(tmp_path / "missing")],
             "--sequence: ")):
        with pytest.raises(SystemExit) as e:
            ts.main(args)
        assert e.value.code == 2, args
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err, err


def _graph_model(path: Path, shape: list, elem: int, nhwc: bool,
                 props: dict[str, str] | None = None) -> Path:
    """A model built node by node: mean over the channels, then softplus (depth > 0)."""
    from onnx import TensorProto, helper

    nodes, x = [], "image"
    if elem != TensorProto.FLOAT:
        nodes.append(helper.make_node("Cast", [x], ["xf"], to=TensorProto.FLOAT))
        x = "xf"
    if nhwc:
        nodes.append(helper.make_node("Transpose", [x], ["xt"], perm=[0, 3, 1, 2]))
        x = "xt"
    nodes += [helper.make_node("ReduceMean", [x], ["m"], axes=[1], keepdims=1),
              helper.make_node("Softplus", ["m"], ["depth"])]
    return save_graph(path, nodes, [helper.make_tensor_value_info("image", elem, shape)],
                      props=props)


def test_onnx_model_shapes_and_settings_are_checked(tmp_path: Path, rgb: np.ndarray) -> None:
    from onnx import TensorProto

    from toolkit.depth.onnx_backend import OnnxDepthBackend
    from toolkit.depth.onnx_backend import OnnxDepthConfig as C

    # Channels last: named at load time, and run when the recipe says layout: nhwc.
    nhwc = _graph_model(tmp_path / "nhwc.onnx", [1, 28, 42, 3], TensorProto.FLOAT, True)
    with pytest.raises(ValueError, match=r"channels last; set layout: nhwc"):
        OnnxDepthBackend(C(model=nhwc, kind="relative_depth"))
    be = OnnxDepthBackend(C(model=nhwc, kind="relative_depth", layout="nhwc", threads=1))
    assert be.preprocess(rgb).shape == (1, 28, 42, 3)
    assert be.predict(rgb).values.shape == rgb.shape[:2]
    # A half-precision input takes the image cast to float16.
    half = _graph_model(tmp_path / "half.onnx", [1, 3, "h", "w"], TensorProto.FLOAT16, False,
                        {"channel_order": "BGR"})  # metadata in capitals
    be = OnnxDepthBackend(C(model=half, kind="relative_depth", input_size=(28, 42), threads=1))
    assert be.preprocess(rgb).dtype == np.float16 and be.channel_order == "bgr"
    assert np.isfinite(be.predict(rgb).values).all()
    # mean/std in 0-255 units (mmcv configs) would feed a constant image.
    with pytest.raises(ValueError, match="0-255 units; give them divided by 255"):
        OnnxDepthBackend(C(model=half, kind="relative_depth", mean=(123.7, 116.3, 103.5),
                           std=(58.4, 57.1, 57.4)))
    with pytest.raises(ValueError, match=r"output_index 2, but the model has 1 output"):
        OnnxDepthBackend(C(model=half, kind="relative_depth", output_index=2))
    # A dynamic ViT-style model sees whole patches: stretch sizes round to multiple_of.
    assert be.input_hw((480, 640)) == (28, 42)
    vit = OnnxDepthBackend(C(model=half, kind="relative_depth", input_size=(480, 640)))
    assert vit.input_hw((480, 640)) == (476, 644)


def test_onnx_invalid_output_does_not_blend_into_valid_depth(tmp_path: Path) -> None:
    """A network's 0 (no depth) next to 4 m, upsampled: bilinear would invent 1 and 3 m."""
    from toolkit.depth.onnx_backend import OnnxDepthBackend
    from toolkit.depth.onnx_backend import OnnxDepthConfig as C

    be = OnnxDepthBackend(C(model=_export(tmp_path / "t.onnx", (28, 42)), kind="metric_depth"))
    raw = np.array([[0.0, 0.0, 4.0, 4.0], [0.0, 0.0, 4.0, 4.0]], np.float32)[None, None]
    out = be.postprocess(raw, (4, 8))
    valid = out[np.isfinite(out)]
    assert len(valid) >= 12 and np.all(valid == pytest.approx(4.0))
    assert np.isnan(out[:, :3]).all()
    # channels-last single-channel output [1, h, w, 1] is one depth map too
    assert be.postprocess(np.full((1, 2, 3, 1), 2.0, np.float32), (2, 3)).shape == (2, 3)


def test_simulated_settings_are_checked_with_the_recipe() -> None:
    from pydantic import ValidationError

    from toolkit.depth.stage import DepthConfig

    with pytest.raises(ValidationError, match=r"unknown key\(s\) \['scal'\]"):
        DepthConfig(stage="depth", backend="simulated", simulated={"scal": 2.0})
    with pytest.raises(ValidationError, match="simulated"):
        DepthConfig(stage="depth", backend="simulated", simulated={"scale": "big"})
    assert DepthConfig(stage="depth", backend="simulated", simulated={"scale": 2.0})
    # The network's input size and rounding too (they passed `validate` and failed after
    # the earlier stages had run; multiple_of 0 ran as 14).
    for bad in ({"input_size": 0}, {"input_size": [480, -640]}, {"multiple_of": 0}):
        with pytest.raises(ValidationError, match="input_size|multiple_of"):
            DepthConfig(stage="depth", model="m.onnx", **bad)


def test_onnx_multiple_of_one_keeps_the_asked_size(tmp_path: Path) -> None:
    from toolkit.depth.onnx_backend import OnnxDepthBackend, OnnxDepthConfig

    be = OnnxDepthBackend(OnnxDepthConfig(model=_export(tmp_path / "t.onnx", None),
                                          kind="relative_depth", input_size=(480, 640),
                                          multiple_of=1))
    assert be.input_hw((480, 640)) == (480, 640)


def _two_output_model(path: Path, two_inputs: bool = False) -> Path:
    """UniDepth's export layout: the intrinsics [1, 3, 3] first, the depth second (or an
    intrinsics input beside the image)."""
    from onnx import TensorProto, helper

    k = helper.make_tensor("k", TensorProto.FLOAT, [1, 3, 3], np.eye(3).reshape(-1).tolist())
    nodes = [helper.make_node("ReduceMean", ["image"], ["m"], axes=[1], keepdims=1),
             helper.make_node("Softplus", ["m"], ["depth"]),
             helper.make_node("Constant", [], ["out_K"], value=k)]
    inputs = [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "h", "w"])]
    if two_inputs:
        inputs.append(helper.make_tensor_value_info("K", TensorProto.FLOAT, [1, 3, 3]))
    return save_graph(path, nodes, inputs, [
        helper.make_tensor_value_info("out_K", TensorProto.FLOAT, [1, 3, 3]),
        helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, 1, "h", "w"])])


def test_onnx_models_of_other_shapes_are_named_before_they_run(tmp_path: Path,
                                                               rgb: np.ndarray) -> None:
    from onnx import TensorProto

    from toolkit.depth.onnx_backend import OnnxDepthBackend
    from toolkit.depth.onnx_backend import OnnxDepthConfig as C

    uni = _two_output_model(tmp_path / "uni.onnx")
    # output 0 is the intrinsics: refused, with the outputs listed (it was stretched over
    # the image as a depth map)
    with pytest.raises(ValueError, match=r"output 0 \('out_K'\) has shape \[1, 3, 3\].*"
                       r"1: 'depth'.*output_index"):
        OnnxDepthBackend(C(model=uni, kind="metric_depth"))
    be = OnnxDepthBackend(C(model=uni, kind="metric_depth", output_index=1, input_size=28))
    assert be.predict(rgb).values.shape == rgb.shape[:2]
    assert be.describe()["output"] == "depth" and be.describe()["input_hw"] == [28, 28]
    with pytest.raises(ValueError, match=r"takes 2 inputs \('image'.*'K'"):
        OnnxDepthBackend(C(model=_two_output_model(tmp_path / "k.onnx", True),
                           kind="metric_depth", output_index=1))
    # keep_aspect on a fixed input would stretch silently
    fixed = _graph_model(tmp_path / "fixed.onnx", [1, 3, 28, 42], TensorProto.FLOAT, False)
    with pytest.raises(ValueError, match="keep_aspect needs a model exported with dynamic"):
        OnnxDepthBackend(C(model=fixed, kind="relative_depth", resize="keep_aspect"))
    dyn = _graph_model(tmp_path / "dyn.onnx", [1, 3, "h", "w"], TensorProto.FLOAT, False,
                       {"mean": "[0.5, 0.5, 0.5]"})  # a bracketed list is read too
    with pytest.raises(ValueError, match=r"keep_aspect takes one input_size"):
        OnnxDepthBackend(C(model=dyn, kind="relative_depth", resize="keep_aspect",
                           input_size=(28, 42)))
    assert OnnxDepthBackend(C(model=dyn, kind="relative_depth")).mean.tolist() == [0.5] * 3
    # metadata errors name the key; no kind anywhere names the recipe's setting
    bad = _graph_model(tmp_path / "bad.onnx", [1, 3, "h", "w"], TensorProto.FLOAT, False,
                       {"input_height": "518.5", "input_width": "518"})
    with pytest.raises(ValueError, match=r"metadata 'input_height' is '518.5'"):
        OnnxDepthBackend(C(model=bad, kind="relative_depth"))
    with pytest.raises(ValueError, match=r"depth stage's 'output' setting"):
        OnnxDepthBackend(C(model=dyn))


def test_depth_settings_the_model_refuses_are_found_before_the_run(tmp_path: Path) -> None:
    """validate and the start of run read the model's inputs, outputs and metadata: what
    the backend refuses when it loads the model stopped the run only after the stages
    before depth (a missing depth_kind after the simulator had run)."""
    from onnx import TensorProto

    from toolkit.recipe.runner import missing_inputs, run_recipe
    from toolkit.recipe.schema import RecipeError, load_recipe

    dyn = _graph_model(tmp_path / "dyn.onnx", [1, 3, "h", "w"], TensorProto.FLOAT, False)
    fixed = _graph_model(tmp_path / "fixed.onnx", [1, 3, 28, 42], TensorProto.FLOAT, False)
    recipe = tmp_path / "r.yaml"

    def problems(**depth: object) -> list[str]:
        keys = "".join(f"\n    {k}: {v}" for k, v in depth.items())
        recipe.write_text(f"name: r\noutput: {tmp_path / 'run'}\nstages:\n"
                          f"  - stage: simulate\n    duration_s: 1\n"
                          f"  - stage: depth\n    backend: onnx{keys}\n")
        return missing_inputs(load_recipe(recipe))

    # Depth Anything / MiDaS exports carry no depth_kind: the field to set is named.
    found = problems(model=dyn)
    assert len(found) == 1 and "no 'depth_kind' metadata" in found[0], found
    assert "depth stage's 'output' setting" in found[0] and str(dyn) in found[0]
    for keys, why in (
            ({"output_index": 2}, r"output_index 2, but the model has 1 output.*set "
                                  "output_index"),
            ({"model": fixed, "resize": "keep_aspect"}, "keep_aspect needs a model exported "
                                                        "with dynamic height/width"),
            ({"model": fixed, "input_size": 56}, r"fixed input of height 28, width 42, but "
                                                 r"input_size asks for \[56, 56\].*set "
                                                 r"input_size: \[28, 42\] or drop it"),
            # Swapped sides (a user reading a WxH figure): the message shows both in the
            # recipe's [h, w] order.
            ({"model": fixed, "input_size": [42, 28]}, r"asks for \[42, 28\] \(\[height, "
                                                       r"width\]\); set input_size: \[28, 42\]")):
        found = problems(**{"model": dyn, "output": "relative_disparity", **keys})
        assert len(found) == 1 and re.search(why, found[0]), (keys, found)
    # keep_aspect takes one side: refused with the recipe, no model needed.
    with pytest.raises(RecipeError, match=r"keep_aspect takes one input_size.*not \[28, 42\]"):
        problems(model=dyn, output="relative_disparity", resize="keep_aspect",
                 input_size=[28, 42])
    # Settings the backend takes pass, the shipped model's too.
    assert problems(model=dyn, output="relative_disparity", resize="keep_aspect",
                    input_size=28) == []
    assert problems(model=fixed, output="relative_depth", input_size=[28, 42]) == []
    shipped = Path(__file__).resolve().parents[1] / "datasets/models/small-depth.onnx"
    assert problems(model=shipped) == []
    # An op with no CPU kernel (bfloat16 Relu) may run on the GPU: not refused, and no
    # traceback out of validate (the check's session is a CPU one).
    from onnx import helper

    bf16 = save_graph(tmp_path / "bf16.onnx", [
        helper.make_node("Cast", ["image"], ["b"], to=TensorProto.BFLOAT16),
        helper.make_node("Relu", ["b"], ["r"]),
        helper.make_node("Cast", ["r"], ["f"], to=TensorProto.FLOAT),
        helper.make_node("ReduceMean", ["f"], ["depth"], axes=[1], keepdims=1)],
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "h", "w"])])
    assert problems(model=bf16, output="relative_depth") == []
    # run stops before its first stage: the simulator does not run.
    problems(model=dyn)
    with pytest.raises(RecipeError, match="no 'depth_kind' metadata"):
        run_recipe(load_recipe(recipe))
    assert not (tmp_path / "run" / "simulate").exists()


def test_onnx_image_input_must_take_one_rgb_image(tmp_path: Path, rgb: np.ndarray) -> None:
    """A grayscale or RGB-D network was loaded, then failed at its first frame with advice
    about multiple_of; now refused at load (and by validate), and the size advice is given
    only where a size can be what onnxruntime refused."""
    import onnxruntime as ort
    from onnx import TensorProto, helper

    from toolkit.depth import onnx_backend
    from toolkit.depth.onnx_backend import OnnxDepthBackend
    from toolkit.depth.onnx_backend import OnnxDepthConfig as C

    for shape, layout, why in (([1, 1, "h", "w"], "nchw", r"takes 1 channel\(s\)"),
                               ([1, 4, "h", "w"], "nchw", r"takes 4 channel\(s\)"),
                               ([1, "h", "w", 1], "nhwc", r"takes 1 channel\(s\)"),
                               ([2, 3, "h", "w"], "nchw", "a batch of 2 images")):
        path = _graph_model(tmp_path / "m.onnx", shape, TensorProto.FLOAT, layout == "nhwc")
        config = C(model=path, kind="relative_depth", layout=layout)
        with pytest.raises(ValueError, match=why):
            OnnxDepthBackend(config)
        assert re.search(why, onnx_backend.model_problem(config) or ""), shape
    # onnxruntime's own refusals, as the run would meet them
    gray = _graph_model(tmp_path / "gray.onnx", [1, 1, "h", "w"], TensorProto.FLOAT, False)
    fixed = _graph_model(tmp_path / "fixed.onnx", [1, 3, 28, 42], TensorProto.FLOAT, False)

    def refusal(path: Path, x: np.ndarray) -> str:
        with pytest.raises(Exception) as e:  # noqa: PT011 - onnxruntime's own type
            ort.InferenceSession(str(path)).run(None, {"image": x})
        return str(e.value)

    dyn = _graph_model(tmp_path / "dyn.onnx", [1, 3, "h", "w"], TensorProto.FLOAT, False)
    be = OnnxDepthBackend(C(model=dyn, kind="relative_depth", threads=1))
    channels = be._failure_hint(refusal(gray, np.zeros((1, 3, 8, 8), np.float32)))
    assert "multiple_of" not in channels and "axes [1]" in channels
    width = be._failure_hint(refusal(fixed, np.zeros((1, 3, 28, 28), np.float32)))
    assert "set multiple_of (now 14)" in width
    # A size the graph cannot take fails inside it, where onnxruntime names no axis: the
    # size advice stays (MiDaS at a size that is no multiple of 32).
    c = helper.make_tensor("c", TensorProto.FLOAT, [1, 3, 28, 42], [0.0] * 28 * 42 * 3)
    add = save_graph(tmp_path / "add.onnx", [
        helper.make_node("Constant", [], ["c"], value=c),
        helper.make_node("Add", ["image", "c"], ["s"]),
        helper.make_node("ReduceMean", ["s"], ["m"], axes=[1], keepdims=1),
        helper.make_node("Softplus", ["m"], ["depth"])],
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "h", "w"])])
    with pytest.raises(ValueError, match=r"failed on a 28x28 input.*set multiple_of \(now 1\)"):
        OnnxDepthBackend(C(model=add, kind="relative_depth", input_size=28, multiple_of=1,
                           threads=1)).predict(rgb)
    assert OnnxDepthBackend(C(model=add, kind="relative_depth", input_size=(28, 42),
                              threads=1)).predict(rgb).values.shape == rgb.shape[:2]


def test_depth_threads_keep_an_interrupted_runs_frames(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """threads / device / prefetch change how fast the stage runs, not what it writes: an
    interrupted run's frames are kept under new ones (they were all predicted again), and
    a finished stage stays cached (it reran, and made every later stage rerun)."""
    from recipe_helpers import SequenceFolder, run_stages  # the tests folder is on sys.path

    from toolkit.depth.stage import DepthStage
    from toolkit.fusion.synthetic import write_box_room

    seq = write_box_room(tmp_path / "seq", n_frames=4)
    register = {"t_sequence": SequenceFolder, "depth": DepthStage}

    def stages(**depth: object) -> list[dict[str, object]]:
        return [{"stage": "t_sequence", "path": str(seq)},
                {"stage": "depth", "backend": "simulated", **depth}]

    predict = SimulatedDepthBackend.predict

    def dies_at_frame_2(self: SimulatedDepthBackend, rgb: np.ndarray, **kw: object) -> object:
        if kw["frame_index"] == 2:
            raise RuntimeError("killed")
        return predict(self, rgb, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(SimulatedDepthBackend, "predict", dies_at_frame_2)
    assert not run_stages(tmp_path, stages(), register).ok
    monkeypatch.setattr(SimulatedDepthBackend, "predict", predict)
    again = run_stages(tmp_path, stages(threads=1, device="cpu", prefetch=False), register)
    assert again.ok and again.metrics["depth"]["frames_resumed"] == 2
    same = run_stages(tmp_path, stages(threads=2), register)
    assert same.statuses["depth"] == "cached" and same.metrics["depth"]["frames_resumed"] == 2


def test_depth_settings_that_cannot_run_are_refused_with_the_recipe() -> None:
    from pydantic import ValidationError

    from toolkit.depth.stage import DepthConfig

    with pytest.raises(ValidationError, match="backend 'onnx' needs 'model'"):
        DepthConfig(stage="depth", backend="onnx", model=None)
    with pytest.raises(ValidationError, match="needs input_size"):
        DepthConfig(stage="depth", backend="dav2s_random")


def test_the_simulated_wander_drifts_without_jumps() -> None:
    """Drawn after its steps, the series' first value changed with the length generated,
    and the log-scale jumped at frames 256, 512, ...: 39x a normal step for a wander of
    2000 frames."""
    steps_at, steps_else = [], []
    for seed in range(10):
        b = SimulatedDepthBackend(SimulatedDepthParams(wander_sigma=0.05, wander_frames=2000,
                                                       seed=seed))
        w = np.array([b._wander(i) for i in range(600)])
        steps_at += [abs(w[256] - w[255]), abs(w[512] - w[511])]
        steps_else.append(np.median(np.abs(np.diff(w))))
    assert np.median(steps_at) < 3 * np.median(steps_else)
    # A backend asked for frame 500 first gives frame 10 what a fresh one gives.
    late = SimulatedDepthBackend(SimulatedDepthParams(seed=3))
    late.frame_scale(500)
    fresh = SimulatedDepthBackend(SimulatedDepthParams(seed=3))
    assert late.frame_scale(10) == fresh.frame_scale(10)


@pytest.mark.parametrize("corr", [0.1, 0.3, 1.5])
def test_simulated_noise_has_the_std_asked_for(corr: float) -> None:
    """The continuous-limit factor 2 sqrt(pi) sigma gave 0.36x the std at sigma 0.1."""
    b = SimulatedDepthBackend(SimulatedDepthParams(noise_corr_px=corr))
    stds = [float(b.noise_field(240, 320, i).std()) for i in range(4)]
    assert np.mean(stds) == pytest.approx(1.0, rel=0.04)


def test_simulated_settings_that_contradict_or_leak_are_caught() -> None:
    from toolkit.depth.stage import DepthConfig

    with pytest.raises(ValueError, match="seed"):
        DepthConfig(stage="depth", backend="simulated", simulated={"seed": -1})
    with pytest.raises(ValueError, match="output is relative_disparity but preset groundtruth "
                                         "makes metric_depth"):
        DepthConfig(stage="depth", backend="simulated", preset="groundtruth",
                    output="relative_disparity")
    # Turning on the scale draw no longer redraws the distortion field.
    a = SimulatedDepthBackend(SimulatedDepthParams(scale_log_sigma=0.0))
    b = SimulatedDepthBackend(SimulatedDepthParams(scale_log_sigma=1e-9))
    assert np.array_equal(a.distortion_field(30, 40, 5), b.distortion_field(30, 40, 5))
