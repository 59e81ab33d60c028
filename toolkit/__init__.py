"""Metric 3D reconstruction for mobile robots from a monocular camera and a 2D lidar.

Core types live in ``toolkit.geometry``, ``toolkit.camera`` and ``toolkit.sensors``;
formats in ``toolkit.io``; stages (simulate, slam2d, depth, fuse, splat, ...) in their own
subpackages, chained by ``python -m toolkit.recipe run RECIPE.yaml``.
"""

__version__ = "0.1.0"
