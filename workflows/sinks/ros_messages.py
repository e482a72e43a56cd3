"""Builders of ROS messages (rosbags message objects) from fleetcal arrays.

Every builder takes ``profile`` (``"ros2"`` or ``"ros1"``) and returns an object of that profile's
typestore, ready for ``typestore.serialize_cdr`` / ``serialize_ros1`` (``LogWriter.write`` does
this). Type names are ROS 2 style (``sensor_msgs/msg/PointCloud2``) in both profiles. Everything a
builder writes round-trips through ``readers.decode``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.transforms import to_quat
from fleetcal.readers.decode.pointcloud2 import POINTFIELD_DTYPES

Profile = Literal["ros1", "ros2"]

_POINTFIELD_CODES = {dt.str[1:]: code for code, dt in POINTFIELD_DTYPES.items()}

IMAGE_ENCODINGS = (
    "mono8",
    "mono16",
    "rgb8",
    "bgr8",
    "rgba8",
    "bgra8",
    "bayer_rggb8",
    "bayer_bggr8",
    "bayer_gbrg8",
    "bayer_grbg8",
)
"""Encodings ``image`` can write (and ``readers.decode.decode_image`` reads)."""

_BAYER_OFFSETS = {
    "bayer_rggb8": {"r": (0, 0), "b": (1, 1)},
    "bayer_bggr8": {"r": (1, 1), "b": (0, 0)},
    "bayer_gbrg8": {"r": (1, 0), "b": (0, 1)},
    "bayer_grbg8": {"r": (0, 1), "b": (1, 0)},
}
"""(row, column) of the red and blue sample in each 2x2 Bayer cell; green fills the other two."""

_TFMESSAGE_ROS1 = "geometry_msgs/TransformStamped[] transforms\n"
"""tf2_msgs/TFMessage, which the Noetic typestore of rosbags lacks (its other types are there)."""


@cache
def get_store(profile: Profile) -> Typestore:
    """The shared typestore of a profile: ROS 2 Humble (``ros2``) or ROS 1 Noetic + tf2_msgs (``ros1``).

    Callers must not register types in it; make a private ``get_typestore`` for that.
    """
    if profile == "ros2":
        return get_typestore(Stores.ROS2_HUMBLE)
    if profile == "ros1":
        store = get_typestore(Stores.ROS1_NOETIC)
        store.register(get_types_from_msg(_TFMESSAGE_ROS1, "tf2_msgs/msg/TFMessage"))
        return store
    raise InputError(f"unknown message profile {profile!r} (expected 'ros1' or 'ros2')")


def _types(profile: Profile) -> dict[str, Any]:
    return get_store(profile).types


def _time(stamp_ns: int, profile: Profile) -> Any:
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise InputError(f"negative stamp {stamp_ns} ns cannot be written to a ROS message")
    Time = _types(profile)["builtin_interfaces/msg/Time"]
    return Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)


def header(stamp_ns: int, frame_id: str, profile: Profile = "ros2") -> Any:
    """``std_msgs/msg/Header`` (ROS 1: with ``seq`` 0)."""
    Header = _types(profile)["std_msgs/msg/Header"]
    if profile == "ros1":
        return Header(seq=0, stamp=_time(stamp_ns, profile), frame_id=frame_id)
    return Header(stamp=_time(stamp_ns, profile), frame_id=frame_id)


def _pack_rgb(r: NDArray[Any], g: NDArray[Any], b: NDArray[Any]) -> NDArray[np.float32]:
    """PCL-style packed colour: uint32 0x00RRGGBB bits viewed as float32."""
    packed = (
        (np.asarray(r, dtype=np.uint32) << 16)
        | (np.asarray(g, dtype=np.uint32) << 8)
        | np.asarray(b, dtype=np.uint32)
    )
    return packed.view(np.float32)


def pointcloud2(
    stamp_ns: int,
    frame_id: str,
    points_xyz: NDArray[np.floating],
    channels: Mapping[str, NDArray[Any]] | None = None,
    *,
    organized_shape: tuple[int, int] | None = None,
    profile: Profile = "ros2",
    point_step: int | None = None,
    is_bigendian: bool = False,
) -> Any:
    """``sensor_msgs/msg/PointCloud2`` from (N, 3) points (metres, ``frame_id``) and per-point channels.

    Fields are x, y, z (float32, or float64 when ``points_xyz`` is float64) then the channels in
    order, each at its natural alignment. ``r``, ``g``, ``b`` (uint8) channels are packed PCL-style
    into one float32 ``rgb`` field. Channel dtypes must be one of the eight PointField types.

    Args:
        organized_shape: (height, width) with height * width == N for an organised cloud (invalid
            points stay in place as NaN); None writes height 1, width N.
        point_step: bytes per point; larger than the packed size adds trailing padding.
        is_bigendian: write the payload big-endian.
    """
    pts = np.asarray(points_xyz)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points_xyz must be (N, 3), got shape {pts.shape}")
    n = pts.shape[0]
    columns = _pointcloud_columns(pts, channels or {})
    layout = _point_layout(columns, ">" if is_bigendian else "<", profile)
    step = layout.packed_step if point_step is None else int(point_step)
    if step < layout.end:
        raise InputError(f"point_step {step} is smaller than the {layout.end} bytes of the fields")
    table = np.zeros(n, dtype=np.dtype({"names": layout.names, "formats": layout.formats, "offsets": layout.offsets,
                                        "itemsize": step}))
    for name, arr in columns:
        table[name] = arr
    if organized_shape is None:
        height, width = 1, n
    else:
        height, width = (int(v) for v in organized_shape)
        if height * width != n:
            raise InputError(f"organized_shape {organized_shape} does not hold {n} points")
    return _types(profile)["sensor_msgs/msg/PointCloud2"](
        header=header(stamp_ns, frame_id, profile),
        height=height,
        width=width,
        fields=layout.fields,
        is_bigendian=is_bigendian,
        point_step=step,
        row_step=step * width,
        data=table.view(np.uint8).reshape(-1),
        is_dense=bool(np.all(np.isfinite(pts))),
    )


def _pointcloud_columns(pts: NDArray[Any], channels: Mapping[str, NDArray[Any]]) -> list[tuple[str, NDArray[Any]]]:
    """(name, values) of every field in order: x, y, z (float64 points stay float64, others float32), the
    channels (bool as uint8), then r, g, b packed into one ``rgb`` (all three or none)."""
    n = pts.shape[0]
    xyz_dtype = np.dtype(np.float64) if pts.dtype == np.float64 else np.dtype(np.float32)
    columns: list[tuple[str, NDArray[Any]]] = [(axis, pts[:, i].astype(xyz_dtype)) for i, axis in enumerate("xyz")]
    chans = dict(channels)
    colour = [c for c in ("r", "g", "b") if c in chans]
    if colour and len(colour) != 3:
        raise InputError(f"colour channels need all of r, g, b; got only {', '.join(colour)}")
    for name, values in chans.items():
        arr = np.asarray(values)
        if arr.shape != (n,):
            raise InputError(f"channel {name!r} has shape {arr.shape}, expected ({n},)")
        if name in ("r", "g", "b"):
            continue
        if arr.dtype == np.bool_:
            arr = arr.astype(np.uint8)
        columns.append((name, arr))
    if colour:
        columns.append(("rgb", _pack_rgb(chans["r"], chans["g"], chans["b"])))
    return columns


@dataclass
class _PointLayout:
    """Where each field of a point lies: the PointFields, their names, NumPy formats and byte offsets, where the
    last one ends and the packed point step (that end rounded up to the largest field's alignment), bytes."""

    fields: list[Any]
    names: list[str]
    formats: list[np.dtype[Any]]
    offsets: list[int]
    end: int
    packed_step: int


def _point_layout(columns: list[tuple[str, NDArray[Any]]], order: Literal["<", ">"], profile: Profile) -> _PointLayout:
    """The layout of ``columns``, each field at its natural alignment, in byte order ``order``."""
    PointField = _types(profile)["sensor_msgs/msg/PointField"]
    fields = []
    names: list[str] = []
    formats: list[np.dtype[Any]] = []
    offsets: list[int] = []
    offset = 0
    max_align = 1
    for name, arr in columns:
        code = _POINTFIELD_CODES.get(np.dtype(arr.dtype).newbyteorder("<").str[1:])
        if code is None:
            raise InputError(f"channel {name!r} has dtype {arr.dtype}, which PointCloud2 cannot hold")
        size = POINTFIELD_DTYPES[code].itemsize
        offset = -(-offset // size) * size
        max_align = max(max_align, size)
        fields.append(PointField(name=name, offset=offset, datatype=code, count=1))
        names.append(name)
        formats.append(POINTFIELD_DTYPES[code].newbyteorder(order))
        offsets.append(offset)
        offset += size
    packed_step = -(-offset // max_align) * max_align
    return _PointLayout(fields, names, formats, offsets, offset, packed_step)


def _mosaic(rgb: NDArray[np.uint8], encoding: str) -> NDArray[np.uint8]:
    """Sample an RGB image with a Bayer pattern (one 8-bit value per pixel)."""
    out = rgb[:, :, 1].copy()
    for colour, channel in (("r", 0), ("b", 2)):
        dr, dc = _BAYER_OFFSETS[encoding][colour]
        out[dr::2, dc::2] = rgb[dr::2, dc::2, channel]
    return out


def _encode_pixels(image: NDArray[Any], encoding: str) -> NDArray[Any]:
    """Pixels of ``image`` (grey or RGB, fleetcal layout) in the byte layout of ``encoding``."""
    img = np.asarray(image)
    if encoding == "mono16":
        if img.ndim != 2 or img.dtype not in (np.uint16, np.uint8):
            raise InputError(f"mono16 needs an (H, W) uint16 image, got {img.dtype} {img.shape}")
        return img.astype(np.uint16)
    if img.dtype != np.uint8:
        raise InputError(f"{encoding} needs a uint8 image, got {img.dtype}")
    if encoding == "mono8":
        if img.ndim == 3:
            return np.asarray(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
        return img
    rgb = img if img.ndim == 3 else np.repeat(img[:, :, None], 3, axis=2)
    if rgb.shape[2] != 3:
        raise InputError(f"colour image must be (H, W, 3) RGB, got shape {img.shape}")
    if encoding == "rgb8":
        return rgb
    if encoding == "bgr8":
        return rgb[:, :, ::-1]
    if encoding in ("rgba8", "bgra8"):
        alpha = np.full((*rgb.shape[:2], 1), 255, dtype=np.uint8)
        base = rgb if encoding == "rgba8" else rgb[:, :, ::-1]
        return np.concatenate([base, alpha], axis=2)
    if encoding in _BAYER_OFFSETS:
        return _mosaic(rgb, encoding)
    raise InputError(f"cannot write image encoding {encoding!r}; supported: {', '.join(IMAGE_ENCODINGS)}")


def image(
    stamp_ns: int,
    frame_id: str,
    image: NDArray[Any],
    encoding: str,
    profile: Profile = "ros2",
    *,
    row_padding: int = 0,
    is_bigendian: bool = False,
) -> Any:
    """``sensor_msgs/msg/Image`` of ``image`` ((H, W) grey or (H, W, 3) RGB) stored as ``encoding``.

    Colour is converted to the encoding's layout (bgr8 swaps channels, rgba8/bgra8 add alpha 255,
    bayer_* samples the mosaic); ``row_padding`` adds zero bytes at the end of each row (``step``).
    ``is_bigendian`` only changes mono16 byte order.
    """
    pixels = _encode_pixels(image, encoding)
    height, width = pixels.shape[:2]
    if pixels.dtype == np.uint16:
        pixels = pixels.astype(">u2" if is_bigendian else "<u2")
    row = np.ascontiguousarray(pixels).view(np.uint8).reshape(height, -1)
    if row_padding:
        row = np.concatenate([row, np.zeros((height, int(row_padding)), dtype=np.uint8)], axis=1)
    return _types(profile)["sensor_msgs/msg/Image"](
        header=header(stamp_ns, frame_id, profile),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=int(is_bigendian),
        step=row.shape[1],
        data=np.ascontiguousarray(row).reshape(-1),
    )


def compressed_image(
    stamp_ns: int,
    frame_id: str,
    image: NDArray[Any],
    fmt: Literal["jpeg", "png"] = "jpeg",
    quality: int = 90,
    profile: Profile = "ros2",
) -> Any:
    """``sensor_msgs/msg/CompressedImage`` (jpeg or png, OpenCV) of an (H, W) grey or (H, W, 3) RGB image."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if fmt == "jpeg":
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    elif fmt == "png":
        ok, buf = cv2.imencode(".png", img)
    else:
        raise InputError(f"cannot write compressed image format {fmt!r}; supported: jpeg, png")
    if not ok:
        raise InputError(f"OpenCV could not encode a {img.dtype} {img.shape} image as {fmt}")
    return _types(profile)["sensor_msgs/msg/CompressedImage"](
        header=header(stamp_ns, frame_id, profile),
        format=fmt,
        data=np.asarray(buf, dtype=np.uint8).reshape(-1),
    )


def camera_info(stamp_ns: int, frame_id: str, camera: CameraModel, profile: Profile = "ros2") -> Any:
    """``sensor_msgs/msg/CameraInfo`` of a camera model (R its ``R_rect`` or the identity, P = [K | 0]).

    ``none`` is written as ``plumb_bob`` with zero coefficients; ``cylindrical`` is written by name
    (not a ROS model; only fleetcal reads it back).
    """
    model = camera.distortion_model
    D = camera.D
    if model == "none":
        model, D = "plumb_bob", np.zeros(5)
    P = np.zeros((3, 4))
    P[:, :3] = camera.K
    arrays = {
        "d": np.asarray(D, dtype=np.float64).copy(),
        "k": camera.K.reshape(-1).astype(np.float64),
        "r": (np.eye(3) if camera.R_rect is None else camera.R_rect).reshape(-1).astype(np.float64),
        "p": P.reshape(-1),
    }
    if profile == "ros1":
        arrays = {key.upper(): value for key, value in arrays.items()}
    types = _types(profile)
    roi = types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return types["sensor_msgs/msg/CameraInfo"](
        header=header(stamp_ns, frame_id, profile),
        height=camera.height,
        width=camera.width,
        distortion_model=model,
        binning_x=0,
        binning_y=0,
        roi=roi,
        **arrays,
    )


def _pose_parts(T: NDArray[np.float64], profile: Profile) -> tuple[Any, Any]:
    types = _types(profile)
    t, q = to_quat(np.asarray(T, dtype=np.float64))
    quat = types["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
    return t, quat


def tf_message(
    transforms: Sequence[tuple[int, str, str, NDArray[np.float64]]], profile: Profile = "ros2"
) -> Any:
    """``tf2_msgs/msg/TFMessage`` from (stamp_ns, parent, child, T_parent_child) tuples."""
    types = _types(profile)
    items = []
    for stamp_ns, parent, child, T_parent_child in transforms:
        t, quat = _pose_parts(T_parent_child, profile)
        vec = types["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]), z=float(t[2]))
        items.append(
            types["geometry_msgs/msg/TransformStamped"](
                header=header(stamp_ns, parent, profile),
                child_frame_id=child,
                transform=types["geometry_msgs/msg/Transform"](translation=vec, rotation=quat),
            )
        )
    return types["tf2_msgs/msg/TFMessage"](transforms=items)


def path(
    stamp_ns: int,
    frame_id: str,
    stamps_ns: Sequence[int] | NDArray[np.int64],
    T_frame_poses: NDArray[np.float64] | Sequence[NDArray[np.float64]],
    profile: Profile = "ros2",
) -> Any:
    """``nav_msgs/msg/Path`` in ``frame_id``: one PoseStamped per (stamp_ns, 4x4 ``T_frame_pose``)."""
    poses_T = np.asarray(T_frame_poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(stamps_ns) != poses_T.shape[0]:
        raise InputError(f"path has {len(stamps_ns)} stamps but {poses_T.shape[0]} poses")
    types = _types(profile)
    poses = []
    for stamp, T in zip(stamps_ns, poses_T, strict=True):
        t, quat = _pose_parts(T, profile)
        point = types["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2]))
        poses.append(
            types["geometry_msgs/msg/PoseStamped"](
                header=header(int(stamp), frame_id, profile),
                pose=types["geometry_msgs/msg/Pose"](position=point, orientation=quat),
            )
        )
    return types["nav_msgs/msg/Path"](header=header(stamp_ns, frame_id, profile), poses=poses)
