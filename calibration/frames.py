"""Frame conventions shared by the calibration modules."""

from __future__ import annotations

import numpy as np

# Laser (REP 103: x forward, y left, z up) -> camera optical (x right, y down, z forward)
# for a laser that looks where the camera looks: T_camera_laser's rotation of that mount.
R_CAMERA_LASER_NOMINAL = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
