"""``tf2_msgs/TFMessage`` -> (stamp_ns, parent, child, T_parent_child) tuples."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import TransformError
from fleetcal.pipeline.transforms import from_quat
from fleetcal.readers.decode.common import stamp_to_ns

QUAT_NORM_RANGE = (0.9, 1.1)
"""Quaternions with a norm inside this open range are renormalised; others are rejected."""


def decode_transform(stamped: Any) -> tuple[int, str, str, NDArray[np.float64]]:
    """One ``geometry_msgs/TransformStamped`` as (stamp_ns, parent, child, ``T_parent_child``).

    Raises:
        TransformError: NaN/infinite values, a quaternion norm outside ``QUAT_NORM_RANGE``, or
            an empty frame name.
    """
    parent = str(stamped.header.frame_id).lstrip("/")
    child = str(stamped.child_frame_id).lstrip("/")
    if not parent or not child:
        raise TransformError(f"transform {parent or '?'} -> {child or '?'} has an empty frame name")
    t = stamped.transform.translation
    q = stamped.transform.rotation
    translation = np.array([t.x, t.y, t.z], dtype=np.float64)
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    if not (np.all(np.isfinite(translation)) and np.all(np.isfinite(quat))):
        raise TransformError(f"transform {parent} -> {child} has NaN or infinite values")
    with np.errstate(over="ignore"):  # a huge (corrupt) quaternion overflows to inf and is rejected below
        norm = float(np.linalg.norm(quat))
    low, high = QUAT_NORM_RANGE
    if not low < norm < high:
        raise TransformError(
            f"transform {parent} -> {child} has a quaternion of norm {norm:.3g} (not a rotation)"
        )
    return stamp_to_ns(stamped.header.stamp), parent, child, from_quat(translation, quat / norm)


def decode_tf(msg: Any) -> list[tuple[int, str, str, NDArray[np.float64]]]:
    """Every transform of a TFMessage, leading '/' stripped from frame names.

    Raises:
        TransformError: for the first invalid transform (see ``decode_transform``); use
            ``decode_transform`` per entry to skip bad ones instead.
    """
    return [decode_transform(stamped) for stamped in msg.transforms]
