"""ROS bags with ``sensor_msgs/PointCloud2`` messages (ROS 2 directories, ROS 1 ``.bag`` files)
via the ``rosbags`` package.

Reading: every message of one PointCloud2 topic becomes a scan (``times`` = header stamp + the
``time``/``t`` field when present). Organized clouds (``height > 1``) keep their grid; otherwise a
``ring`` field builds one (see :mod:`mi_lidar.io.cloud`). Scans of different sizes are padded with
invalid cells (``attributes['valid']`` False). Fields beyond the standard ones become attributes.
A scan's pose is its cloud's ``frame_id`` resolved through ``/tf_static`` and ``/tf`` (the latest
transform at or before the cloud's stamp) up to the root frame; identity when the bag has none.

Writing: a ROS 2 bag (sqlite3 storage, Humble message definitions) with one organized ``H x W``
PointCloud2 per scan on ``topic``: fields ``x y z intensity`` (FLOAT32), ``ring`` (UINT16, 0 =
lowest beam), ``column`` (UINT32) and ``time`` (FLOAT32, s since the scan's first ray), then one
field per other attribute of the log (``label``, ``element_id``, ``valid``...: its own type;
booleans as UINT8, 64-bit integers as INT32/UINT32 when they fit, else FLOAT64), misses
as NaN points with ``is_dense`` False, which RViz and Open3D accept. Poses go on ``/tf``: one
``tf2_msgs/TFMessage`` per scan at the scan's stamp with ``world_frame -> base_frame`` = the scan's
sensor-to-world pose, and ``/tf_static`` holds the identity ``base_frame -> frame_id`` (the log's
poses are the sensor's own), so RViz with fixed frame ``map`` places every scan, and
:func:`read_rosbag_log` reads them back.

The log's sensor metadata (``log.sensor``: name, pattern, ranges...) goes on ``<topic>/sensor_info``
(``/points/sensor_info``): one ``std_msgs/String`` holding it as a strict JSON object (a non-finite value,
such as ``max_range`` inf, is null there and listed under ``$non_finite``:
:func:`~mi_lidar.core.strict_json.dumps_exact`), latched (transient
local, as ``/tf_static``) and stamped with the first scan, so ``ros2 topic echo`` shows it during
``ros2 bag play``. Per-ray origins (m, sensor frame), when any is non-zero (a sensor whose beams
leave from an offset, e.g. Ouster's beam origins), have no place in a PointCloud2: they go as three
more FLOAT32 fields ``origin_x origin_y origin_z`` per point, while ``x y z`` stay the return point
(origin + range x direction) that viewers draw. Read back, both make the log the one written:
``log.sensor`` is the JSON object as written and every ray keeps its origin.
"""

from __future__ import annotations

import errno
import os
import shutil
import sqlite3
import tempfile
from pathlib import Path

import numpy as np

from mi_lidar.core.errors import LogFormatError, parser_message, unreadable
from mi_lidar.core.log import Log
from mi_lidar.core.strict_json import dumps_exact, loads_exact
from mi_lidar.io.cloud import ORIGIN_FIELDS, STANDARD_FIELDS, cloud_from_log, log_from_fields, stack_scans

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
SENSOR_INFO = "/sensor_info"  # the sensor metadata topic: the cloud topic plus this suffix
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_WRITE_FIELDS = (("x", 7), ("y", 7), ("z", 7), ("intensity", 7), ("ring", 4), ("column", 6), ("time", 7))
_FIELD_TYPES = {np.dtype(code): datatype for datatype, code in _DATATYPES.items()}
MAX_TF_DEPTH = 16  # frames walked from a cloud's frame_id towards the root of the tf tree


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def decode_pointcloud2(msg, where: str) -> tuple[dict[str, np.ndarray], int, int]:
    """Decode a deserialized PointCloud2 into ``(fields, width, height)`` (fields row-major (N,))."""
    height, width, step, row_step = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for field in msg.fields:
        if field.datatype not in _DATATYPES:
            raise LogFormatError(f"{where}: field {field.name!r} has unknown datatype {field.datatype}")
        for k in range(max(int(field.count), 1)):
            names.append(field.name if field.count <= 1 else f"{field.name}_{k}")
            formats.append(order + _DATATYPES[field.datatype])
            offsets.append(int(field.offset) + k * np.dtype(_DATATYPES[field.datatype]).itemsize)
    data = np.asarray(msg.data, dtype=np.uint8)
    if (
        row_step < width * step
        or len(data) < height * row_step
        or (offsets and max(o + np.dtype(f).itemsize for o, f in zip(offsets, formats)) > step)
    ):
        raise LogFormatError(
            f"{where}: PointCloud2 layout inconsistent (height {height}, width {width}, point_step {step}, "
            f"row_step {row_step}, {len(data)} data bytes)"
        )
    try:
        record = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    except ValueError as exc:
        raise LogFormatError(f"{where}: invalid PointCloud2 fields ({exc})") from exc
    rows = data[: height * row_step].reshape(height, row_step)[:, : width * step]
    table = np.ascontiguousarray(rows).view(record).reshape(-1)
    return {n: table[n].astype(record[n].newbyteorder("=")) for n in names}, width, height


def read_rosbag_log(path: str | os.PathLike, topic: str | None = None, min_range: float = 0.0) -> Log:
    """Read the PointCloud2 messages of one topic as a multi-scan log.

    Args:
        path: A ROS 2 bag directory (or its ``.db3``/``.mcap`` file) or a ROS 1 ``.bag``.
        topic: The PointCloud2 topic; may be omitted when the bag has exactly one.
        min_range: Points closer than this are misses (m).

    Returns:
        A log of one scan per message (padded to the largest grid). ``sensor`` is the JSON object of the
        topic's ``sensor_info`` when the bag has one (a bag :func:`write_rosbag_log` wrote), else the topic,
        the bag and the cloud's frame; ray origins come from ``origin_x/y/z`` fields when present.

    Raises:
        LogFormatError: Unreadable bag, no (or several, without ``topic``) PointCloud2 topics, fewer
            messages than the bag's metadata counts, a message whose layout is inconsistent, or a
            ``sensor_info`` that is not a JSON object.
    """
    from rosbags.highlevel import AnyReader

    path = Path(path)
    if path.is_file() and path.suffix in (".db3", ".mcap"):
        path = path.parent
    if not path.exists():
        raise LogFormatError(f"{path}: no such ROS bag")
    for part in sorted(path.iterdir()) if path.is_dir() else [path]:  # (was 'damaged or incomplete: copy it again')
        if part.is_file() and not os.access(part, os.R_OK):
            raise unreadable(part, "bag file")
    if path.is_dir():
        path = _BagFolder(path)
    logs, poses = [], []
    try:
        with AnyReader([path], default_typestore=_typestore()) as reader:
            tree = _read_tf(reader)
            clouds = sorted({c.topic for c in reader.connections if c.msgtype == POINTCLOUD2})
            if topic is None and len(clouds) != 1:
                raise LogFormatError(f"{path}: PointCloud2 topics {clouds}; pass topic= to choose exactly one")
            chosen = topic or clouds[0]
            if chosen not in clouds:
                raise LogFormatError(f"{path}: no PointCloud2 topic {chosen!r}; found {clouds}")
            connections = [c for c in reader.connections if c.topic == chosen]
            for index, (connection, _, raw) in enumerate(reader.messages(connections=connections)):
                msg = reader.deserialize(raw, connection.msgtype)
                where = f"{path}: {chosen} message {index}"
                fields, width, height = decode_pointcloud2(msg, where)
                if any(c not in fields for c in "xyz"):
                    raise LogFormatError(f"{where}: PointCloud2 lacks x y z fields")
                if "ring" not in fields and height > 1:
                    rows, cols = np.indices((height, width))
                    fields.update(ring=(height - 1 - rows).ravel(), column=cols.ravel())
                stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
                poses.append(
                    _frame_pose(tree, msg.header.frame_id, msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
                )
                logs.append(
                    log_from_fields(
                        fields,
                        min_range=min_range,
                        start_time=stamp,
                        sensor={"name": f"rosbag:{chosen}", "source": str(path), "frame_id": msg.header.frame_id},
                    )
                )
            sensor = _read_sensor_info(reader, path, chosen)
    except LogFormatError:
        raise
    except Exception as exc:  # rosbags raises many reader/deserializer error types.
        raise LogFormatError(
            f"{path}: not a readable ROS bag ({type(exc).__name__}: {parser_message(exc)}); the bag is damaged or "
            "incomplete: copy it again or record it again"
        ) from exc
    if not logs:
        raise LogFormatError(f"{path}: topic {chosen!r} has no messages")
    counted = _message_count(path, chosen, connections)
    if len(logs) < counted:
        raise LogFormatError(
            f"{path}: its metadata counts {counted} messages on {chosen}, its storage holds {len(logs)}: the bag is "
            f"incomplete (a recording cut short, a storage file replaced?); if the storage is what you have, rebuild "
            f"the metadata from it with `ros2 bag reindex {path}`"
        )
    log = stack_scans(logs)
    log.poses = np.stack(poses)
    if sensor is not None:
        log.sensor = sensor
    return log


def _message_count(path, topic: str, connections) -> int:
    """The number of messages the bag's metadata counts on ``topic`` (its connections' ``message_count``).

    Raises:
        LogFormatError: a count that is not a whole number >= 0 (a damaged ``metadata.yaml``).
    """
    for connection in connections:
        count = connection.msgcount
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise LogFormatError(
                f"{path}: its metadata counts {count!r} messages on {topic}; a message_count is a whole number >= 0: "
                f"repair metadata.yaml, or rebuild it from the storage with `ros2 bag reindex {path}`"
            )
    return sum(c.msgcount for c in connections)


class _BagFolder(type(Path())):  # type: ignore[misc]
    """A ROS 2 bag folder, whatever its name: rosbags' ``AnyReader`` takes every ``*.bag`` path for a ROS 1 file,
    so a folder ``drive.bag`` (which :func:`write_rosbag_log` writes for ``convert log.npz drive.bag``) read as
    "Is a directory"."""

    @property
    def suffix(self) -> str:
        return ""


def _read_sensor_info(reader, path: Path, topic: str) -> dict | None:
    """The sensor metadata on ``topic`` + :data:`SENSOR_INFO` (a JSON object in a ``std_msgs/String``), or None
    when the bag has none.

    Raises:
        LogFormatError: the message is not a JSON object (the bag and topic named).
    """
    connections = [c for c in reader.connections if c.topic == topic + SENSOR_INFO and c.msgtype == STRING]
    if not connections:
        return None
    for connection, _, raw in reader.messages(connections=connections):
        text = reader.deserialize(raw, connection.msgtype).data
        try:
            sensor = loads_exact(text)
        except ValueError as exc:
            raise LogFormatError(f"{path}: {topic + SENSOR_INFO} is not JSON ({exc}); record the bag again") from exc
        if not isinstance(sensor, dict):
            raise LogFormatError(f"{path}: {topic + SENSOR_INFO} holds a {type(sensor).__name__}; expected an object")
        return sensor
    return None


def _matrix(transform) -> np.ndarray:
    """The (4, 4) matrix of a ``geometry_msgs/Transform``."""
    from scipy.spatial.transform import Rotation

    q, v = transform.rotation, transform.translation
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    matrix[:3, 3] = v.x, v.y, v.z
    return matrix


def _read_tf(reader) -> dict[str, list[tuple[int, str, np.ndarray]]]:
    """Every transform of ``/tf`` and ``/tf_static``: child frame -> ``(stamp ns, parent, (4, 4))`` by stamp.

    A static transform holds at every time (stamp -1).
    """
    tree: dict[str, list[tuple[int, str, np.ndarray]]] = {}
    connections = [c for c in reader.connections if c.topic in ("/tf", "/tf_static") and c.msgtype == TF_MESSAGE]
    if not connections:
        return tree  # (an empty list would read every message)
    for connection, _, raw in reader.messages(connections=connections):
        static = connection.topic == "/tf_static"
        for stamped in reader.deserialize(raw, connection.msgtype).transforms:
            stamp = -1 if static else stamped.header.stamp.sec * 10**9 + stamped.header.stamp.nanosec
            tree.setdefault(stamped.child_frame_id, []).append(
                (stamp, stamped.header.frame_id, _matrix(stamped.transform))
            )
    for entries in tree.values():
        entries.sort(key=lambda entry: entry[0])
    return tree


def _frame_pose(tree: dict, frame: str, stamp: int) -> np.ndarray:
    """The (4, 4) pose of ``frame`` in the root frame of ``tree`` at ``stamp`` (ns); identity without transforms.

    Each step up the tree takes the latest transform at or before ``stamp`` (the earliest when all
    are later).
    """
    pose = np.eye(4)
    for _ in range(MAX_TF_DEPTH):
        entries = tree.get(frame)
        if not entries:
            break
        before = [entry for entry in entries if entry[0] <= stamp]
        _, frame, matrix = before[-1] if before else entries[0]
        pose = matrix @ pose
    return pose


def _latched_qos() -> list:
    """The QoS ``ros2 bag record`` offers for ``/tf_static``: reliable, transient local (latched)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    forever = QosTime(2147483647, 4294967295)
    return [
        Qos(
            QosHistory.KEEP_LAST,
            1,
            QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL,
            forever,
            forever,
            QosLiveliness.AUTOMATIC,
            forever,
            avoid_ros_namespace_conventions=False,
        )
    ]


def _tf_message(types, stamp, parent: str, child: str, pose: np.ndarray):
    """A ``tf2_msgs/TFMessage`` with one transform ``parent -> child`` = (4, 4) ``pose``."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
    transform = types["geometry_msgs/msg/Transform"](
        translation=types["geometry_msgs/msg/Vector3"](x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3])),
        rotation=types["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z), w=float(w)),
    )
    header = types["std_msgs/msg/Header"](stamp=stamp, frame_id=parent)
    stamped = types["geometry_msgs/msg/TransformStamped"](header=header, child_frame_id=child, transform=transform)
    return types[TF_MESSAGE](transforms=[stamped])


def _attribute_fields(log: Log) -> list[tuple[str, int]]:
    """``(name, PointField datatype)`` of the log's attributes beyond the standard fields."""
    fields = []
    for name, values in sorted(log.attributes.items()):
        if name in STANDARD_FIELDS or name in ORIGIN_FIELDS:
            continue
        dtype = np.dtype(values.dtype)
        if dtype.kind == "b":
            dtype = np.dtype("u1")
        elif dtype.kind in "iu" and dtype.itemsize == 8:
            small = np.dtype(dtype.kind + "4")
            fits = values.size == 0 or (np.iinfo(small).min <= values.min() and values.max() <= np.iinfo(small).max)
            dtype = small if fits else np.dtype("f8")
        fields.append((name, _FIELD_TYPES.get(dtype, 8)))  # another type (float16...) as FLOAT64
    return fields


def write_rosbag_log(
    log: Log,
    path: str | os.PathLike,
    topic: str = "/points",
    frame_id: str = "lidar",
    world_frame: str = "map",
    base_frame: str = "base_link",
) -> Path:
    """Write every scan of ``log`` as a PointCloud2 message into a new ROS 2 bag directory, with the
    poses on ``/tf`` and ``/tf_static``, the sensor metadata on ``<topic>/sensor_info`` and non-zero ray
    origins as ``origin_x origin_y origin_z`` fields (see the module docstring).

    The bag is written to a temporary directory next to ``path`` and renamed when complete.

    Raises:
        FileExistsError: ``path`` already exists (bags are never overwritten).
        OSError: the bag could not be written (a full disk, ``ulimit -f``), naming ``path``; nothing is left.
    """
    from rosbags.rosbag2 import Writer

    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists; remove it or choose another bag name")
    path.parent.mkdir(parents=True, exist_ok=True)
    store = _typestore()
    types = store.types
    point_field = types["sensor_msgs/msg/PointField"]
    layout, offset = [], 0
    with_origins = bool(np.any(log.origins != 0))
    attribute_fields = _attribute_fields(log)
    fields = [*_WRITE_FIELDS, *attribute_fields, *((name, 7) for name in ORIGIN_FIELDS if with_origins)]
    for name, datatype in fields:
        layout.append(point_field(name=name, offset=offset, datatype=datatype, count=1))
        offset += np.dtype(_DATATYPES[datatype]).itemsize
    record = np.dtype(
        {
            "names": [n for n, _ in fields],
            "formats": ["<" + _DATATYPES[d] for _, d in fields],
            "offsets": [f.offset for f in layout],
            "itemsize": offset,
        }
    )
    _, height, width = log.shape
    staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        bag = staging / "bag"
        with Writer(bag, version=8) as writer:
            connection = writer.add_connection(topic, POINTCLOUD2, typestore=store)
            tf = writer.add_connection("/tf", TF_MESSAGE, typestore=store)
            tf_static = writer.add_connection(
                "/tf_static", TF_MESSAGE, typestore=store, offered_qos_profiles=_latched_qos()
            )
            sensor_info = writer.add_connection(
                topic + SENSOR_INFO, STRING, typestore=store, offered_qos_profiles=_latched_qos()
            )
            for index in range(log.n_scans):
                cloud = cloud_from_log(log, index, organized=True)
                cloud.update({name: log.attributes[name][index].ravel() for name, _ in attribute_fields})
                origins = log.origins[index if len(log.origins) > 1 else 0].reshape(-1, 3)
                cloud.update({name: origins[:, axis] for axis, name in enumerate(ORIGIN_FIELDS) if with_origins})
                table = np.empty(height * width, dtype=record)
                for name in record.names:
                    table[name] = cloud[name]
                start = float(log.times[index].min())
                sec = int(np.floor(start))
                nanosec = int(round((start - sec) * 1e9)) % 1_000_000_000
                stamp = types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
                msg = types[POINTCLOUD2](
                    header=types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id),
                    height=height,
                    width=width,
                    fields=layout,
                    is_bigendian=False,
                    point_step=offset,
                    row_step=offset * width,
                    data=np.frombuffer(table.tobytes(), dtype=np.uint8),
                    is_dense=bool(log.hit[index].all()),
                )
                nanoseconds = int(round(start * 1e9))
                if index == 0:
                    mount = _tf_message(types, stamp, base_frame, frame_id, np.eye(4))
                    writer.write(tf_static, nanoseconds, store.serialize_cdr(mount, TF_MESSAGE))
                    info = types[STRING](data=dumps_exact(log.sensor))
                    writer.write(sensor_info, nanoseconds, store.serialize_cdr(info, STRING))
                pose = _tf_message(types, stamp, world_frame, base_frame, log.poses[index])
                writer.write(tf, nanoseconds, store.serialize_cdr(pose, TF_MESSAGE))
                writer.write(connection, nanoseconds, store.serialize_cdr(msg, POINTCLOUD2))
        os.replace(bag, path)
    except sqlite3.Error as exc:  # the storage could not be written (a full disk, ulimit -f): was a traceback
        raise OSError(errno.EIO, f"the bag's storage could not be written ({exc})", os.fspath(path)) from exc
    except OSError as exc:  # a failed write names the bag, not a file of the staging folder or none
        if exc.filename is not None and not str(exc.filename).startswith(str(staging)):
            raise
        raise OSError(exc.errno or errno.EIO, exc.strerror or str(exc), os.fspath(path)) from exc
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return path
