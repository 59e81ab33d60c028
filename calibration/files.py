"""Calibration files: camera YAML, extrinsic / rig YAML, in the toolkit's conventions.

The extrinsic is stored as ``T_camera_laser`` (``p_camera_optical = T_camera_laser @
p_laser``) with the direction written next to it, together with the same transform in
tf form (parent ``camera_optical``, child ``laser``, xyz + quaternion xyzw), which is what
``static_transform_publisher`` and a ROS ``TransformStamped`` take. Readers accept the
toolkit's rig YAML, a bare ``T_camera_laser`` or ``T_laser_camera`` matrix, and tf-style
mappings, so a result from another tool can be checked with ``python -m calibration check``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from toolkit.camera import PinholeCamera, distortion_values, plumb_bob_distortion
from toolkit.errors import InputError
from toolkit.geometry import checked_rigid, inv_se3, pose_from_xyz_quat, pose_to_xyz_quat
from toolkit.io.atomic import atomic_write_text
from toolkit.io.yaml_file import load_yaml
from toolkit.sensors import Rig

DIRECTION = "p_camera_optical = T_camera_laser @ p_laser (maps laser points into the camera)"


class CalibrationFileError(InputError):
    """A calibration file is missing or malformed; the message names the file and field."""


def _load_yaml(path: Path, what: str) -> Any:
    return load_yaml(path, CalibrationFileError, f"{what} file not found")


# ---------------------------------------------------------------------------- camera


_CAMERA_FIELDS = ("(need width, height, fx, fy, cx, cy[, distortion]; or a ROS "
                  "camera_calibration YAML: image_width, image_height, camera_matrix, "
                  "distortion_coefficients; or a CameraInfo message dump: width, height, k, d)")


def camera_from_mapping(d: Any, source: str) -> PinholeCamera:
    """A camera from the toolkit's camera/rig YAML or a ROS ``camera_info`` YAML."""
    if not isinstance(d, dict):
        raise CalibrationFileError(f"{source}: expected a mapping with the camera intrinsics")
    if "camera" in d and isinstance(d["camera"], dict):
        d = d["camera"]
    try:
        if "camera_matrix" in d or "image_width" in d:
            # ROS camera_calibration output (camera_info YAML).
            K = np.asarray(d["camera_matrix"]["data"], dtype=np.float64).reshape(3, 3)
            dist = distortion_values((d.get("distortion_coefficients") or {}).get("data"),
                                     "distortion_coefficients")
            dist = _plumb_bob(d.get("distortion_model"), dist, source,
                              "distortion_coefficients")
            return PinholeCamera.from_K(K, int(d["image_width"]), int(d["image_height"]), dist)
        if ("k" in d or "K" in d) and "fx" not in d:
            # ``ros2 topic echo --once .../camera_info`` (ROS 2: k, d; ROS 1: K, D).
            K = np.asarray(d.get("k", d.get("K")), dtype=np.float64).reshape(3, 3)
            dist = distortion_values(d.get("d", d.get("D")), "d" if "d" in d else "D")
            dist = _plumb_bob(d.get("distortion_model"), dist, source, "d")
            return PinholeCamera.from_K(K, int(d["width"]), int(d["height"]), dist)
        # Named here: PinholeCamera's KeyError text, wrapped below, read as one odd field
        # name ("camera is missing ['cy']").
        missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in d]
        if missing:
            raise CalibrationFileError(f"{source}: missing field "
                                       f"{', '.join(map(repr, missing))} {_CAMERA_FIELDS}")
        # The toolkit's own layout names its lens model under "model" (to_dict writes
        # "pinhole"); COLMAP-style names such as OPENCV_FISHEYE mean another lens.
        model = d.get("distortion_model", d.get("model"))
        if model is not None and str(model).strip().lower() != "pinhole":
            d = {**d, "distortion": _plumb_bob(model, distortion_values(d.get("distortion")),
                                               source, "distortion",
                                               "distortion_model" if "distortion_model" in d
                                               else "model")}
        return PinholeCamera.from_dict(d)
    except CalibrationFileError:
        raise
    except KeyError as e:
        raise CalibrationFileError(f"{source}: missing field {e} {_CAMERA_FIELDS}") from None
    except (TypeError, ValueError) as e:
        raise CalibrationFileError(f"{source}: bad camera field: {e}") from None


# Names of the model the camera has (OpenCV's k1 k2 p1 p2 k3): ROS camera_info's, Kalibr's,
# and the one ``write_camera`` writes.
def _plumb_bob(model: Any, dist: np.ndarray, source: str, field: str,
               model_field: str = "distortion_model") -> np.ndarray:
    """The k1 k2 p1 p2 k3 coefficients of a camera file, or an error naming the model.

    Reading another model's coefficients as these projects wrongly without any error
    (an equidistant fisheye's k1..k4 as plumb_bob's are hundreds of pixels off at the
    image edge), so only models that are this one, or reduce to it, are accepted.
    """
    name = "" if model is None else str(model).strip().lower()
    if name == "none" and np.any(dist):
        raise CalibrationFileError(f"{source}: field 'distortion_model' is 'none' but field "
                                   f"'{field}' is not all zero; set distortion_model: plumb_bob "
                                   "if those are k1 k2 p1 p2 k3")
    try:
        coefficients = plumb_bob_distortion(model, dist, field)
    except ValueError as e:
        raise CalibrationFileError(f"{source}: {e}") from None
    if coefficients is None:
        raise CalibrationFileError(
            f"{source}: field '{model_field}' is {model!r}; this tool's camera model is "
            "OpenCV's plumb_bob (k1 k2 p1 p2 k3), so those coefficients cannot be used as "
            "they are. Calibrate the camera with that model (python -m calibration "
            "intrinsics --model opencv5), or undistort the images first and give "
            "distortion_model: plumb_bob with zero coefficients.")
    return coefficients


def load_camera(path: Path) -> PinholeCamera:
    """Read a camera YAML (toolkit camera, rig, or ROS camera_info)."""
    return camera_from_mapping(_load_yaml(path, "camera"), str(path))


def check_image_size(camera: PinholeCamera, camera_source: str, image_path: Path,
                     size: tuple[int, int]) -> None:
    """Raise when an image's (width, height) differs from the camera's."""
    if tuple(size) != camera.size:
        w, h = size
        raise CalibrationFileError(
            f"{image_path}: image is {w}x{h} but {camera_source} fields width/height say "
            f"{camera.width}x{camera.height}. Use the camera YAML calibrated at this "
            f"resolution (python -m calibration intrinsics --images ...), or rescale the "
            f"intrinsics if the images were resized.")


def write_camera(path: Path, camera: PinholeCamera, info: dict[str, Any] | None = None) -> None:
    """Camera YAML: the toolkit's camera mapping plus an optional ``calibration`` block."""
    d: dict[str, Any] = camera.to_dict()
    d["distortion_model"] = "opencv k1 k2 p1 p2 k3"
    if info:
        d["calibration"] = info
    # Written by the CLI outside run folders: what a killed write left goes here.
    atomic_write_text(path, yaml.safe_dump(d, sort_keys=False), clean_stale=True)


# ---------------------------------------------------------------------------- extrinsic


def _matrix(value: Any, source: str, field: str) -> np.ndarray:
    if isinstance(value, dict):  # tf style, as ingest's calibration files allow
        _check_tf_direction(value, source, field)
        _check_camera_frame(value, source, field)
        M = _tf(value, f"{source}: field '{field}'")
    else:
        try:
            M = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            M = np.zeros(0)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise CalibrationFileError(f"{source}: field '{field}' must be a finite 4x4 matrix "
                                   f"(list of rows), got shape {M.shape}")
    try:
        M = checked_rigid(M)
    except ValueError as e:
        raise CalibrationFileError(f"{source}: field '{field}' {e}") from None
    return M


def _tf(d: dict[str, Any], source: str) -> np.ndarray:
    """T_parent_child of a tf-style mapping (xyz + quaternion xyzw)."""
    xyz = d.get("translation", d.get("xyz"))
    quat = d.get("rotation", d.get("quaternion", d.get("quat_xyzw")))
    if isinstance(xyz, dict):
        xyz = [xyz.get(k) for k in "xyz"]
    if isinstance(quat, dict):
        quat = [quat.get(k) for k in "xyzw"]
    try:
        xyz_a = np.asarray(xyz, dtype=np.float64).reshape(3)
        q = np.asarray(quat, dtype=np.float64).reshape(4)
    except (TypeError, ValueError):
        raise CalibrationFileError(f"{source}: tf-style extrinsic needs 'translation' [x, y, z] "
                                   "and 'rotation' [qx, qy, qz, qw]") from None
    if not 0.5 < np.linalg.norm(q) < 2.0:
        raise CalibrationFileError(f"{source}: field 'rotation' is not a unit quaternion xyzw")
    return pose_from_xyz_quat(xyz_a, q / np.linalg.norm(q))


# Frame roles are told by what the names say, not by a list of exact names: with lists
# of five names each, a T_camera_laser entry written from the laser to RealSense's
# camera_color_optical_frame, ZED's zed_left_camera_optical_frame or cam0 was read
# inverted without a word (114.8 deg / 251 mm off), and the bare tf layout refused
# cam0 -> laser and camera_optical_frame -> hokuyo_link as "need a camera optical frame".
_CAMERA_RE = re.compile(r"optical|cam|zed|realsense|kinect|xtion")
_LASER_RE = re.compile(r"laser|lidar|scan|hokuyo|sick|velodyne|ouster|livox|(^|[^a-z])"
                       r"(urg|lms\d*|vlp\d*|os[0-2]|rslidar|hesai|pandar)(\d|[^a-z]|$)")
_BASE_RE = re.compile(r"^(base|base_link|base_footprint|body|chassis)$")


def frame_role(name: str) -> str | None:
    """'camera', 'laser' or 'base' as a frame's name says (``camera_color_optical_frame``,
    ``cam0``, ``zed_left_camera_optical_frame``; ``hokuyo_link``, ``base_scan``,
    ``rplidar_link``, ``velodyne``; ``base_link``), or None when it says nothing or both
    a camera and a laser. A laser's name wins over ``base`` (``base_laser``,
    ``base_scan``)."""
    n = name.lower().strip("/").rsplit("/", 1)[-1]
    camera, laser = bool(_CAMERA_RE.search(n)), bool(_LASER_RE.search(n))
    if camera != laser:
        return "camera" if camera else "laser"
    if not camera and _BASE_RE.match(n):
        return "base"
    return None


def _role_text(name: str) -> str:
    role = frame_role(name)
    return f"{name!r} ({f'a {role} frame' if role else 'its role not told by its name'})"


def _check_tf_direction(value: dict[str, Any], source: str, field: str) -> None:
    """A tf-style ``T_a_b`` whose parent or child names a frame of another role than the
    key's: a parent that is the laser under ``T_camera_laser`` is enough. The key fixes the
    direction, so a reversed entry would be used inverted (bag ingest refuses it too), and
    one between other frames (``base_link`` under ``T_camera_laser``) is another
    transform."""
    roles = field.split("_")[1:]
    if len(roles) != 2 or not all(r in ("camera", "laser", "base") for r in roles):
        return
    a, b = roles
    parent = _frame_name(value, "parent", "frame_id")
    child = _frame_name(value, "child", "child_frame_id")
    rp, rc = frame_role(parent), frame_role(child)
    if rp in (a, None) and rc in (b, None):
        return
    reversed_ = rp in (b, None) and rc in (a, None)
    raise CalibrationFileError(
        f"{source}: field '{field}' has parent {_role_text(parent)} and child "
        f"{_role_text(child)}: {field} maps {b} points into the {a} frame, so its parent "
        f"must be the {a} frame and its child the {b} frame. "
        + ("It is reversed: swap parent and child, or invert the transform."
           if reversed_ else "Name the frames of the transform this entry holds."))


# How to get from a body frame to the optical one: what the errors below suggest.
_OPTICAL_HINT = ("A camera body frame (ROS REP 103: x forward, y left, z up; camera_link, "
                 "*_camera_frame) is not the optical frame (x right, y down, z forward): read "
                 "as it, the view turns 120 degrees. Compose the transform with T_body_optical "
                 "(translation 0, rotation quat_xyzw [-0.5, 0.5, -0.5, 0.5]) and name the "
                 "optical frame (e.g. camera_optical_frame)")


def _frame_name(value: dict[str, Any], key: str, alt: str) -> str:
    return str(value.get(key, value.get(alt, ""))).strip("/")


def _is_body_frame(name: str) -> bool:
    """Whether a camera frame's name is a ROS body frame's (``camera_link``, RealSense's
    ``camera_color_frame``, ZED's ``zed_left_camera_frame``), not an optical one's. Other
    names (``cam0``) say nothing and pass."""
    n = name.lower().rsplit("/", 1)[-1]
    return "optical" not in n and (n.endswith("link") or n.endswith("_frame"))


def _check_camera_frame(value: dict[str, Any], source: str, field: str) -> None:
    """A tf-style ``T_camera_*`` / ``T_*_camera`` naming a body frame for the camera: it
    was read as the optical frame, 120 degrees off (bag ingest and the bare tf layout
    refuse it)."""
    roles = field.split("_")[1:]
    if len(roles) != 2 or "camera" not in roles:
        return
    key, alt = (("parent", "frame_id") if roles[0] == "camera"
                else ("child", "child_frame_id"))
    name = _frame_name(value, key, alt)
    if _is_body_frame(name):
        raise CalibrationFileError(
            f"{source}: field '{field}' has {key} {name!r}, a camera body frame, but "
            f"{field} needs the camera's optical frame. {_OPTICAL_HINT}.")


def extrinsic_from_mapping(d: Any, source: str) -> np.ndarray:
    """T_camera_laser [4, 4] from any of the accepted layouts."""
    if not isinstance(d, dict):
        raise CalibrationFileError(f"{source}: expected a mapping")
    if "T_camera_laser" in d:
        return _matrix(d["T_camera_laser"], source, "T_camera_laser")
    if "T_laser_camera" in d:
        return inv_se3(_matrix(d["T_laser_camera"], source, "T_laser_camera"))
    if "T_base_camera" in d and "T_base_laser" in d:
        Tbc = _matrix(d["T_base_camera"], source, "T_base_camera")
        return inv_se3(Tbc) @ _matrix(d["T_base_laser"], source, "T_base_laser")
    tf = d.get("tf", d)
    if isinstance(tf, dict) and ("parent" in tf or "frame_id" in tf):
        parent = str(tf.get("parent", tf.get("frame_id", ""))).strip("/")
        child = str(tf.get("child", tf.get("child_frame_id", ""))).strip("/")
        T = _tf(tf, source)  # T_parent_child
        # The direction from whichever end tells its role (hokuyo_link, cam0, ...).
        rp, rc = frame_role(parent), frame_role(child)
        # An end of another role (base_link) makes it some other transform; two ends of
        # no known role, either way.
        forward = rp in ("camera", None) and rc in ("laser", None)
        backward = rp in ("laser", None) and rc in ("camera", None)
        if forward != backward:
            camera = parent if forward else child
            if _is_body_frame(camera):
                raise CalibrationFileError(
                    f"{source}: tf from {parent!r} to {child!r}: {camera!r} is a camera body "
                    f"frame, but the extrinsic needs the camera's optical frame. "
                    f"{_OPTICAL_HINT}.")
            return T if forward else inv_se3(T)
        raise CalibrationFileError(
            f"{source}: tf from {_role_text(parent)} to {_role_text(child)}: need a camera "
            "optical frame at one end and a laser frame at the other, told by their names "
            "(camera: *optical*, cam*, *camera*, zed*, realsense*; laser: *laser*, *lidar*, "
            "*scan*, hokuyo*, sick*, velodyne*, ouster*, livox*). Rename the frames, or give "
            f"'T_camera_laser' (4x4, {DIRECTION}). {_OPTICAL_HINT}.")
    raise CalibrationFileError(
        f"{source}: no extrinsic found: give 'T_camera_laser' (4x4, {DIRECTION}), "
        "'T_laser_camera', a rig (T_base_camera + T_base_laser) or a tf mapping "
        "(parent, child, translation, rotation xyzw)")


def read_extrinsic(path: Path) -> tuple[np.ndarray, dict[str, Any] | None]:
    """T_camera_laser [4, 4] from a calibration, rig or tf-style YAML, and the marks it was
    estimated with (``reliable``, ``unreliable_because``; None when the file has none).

    The marks sit in a rig's ``calibration`` block, or at the top of the ``--json`` and
    ``calibration.yaml`` results. A file marked ``reliable: false`` logs a warning, as
    ``read_rig`` does: checked or passed on, it was read without a word.
    """
    from toolkit.io.sequence import warn_if_unreliable

    data = _load_yaml(path, "extrinsic")
    T = extrinsic_from_mapping(data, str(path))
    block = data.get("calibration", data)
    if not isinstance(block, dict) or "reliable" not in block:
        return T, None
    marks = {k: block[k] for k in ("reliable", "unreliable_because") if k in block}
    # A quoted "false" is refused: the calibrate stage took such an extrinsic as reliable,
    # without the refusal --allow-unreliable lifts.
    warn_if_unreliable(path, {"calibration": marks}, CalibrationFileError)
    return T, marks


def load_extrinsic(path: Path) -> np.ndarray:
    """T_camera_laser [4, 4] from a calibration, rig or tf-style YAML (see ``read_extrinsic``)."""
    return read_extrinsic(path)[0]


def extrinsic_to_mapping(T_camera_laser: np.ndarray) -> dict[str, Any]:
    """The matrix with its direction, and the same transform in tf form."""
    xyz, q = pose_to_xyz_quat(T_camera_laser)
    return {
        "T_camera_laser": [[float(v) for v in row] for row in T_camera_laser],
        "direction": DIRECTION,
        "tf": {"parent": "camera_optical", "child": "laser",
               "translation": [float(v) for v in xyz],
               "rotation": [float(v) for v in q],
               "note": "tf convention: maps child (laser) points into the parent (camera) "
                       "frame; quaternion order x y z w"},
    }


def rig_for_extrinsic(camera: PinholeCamera, T_camera_laser: np.ndarray,
                      base_rig: Rig | None = None) -> Rig:
    """A rig holding the calibrated extrinsic.

    With ``base_rig`` the camera stays where it was on the robot and the laser moves;
    without one, ``base_link`` is put at the laser (a 2D lidar is usually mounted level
    on the base), so ``T_base_laser`` is the identity.
    """
    if base_rig is not None:
        return Rig(camera, base_rig.T_base_camera.copy(),
                   base_rig.T_base_camera @ T_camera_laser)
    return Rig(camera, inv_se3(T_camera_laser), np.eye(4))


def write_rig_with_calibration(path: Path, rig: Rig, info: dict[str, Any]) -> None:
    """Rig YAML (read by ``toolkit.io.sequence.read_rig``) plus the extrinsic and its stats."""
    from toolkit.io.sequence import rig_to_dict

    d = rig_to_dict(rig)
    d.update(extrinsic_to_mapping(rig.T_camera_laser))
    d["calibration"] = info
    # Written by the CLI outside run folders: what a killed write left goes here.
    atomic_write_text(path, yaml.safe_dump(d, sort_keys=False), clean_stale=True)
