"""Cross-checks run on the same inputs as the method: TSDF fusion (Open3D), COLMAP
(pycolmap) and the camera-only ("without lidar") configuration.

Modules are imported on use so that ``import toolkit.baselines`` stays cheap:

- ``tsdf``: ``TSDFVolume`` (VoxelBlockGrid), ``MeshRenderer`` / ``render_mesh``;
- ``colmap``: ``run_sfm``, ``evaluate_sfm_trajectory``, ``triangulate_known_poses``;
- ``camera_only``: ``camera_only_reconstruction`` and its alignments;
- ``stage``: the recipe stages ``tsdf``, ``colmap``, ``camera_only``;
- ``synthetic``: a ray-cast textured box room for tests;
- ``common``: poses per frame, observed ground-truth surface, figures.
"""
