"""ONNX models built node by node for the depth tests: their answer is known exactly."""

from pathlib import Path
from typing import Any


def save_graph(path: Path, nodes: list, inputs: list, outputs: list | None = None,
               props: dict[str, str] | None = None) -> Path:
    """Write a graph of ``nodes`` (opset 13) with ``inputs``; one float output "depth" of
    any shape unless ``outputs`` are given; ``props`` as ONNX metadata."""
    import onnx
    from onnx import TensorProto, helper

    outputs = outputs or [helper.make_tensor_value_info("depth", TensorProto.FLOAT, None)]
    graph = helper.make_graph(nodes, "g", inputs, outputs)
    model: Any = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8  # what the onnxruntime here reads
    if props:
        helper.set_model_props(model, props)
    onnx.save(model, str(path))
    return path
