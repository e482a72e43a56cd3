"""Sensor rig, calibration perturbation and the ``<log>.truth.json`` ground-truth file.

The truth file has the schema of ``../shared/data/logs/*.truth.json`` (``lidar_topic``, ``lidar_frame``,
``pairs[]`` with ``camera_topic``, ``camera_frame``, ``T_camera_lidar`` (true), ``T_camera_lidar_in_log``
(what the log's ``/tf_static`` gives)) plus, per pair, the camera's clock ``time_offset_s`` (camera clock minus
lidar clock, s) and ``readout_s`` (rolling-shutter time from the first to the last image row, s; 0: global
shutter), plus ``trajectory`` (per lidar scan ``stamp_ns`` and ``T_map_lidar``,
map = the first scan's lidar frame), ``scene``, ``seed`` and ``format``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.errors import ConfigError
from fleetcal.pipeline.transforms import from_xyz_rpy, invert, make_T
from fleetcal.stages.sinks.atomic import atomic_path

LIDAR_FRAME = "lidar"
BASE_FRAME = "base_link"
ODOM_FRAME = "odom"
LIDAR_TOPIC = "/lidar/points"
CAMERA_YAWS_DEG = (0.0, 90.0, -90.0, 180.0, 45.0, -45.0, 135.0, -135.0)
MAX_CAMERAS = len(CAMERA_YAWS_DEG)
DRIFTS = ("cameras", "lidar")
"""What a simulated log's calibration gets wrong (``build_rig``'s ``drift``)."""
# base_link (x forward, y left, z up) -> camera optical (x right, y down, z forward), columns = optical axes
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_frame(index: int) -> str:
    return f"camera_{index}_optical"


def camera_topics(index: int, compressed: bool, rectified: bool = False) -> tuple[str, str]:
    """(image topic, camera_info topic) of camera ``index`` (``image_rect`` for rectified images)."""
    image = f"/camera_{index}/{'image_rect' if rectified else 'image_raw'}" + ("/compressed" if compressed else "")
    return image, f"/camera_{index}/camera_info"


@dataclass(frozen=True)
class Rig:
    """Sensor poses on the vehicle (true values) and the perturbed calibration the log carries.

    Attributes:
        T_base_lidar: lidar pose in base_link.
        T_base_cameras: (C, 4, 4) camera optical frame poses in base_link (true).
        T_camera_lidar_in_log: (C, 4, 4) perturbed extrinsics written to ``/tf_static``.
    """

    T_base_lidar: NDArray[np.float64]
    T_base_cameras: NDArray[np.float64]
    T_camera_lidar_in_log: NDArray[np.float64]

    @property
    def T_camera_lidar(self) -> NDArray[np.float64]:
        """(C, 4, 4) true extrinsics ``T_camera_lidar``."""
        return np.stack([invert(T) @ self.T_base_lidar for T in self.T_base_cameras])


def perturb(
    T: NDArray[np.float64], rotation_deg: float, translation_m: float, rng: np.random.Generator
) -> NDArray[np.float64]:
    """``T`` with its rotation turned by exactly ``rotation_deg`` about a random axis (applied on the left)
    and its translation moved by exactly ``translation_m`` in a random direction."""
    if not (np.isfinite(rotation_deg) and np.isfinite(translation_m)) or rotation_deg < 0 or translation_m < 0:
        raise ConfigError("perturbation must be non-negative finite degrees and metres")
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    direction = rng.standard_normal(3)
    direction /= np.linalg.norm(direction)
    R = Rotation.from_rotvec(axis * np.radians(rotation_deg)).as_matrix() @ T[:3, :3]
    return make_T(R, T[:3, 3] + direction * translation_m)


def build_rig(cameras: int, lidar_height_m: float, perturb_deg: float, perturb_m: float, seed: int,
              lidar_roll_deg: float = 0.0, camera_yaw_deg: float = 0.0, camera_roll_deg: float = 0.0,
              drift: str = "cameras") -> Rig:
    """Lidar on the roof, rolled ``lidar_roll_deg`` about its forward (x) axis (0: level); camera i looks
    along ``CAMERA_YAWS_DEG[i]`` plus ``camera_yaw_deg`` (left positive), 0.3 m out from the lidar and 0.35 m
    below it, pitched about 4 deg down, rolled ``camera_roll_deg`` about its optical axis, with small seeded
    mounting errors.

    ``drift``: what the log's calibration gets wrong. ``cameras``: each camera's extrinsic is perturbed on its
    own (every pair drifted apart). ``lidar``: the lidar's mount is perturbed once (turned ``perturb_deg`` in
    the base frame about its own origin, moved ``perturb_m``), so every camera's extrinsic is off by the same
    lidar drift and the tf between the cameras is exact, which is what ``calibrate --joint`` assumes."""
    if not 1 <= cameras <= MAX_CAMERAS:
        raise ConfigError(f"cameras must be 1..{MAX_CAMERAS}, got {cameras}")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x716]))
    T_base_lidar = from_xyz_rpy(0.1, 0.0, lidar_height_m, lidar_roll_deg, 0.0, 0.0)
    T_base_cameras = []
    for i in range(cameras):
        yaw = CAMERA_YAWS_DEG[i] + camera_yaw_deg
        roll_err, pitch_err, yaw_err = rng.uniform(-1.0, 1.0, size=3)
        R_mount = Rotation.from_euler("xyz", [roll_err, 4.0 + pitch_err, yaw + yaw_err], degrees=True).as_matrix()
        if camera_roll_deg:
            R_mount = R_mount @ R_BASE_OPTICAL @ Rotation.from_euler("z", camera_roll_deg, degrees=True).as_matrix() \
                @ R_BASE_OPTICAL.T
        offset = np.array([0.3 * np.cos(np.radians(yaw)), 0.3 * np.sin(np.radians(yaw)), -0.35])
        T_base_cameras.append(make_T(R_mount @ R_BASE_OPTICAL, T_base_lidar[:3, 3] + offset))
    cams = np.stack(T_base_cameras)
    if drift == "lidar":
        T_base_lidar_in_log = perturb(T_base_lidar, perturb_deg, perturb_m, rng)
        in_log = np.stack([invert(T) @ T_base_lidar_in_log for T in cams])
    elif drift == "cameras":
        in_log = np.stack([perturb(invert(T) @ T_base_lidar, perturb_deg, perturb_m, rng) for T in cams])
    else:
        raise ConfigError(f"drift must be one of {', '.join(DRIFTS)}, got {drift!r}")
    return Rig(T_base_lidar=T_base_lidar, T_base_cameras=cams, T_camera_lidar_in_log=in_log)


def truth_path_for(log_path: str | os.PathLike[str]) -> Path:
    """``street.mcap`` -> ``street.truth.json``; ``run.bag`` -> ``run.truth.json``; folder ``bag2`` ->
    ``bag2.truth.json`` (as in ``../shared/data/logs``)."""
    p = Path(log_path)
    name = p.name[: -len(p.suffix)] if p.suffix in (".mcap", ".bag") else p.name
    return p.with_name(name + ".truth.json")


def build_truth(
    *,
    rig: Rig,
    compressed: bool,
    scan_stamps_ns: list[int],
    T_map_lidar: NDArray[np.float64],
    scene: str,
    seed: int,
    fmt: str,
    extra: dict[str, Any] | None = None,
    rectified: bool = False,
    time_offset_s: float = 0.0,
    readout_s: float = 0.0,
) -> dict[str, Any]:
    """The truth document (JSON-ready: lists, ints, floats). ``time_offset_s`` (camera clock minus lidar
    clock, s) and ``readout_s`` (rolling-shutter readout, s) are every camera's."""
    pairs = []
    for i, (T_true, T_log) in enumerate(zip(rig.T_camera_lidar, rig.T_camera_lidar_in_log, strict=True)):
        pairs.append(
            {
                "camera_topic": camera_topics(i, compressed, rectified)[0],
                "camera_frame": camera_frame(i),
                "T_camera_lidar": T_true.tolist(),
                "T_camera_lidar_in_log": T_log.tolist(),
                "time_offset_s": float(time_offset_s),
                "readout_s": float(readout_s),
            }
        )
    doc: dict[str, Any] = {
        "source": "fleetcal simulate (synthetic, exact ground truth)",
        "format": fmt,
        "scene": scene,
        "seed": int(seed),
        "lidar_topic": LIDAR_TOPIC,
        "lidar_frame": LIDAR_FRAME,
        "pairs": pairs,
        "T_base_lidar": rig.T_base_lidar.tolist(),
        "trajectory": [
            {"stamp_ns": int(s), "T_map_lidar": T.tolist()} for s, T in zip(scan_stamps_ns, T_map_lidar, strict=True)
        ],
    }
    doc.update(extra or {})
    return doc


def write_truth(path: str | os.PathLike[str], truth: dict[str, Any]) -> Path:
    """Write ``truth`` as indented JSON, atomically."""
    out = Path(path)
    with atomic_path(out) as tmp:
        Path(tmp).write_text(json.dumps(truth, indent=1) + "\n")
    return out


def load_truth(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a truth file; 4x4 lists become float64 arrays. A pair without ``time_offset_s`` or ``readout_s``
    gets 0.0 s for it (synchronised clocks, global shutter)."""
    doc: dict[str, Any] = json.loads(Path(path).read_text())
    for pair in doc.get("pairs", []):
        for key in ("T_camera_lidar", "T_camera_lidar_in_log"):
            pair[key] = np.asarray(pair[key], dtype=np.float64)
        for key in ("time_offset_s", "readout_s"):
            pair[key] = float(pair.get(key, 0.0))
    for entry in doc.get("trajectory", []):
        entry["T_map_lidar"] = np.asarray(entry["T_map_lidar"], dtype=np.float64)
    return doc
