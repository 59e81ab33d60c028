"""Camera intrinsics, camera - 2D lidar extrinsic calibration, and checks.

Run as ``python -m calibration intrinsics|extrinsic|check --help``. The library parts are
importable without the command line:

* ``calibration.board``: board geometry and corner detection
* ``calibration.intrinsics``: ``calibrate_intrinsics`` from detections
* ``calibration.scans``: scan readers (PCD, CSV, npz, sequence) and timestamp pairing
* ``calibration.board_lines``: the board's points in a scan (RANSAC segments)
* ``calibration.extrinsic``: ``calibrate_extrinsic`` (Zhang & Pless 2004), covariance,
  leave-one-out
* ``calibration.check``: overlays and extrinsic consistency scores
* ``calibration.synthetic``: captures with exact ground truth for tests and benchmarks

The extrinsic is ``T_camera_laser``: ``p_camera_optical = T_camera_laser @ p_laser``.
"""
