"""Write a :class:`SimResult` as a rosbag2 (MCAP) directory with the topic contract.

Serialisation is vectorised: for each topic one message is serialised with rosbags' CDR
serializer, the byte offset of every numeric field is located by probing (re-serialising
with that field changed), and all messages of the topic are then filled column-wise in a
numpy byte matrix. The layout of a topic is fixed (constant frame ids, names and array
lengths), so the result is byte-identical to ``typestore.serialize_cdr`` (checked by the
tests). Log time = header stamp = T0_NS + t.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from vehicle_estimation.contract import topics as T
from vehicle_estimation.estimators.common.rotations import quat_from_euler

T0_NS = 1_700_000_000 * 1_000_000_000

_TYPESTORE = None


def typestore():
    global _TYPESTORE
    if _TYPESTORE is None:
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


# --------------------------------------------------------------------------- message builders
# Each builder takes a flat dict of numeric fields (missing -> 0) and returns a message.
def _header(ts, v, frame):
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    return Header(stamp=Time(sec=int(v.get("sec", 0)), nanosec=int(v.get("nsec", 0))), frame_id=frame)


def _arr(v, prefix, n):
    return np.array([v.get(f"{prefix}{i}", 0.0) for i in range(n)], dtype=np.float64)


def _vec3(ts, v, p):
    return ts.types["geometry_msgs/msg/Vector3"](x=v.get(p + "x", 0.0), y=v.get(p + "y", 0.0), z=v.get(p + "z", 0.0))


def _imu(ts, v, frame):
    return ts.types["sensor_msgs/msg/Imu"](
        header=_header(ts, v, frame),
        orientation=ts.types["geometry_msgs/msg/Quaternion"](x=v.get("ox", 0.0), y=v.get("oy", 0.0), z=v.get("oz", 0.0), w=v.get("ow", 0.0)),
        orientation_covariance=_arr(v, "ocov", 9),
        angular_velocity=_vec3(ts, v, "w"),
        angular_velocity_covariance=_arr(v, "wcov", 9),
        linear_acceleration=_vec3(ts, v, "a"),
        linear_acceleration_covariance=_arr(v, "acov", 9),
    )


def _navsat(ts, v, frame):
    return ts.types["sensor_msgs/msg/NavSatFix"](
        header=_header(ts, v, frame),
        status=ts.types["sensor_msgs/msg/NavSatStatus"](status=int(v.get("status", 0)), service=int(v.get("service", 0))),
        latitude=v.get("lat", 0.0), longitude=v.get("lon", 0.0), altitude=v.get("alt", 0.0),
        position_covariance=_arr(v, "pcov", 9),
        position_covariance_type=int(v.get("pcovtype", 0)),
    )


def _twist_cov_stamped(ts, v, frame):
    return ts.types["geometry_msgs/msg/TwistWithCovarianceStamped"](
        header=_header(ts, v, frame),
        twist=ts.types["geometry_msgs/msg/TwistWithCovariance"](
            twist=ts.types["geometry_msgs/msg/Twist"](linear=_vec3(ts, v, "l"), angular=_vec3(ts, v, "w")),
            covariance=_arr(v, "cov", 36)),
    )


def _joint_state(names):
    def build(ts, v, frame):
        n = len(names)
        return ts.types["sensor_msgs/msg/JointState"](
            header=_header(ts, v, frame), name=list(names),
            position=_arr(v, "pos", n), velocity=_arr(v, "vel", n), effort=_arr(v, "eff", n))
    return build


def _float64(ts, v, frame):
    return ts.types["std_msgs/msg/Float64"](data=v.get("data", 0.0))


def _odometry(child):
    def build(ts, v, frame):
        return ts.types["nav_msgs/msg/Odometry"](
            header=_header(ts, v, frame), child_frame_id=child,
            pose=ts.types["geometry_msgs/msg/PoseWithCovariance"](
                pose=ts.types["geometry_msgs/msg/Pose"](
                    position=ts.types["geometry_msgs/msg/Point"](x=v.get("px", 0.0), y=v.get("py", 0.0), z=v.get("pz", 0.0)),
                    orientation=ts.types["geometry_msgs/msg/Quaternion"](x=v.get("qx", 0.0), y=v.get("qy", 0.0), z=v.get("qz", 0.0), w=v.get("qw", 0.0))),
                covariance=_arr(v, "pcov", 36)),
            twist=ts.types["geometry_msgs/msg/TwistWithCovariance"](
                twist=ts.types["geometry_msgs/msg/Twist"](linear=_vec3(ts, v, "l"), angular=_vec3(ts, v, "w")),
                covariance=_arr(v, "tcov", 36)),
        )
    return build


_INT_FIELDS = {"sec": "<i4", "nsec": "<u4", "status": "<i1", "service": "<u2", "pcovtype": "<u1"}


class _Template:
    """Byte template + field offsets of one topic's fixed-layout message."""

    def __init__(self, msgtype: str, builder, frame: str, keys: list[str]):
        ts = typestore()
        self.msgtype = msgtype
        self.builder = builder
        self.frame = frame
        base = bytes(ts.serialize_cdr(builder(ts, {}, frame), msgtype))
        self.base = np.frombuffer(base, dtype=np.uint8).copy()
        self.fields: dict[str, tuple[int, str]] = {}
        for key in keys:
            dtype = _INT_FIELDS.get(key, "<f8")
            width = np.dtype(dtype).itemsize
            probe = {1: 0x55, 2: 0x7F7F, 4: 0x01020304}.get(width) if dtype != "<f8" else 1.2345678901234567e-7
            data = np.frombuffer(bytes(ts.serialize_cdr(builder(ts, {key: probe}, frame), msgtype)), dtype=np.uint8)
            if data.size != self.base.size:
                raise RuntimeError(f"{msgtype}: field {key} changes the message size")
            diff = np.nonzero(data != self.base)[0]
            if diff.size == 0 or diff[-1] - diff[0] + 1 > width:
                raise RuntimeError(f"{msgtype}: cannot locate field {key}")
            off = int(diff[-1] - width + 1) if diff.size < width else int(diff[0])
            # verify
            if data[off:off + width].tobytes() != np.array([probe], dtype=dtype).tobytes():
                raise RuntimeError(f"{msgtype}: offset check failed for {key}")
            self.fields[key] = (off, dtype)

    def fill(self, n: int, values: dict) -> np.ndarray:
        """Byte matrix (n, size) with the fields set (scalars broadcast)."""
        out = np.tile(self.base, (n, 1))
        for key, val in values.items():
            off, dtype = self.fields[key]
            width = np.dtype(dtype).itemsize
            col = np.broadcast_to(np.asarray(val, dtype=np.float64 if dtype == "<f8" else np.int64), (n,))
            out[:, off:off + width] = np.ascontiguousarray(col.astype(dtype)).view(np.uint8).reshape(n, width)
        return out

    def serialize_one(self, values: dict) -> bytes:
        ts = typestore()
        return bytes(ts.serialize_cdr(self.builder(ts, values, self.frame), self.msgtype))


def _keys(prefix, n):
    return [f"{prefix}{i}" for i in range(n)]


def _templates() -> dict:
    stamp = ["sec", "nsec"]
    js_names = tuple(T.WHEEL_JOINTS) + (T.STEERING_JOINT,)
    pt_names = (T.ENGINE_JOINT, T.ENGINE_LOAD_JOINT, T.GEAR_JOINT, T.DRIVE_JOINT)
    return {
        "imu": _Template("sensor_msgs/msg/Imu", _imu, T.IMU_FRAME,
                         stamp + ["ox", "oy", "oz", "ow"] + _keys("ocov", 9) + ["wx", "wy", "wz"] + _keys("wcov", 9)
                         + ["ax", "ay", "az"] + _keys("acov", 9)),
        "gnss": _Template("sensor_msgs/msg/NavSatFix", _navsat, T.GNSS_FRAME,
                          stamp + ["status", "service", "lat", "lon", "alt", "pcovtype"] + _keys("pcov", 9)),
        "twist": _Template("geometry_msgs/msg/TwistWithCovarianceStamped", _twist_cov_stamped, T.BASE_FRAME,
                           stamp + ["lx", "ly", "lz", "wx", "wy", "wz"] + _keys("cov", 36)),
        "joints": _Template("sensor_msgs/msg/JointState", _joint_state(js_names), "",
                            stamp + _keys("pos", 5) + _keys("vel", 5) + _keys("eff", 5)),
        "powertrain": _Template("sensor_msgs/msg/JointState", _joint_state(pt_names), "",
                                stamp + _keys("pos", 4) + _keys("vel", 4) + _keys("eff", 4)),
        "float64": _Template("std_msgs/msg/Float64", _float64, "", ["data"]),
        "odom": _Template("nav_msgs/msg/Odometry", _odometry(T.BASE_FRAME), T.ODOM_FRAME,
                          stamp + ["px", "py", "pz", "qx", "qy", "qz", "qw"] + _keys("pcov", 36)
                          + ["lx", "ly", "lz", "wx", "wy", "wz"] + _keys("tcov", 36)),
    }


def _stamps(t: np.ndarray, t0_ns: int):
    ns = t0_ns + np.round(np.asarray(t) * 1e9).astype(np.int64)
    return ns, ns // 1_000_000_000, ns % 1_000_000_000


def build_streams(result, t0_ns: int = T0_NS) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """(topic, msgtype, log times ns, byte matrix) for every topic of the contract; stamps are
    ``t0_ns`` plus the simulation time (0: a bag starting at 0 s, as other simulators write)."""
    tpl = _templates()
    S, TR = result.sensors, result.truth
    streams = []
    nan = float("nan")

    imu = S["imu"]
    ns, sec, nsec = _stamps(imu["t"], t0_ns)
    vals = {"sec": sec, "nsec": nsec, "ocov0": -1.0,
            "wx": imu["gyro"][:, 0], "wy": imu["gyro"][:, 1], "wz": imu["gyro"][:, 2],
            "ax": imu["accel"][:, 0], "ay": imu["accel"][:, 1], "az": imu["accel"][:, 2],
            "wcov0": imu["gyro_cov"][0], "wcov4": imu["gyro_cov"][1], "wcov8": imu["gyro_cov"][2],
            "acov0": imu["accel_cov"][0], "acov4": imu["accel_cov"][1], "acov8": imu["accel_cov"][2]}
    streams.append((T.IMU, tpl["imu"].msgtype, ns, tpl["imu"].fill(ns.size, vals)))

    gn = S["gnss"]
    ns, sec, nsec = _stamps(gn["t"], t0_ns)
    cov = gn["cov"]
    vals = {"sec": sec, "nsec": nsec, "status": gn["status"].astype(np.int64), "service": 1,
            "lat": gn["lat"], "lon": gn["lon"], "alt": gn["alt"], "pcovtype": 2,
            "pcov0": cov[0], "pcov4": cov[1], "pcov8": cov[2]}
    streams.append((T.GNSS, tpl["gnss"].msgtype, ns, tpl["gnss"].fill(ns.size, vals)))

    sp = S["speed"]
    ns, sec, nsec = _stamps(sp["t"], t0_ns)
    vals = {"sec": sec, "nsec": nsec, "lx": sp["v"], "cov0": sp["var"]}
    streams.append((T.SPEED, tpl["twist"].msgtype, ns, tpl["twist"].fill(ns.size, vals)))

    js = S["joint_states"]
    ns, sec, nsec = _stamps(js["t"], t0_ns)
    vals = {"sec": sec, "nsec": nsec}
    for i in range(5):
        vals[f"pos{i}"] = js["position"][:, i]
        vals[f"vel{i}"] = js["velocity"][:, i]
        vals[f"eff{i}"] = js["effort"][:, i]
    streams.append((T.JOINT_STATES, tpl["joints"].msgtype, ns, tpl["joints"].fill(ns.size, vals)))

    pt = S["powertrain"]
    ns, sec, nsec = _stamps(pt["t"], t0_ns)
    vals = {"sec": sec, "nsec": nsec}
    for i in range(4):
        vals[f"pos{i}"] = nan
        vals[f"vel{i}"] = nan
        vals[f"eff{i}"] = nan
    vals.update({"vel0": pt["engine_speed"], "eff0": pt["engine_torque"], "pos1": pt["load"],
                 "pos2": pt["gear"], "eff3": pt["drive_force"]})
    streams.append((T.POWERTRAIN, tpl["powertrain"].msgtype, ns, tpl["powertrain"].fill(ns.size, vals)))

    # ground truth (100 Hz)
    ns, sec, nsec = _stamps(TR["t"], t0_ns)
    n = ns.size
    f64 = tpl["float64"]
    streams.append((T.GT_MASS, f64.msgtype, ns, f64.fill(n, {"data": TR["mass"]})))
    streams.append((T.GT_ROAD_SLOPE, f64.msgtype, ns, f64.fill(n, {"data": TR["slope"]})))
    streams.append((T.GT_SIDESLIP, f64.msgtype, ns, f64.fill(n, {"data": TR["sideslip"]})))
    vals = {"sec": sec, "nsec": nsec, "lx": TR["vx"], "ly": TR["vy"], "wz": TR["yaw_rate"]}
    streams.append((T.GT_VEHICLE_STATE, tpl["twist"].msgtype, ns, tpl["twist"].fill(n, vals)))
    qx, qy, qz, qw = np.moveaxis(quat_from_euler(TR["roll"], TR["pitch"], TR["yaw"]), -1, 0)
    vals = {"sec": sec, "nsec": nsec, "px": TR["x"], "py": TR["y"], "pz": TR["z"],
            "qx": qx, "qy": qy, "qz": qz, "qw": qw,
            "lx": TR["vx"], "ly": TR["vy"], "wx": TR["wx"], "wy": TR["wy"], "wz": TR["wz"]}
    streams.append((T.GT_ODOMETRY, tpl["odom"].msgtype, ns, tpl["odom"].fill(n, vals)))
    streams += _truth_frames(tpl, S, ns[:1], t0_ns)
    return streams


def _truth_frames(tpl, S, first_ns: np.ndarray, t0_ns: int) -> list:
    """``ground_truth/datum`` (the WGS84 point of the truth's odometry origin, once, at the first
    truth stamp) where the GNSS fixes say about which origin they were made, and
    ``ground_truth/imu_bias`` (the IMU's biases in its own axes, as ``estimation/imu_bias``,
    at 10 Hz of the IMU's stamps) where the IMU says which biases it carries."""
    streams = []
    origin = S["gnss"].get("origin")
    if origin is not None:
        sec, nsec = first_ns // 1_000_000_000, first_ns % 1_000_000_000
        vals = {"sec": sec, "nsec": nsec, "status": 0, "service": 1,
                "lat": origin[0], "lon": origin[1], "alt": origin[2], "pcovtype": 0}
        streams.append((T.GT_DATUM, tpl["gnss"].msgtype, first_ns, tpl["gnss"].fill(1, vals)))
    imu = S["imu"]
    accel_bias = imu.get("accel_bias", imu.get("bias_accel"))
    gyro_bias = imu.get("gyro_bias", imu.get("bias_gyro"))
    if accel_bias is not None and gyro_bias is not None:
        t = np.asarray(imu["t"])
        step = max(1, int(round(0.1 / float(np.median(np.diff(t)))))) if t.size > 1 else 1
        k = np.arange(0, t.size, step)
        ba = np.broadcast_to(np.asarray(accel_bias, dtype=float), (t.size, 3))[k]
        bg = np.broadcast_to(np.asarray(gyro_bias, dtype=float), (t.size, 3))[k]
        ns, sec, nsec = _stamps(t[k], t0_ns)
        vals = {"sec": sec, "nsec": nsec, "ocov0": -1.0,
                "wx": bg[:, 0], "wy": bg[:, 1], "wz": bg[:, 2], "ax": ba[:, 0], "ay": ba[:, 1], "az": ba[:, 2]}
        streams.append((T.GT_IMU_BIAS, tpl["imu"].msgtype, ns, tpl["imu"].fill(ns.size, vals)))
    return streams


def check_new_bag_path(path) -> Path:
    """A path a new rosbag2 directory can be written to: it must not exist, and must not end in
    ``.bag``: rosbags (and ``ros2 bag``) read such a path as a ROS 1 bag file, so the bag could
    not be opened again. Raises ``FileExistsError`` / ``ValueError`` saying which."""
    path = Path(path)
    if path.suffix == ".bag":
        raise ValueError(f"{path}: a rosbag2 directory must not end in '.bag' (it would be read as a "
                         f"ROS 1 bag file); name it e.g. {path.with_suffix('')}")
    if path.exists():
        raise FileExistsError(f"{path} exists")
    return path


def write_bag(result, path) -> Path:
    """Write every topic of a simulation in global stamp order to a new MCAP rosbag2 directory."""
    check_new_bag_path(path)         # before the streams are built: that is the slow part
    return write_streams(build_streams(result), path)


def write_streams(streams, path) -> Path:
    """Write ``(topic, msgtype, stamps_ns, serialized rows)`` streams in global stamp order (log
    time = header stamp) to a new MCAP rosbag2 directory ``path``."""
    path = check_new_bag_path(path)
    ts = typestore()
    # global order: by stamp, ties by topic order (stable sort)
    stamps = np.concatenate([s[2] for s in streams])
    which = np.concatenate([np.full(s[2].size, i, dtype=np.int32) for i, s in enumerate(streams)])
    row = np.concatenate([np.arange(s[2].size, dtype=np.int64) for s in streams])
    order = np.lexsort((which, stamps))
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = [writer.add_connection(topic, msgtype, typestore=ts) for topic, msgtype, _, _ in streams]
        mats = [s[3] for s in streams]
        write = writer.write
        for i in order.tolist():
            w = which[i]
            write(conns[w], int(stamps[i]), mats[w][row[i]].tobytes())
    return path
