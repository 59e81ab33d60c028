"""Lidar-to-image projection, per-frame scale estimation, coloured clouds and the voxel map."""
