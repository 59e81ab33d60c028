"""Open3D ``VoxelBlockGrid`` to bytes and back, for checkpoints of stages that fuse frames.

Open3D saves a grid only to an npz file; these go through a temporary one so that the grid
can travel inside a stage's pickled state.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any


def voxel_grid_bytes(grid: Any) -> bytes:
    """Open3D's own npz of ``grid`` (a grid with at least one block: Open3D cannot load an
    empty one)."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "grid.npz"
        grid.save(str(path))
        return path.read_bytes()


def voxel_grid_from_bytes(data: bytes) -> Any:
    """The ``open3d.t.geometry.VoxelBlockGrid`` that ``voxel_grid_bytes`` saved."""
    import open3d as o3d

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "grid.npz"
        path.write_bytes(data)
        return o3d.t.geometry.VoxelBlockGrid.load(str(path))


class GridCheckpoint:
    """``state``/``restore`` for a volume keeping its Open3D grid in ``grid`` and the number
    of frames it fused in ``frames`` (mixed into the fusion's volumes)."""

    grid: Any
    frames: int

    def state(self) -> dict[str, Any]:
        """The volume and its frame count, picklable (with ``restore``: a checkpoint)."""
        # Open3D cannot load a grid without blocks.
        return {"grid_npz": voxel_grid_bytes(self.grid) if self.frames else None,
                "frames": self.frames}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from ``state()`` of a volume with the same settings."""
        if state["grid_npz"] is not None:
            self.grid = voxel_grid_from_bytes(state["grid_npz"])
        self.frames = int(state["frames"])
