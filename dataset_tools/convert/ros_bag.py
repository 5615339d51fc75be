"""Reader of ROS 1 (.bag) and ROS 2 (sqlite3 or MCAP folder) bags into `EpisodeStreams`, via `rosbags`.

rosbags' AnyReader parses both generations with the same API, so one reader serves both; no ROS install.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dataset_tools.convert.streams import (
    CameraStream,
    ConversionError,
    EpisodeStreams,
    GripperStream,
    JointStream,
    PoseStream,
    finger_opening_closed,
)
from dataset_tools.convert.topics import TopicMap

JOINT_STATE = "sensor_msgs/msg/JointState"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"


def is_bag(path: Path) -> bool:
    path = Path(path)
    return (path.is_file() and path.suffix == ".bag") or (path.is_dir() and (path / "metadata.yaml").is_file())


def find_bags(path: Path) -> list[Path]:
    """One bag, or every bag directly inside a folder (sorted), one episode each."""
    path = Path(path)
    if is_bag(path):
        return [path]
    if path.is_dir():
        return sorted(p for p in path.iterdir() if is_bag(p))
    return []


def read_bag(path: Path, topics: TopicMap) -> EpisodeStreams:
    from rosbags.highlevel import AnyReader

    source = str(path)
    try:
        with AnyReader([Path(path)]) as reader:
            return _read(reader, source, topics)
    except ConversionError:
        raise
    except Exception as err:  # rosbags raises many kinds for truncated or corrupt files
        raise ConversionError(f"{source}: cannot read the bag, truncated or corrupt? ({type(err).__name__}: {err})") from err


def _read(reader, source: str, topics: TopicMap) -> EpisodeStreams:
    by_topic = {c.topic: c for c in reader.connections}
    start_ns = reader.start_time

    def connection(topic: str, allowed: tuple[str, ...], what: str):
        conn = by_topic.get(topic)
        if conn is None:
            raise ConversionError(
                f"{source}: {what} topic {topic!r} is not in the bag (topics: {sorted(by_topic)}); "
                f"set it with --topics.<name>=..."
            )
        if conn.msgtype not in allowed:
            raise ConversionError(f"{source}: topic {topic} has type {conn.msgtype}, expected one of {allowed}")
        return conn

    def messages(conn):
        for _, log_ns, raw in reader.messages(connections=[conn]):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as err:
                raise ConversionError(
                    f"{source}: topic {conn.topic} at t={log_ns / 1e9:.6f} s: corrupt message ({err})"
                ) from err
            stamp = getattr(getattr(msg, "header", None), "stamp", None)
            stamp_ns = stamp.sec * 10**9 + stamp.nanosec if stamp is not None and topics.use_header_stamps else 0
            yield ((stamp_ns or log_ns) - start_ns) / 1e9, msg

    joints_conn = connection(topics.joint_states, (JOINT_STATE,), "joint states")
    wanted = list(topics.joint_names) + (list(topics.gripper_joints) if topics.gripper_source == "joint" else [])
    joint_time, joint_rows = [], []
    for time_s, msg in messages(joints_conn):
        names = list(msg.name)
        missing = [n for n in wanted if n not in names]
        if missing:
            raise ConversionError(
                f"{source}: topic {topics.joint_states} at t={start_ns / 1e9 + time_s:.6f} s: joints {missing} "
                f"are not in the message (it has {names}); set --topics.joint_names / --topics.gripper_joints"
            )
        position = np.asarray(msg.position, dtype=np.float64)
        joint_time.append(time_s)
        joint_rows.append(position[[names.index(n) for n in wanted]])
    if not joint_rows:
        raise ConversionError(f"{source}: topic {topics.joint_states} has no messages")
    joint_time_s = np.asarray(joint_time)
    joint_values = np.stack(joint_rows)
    n_arm = len(topics.joint_names)
    joints = JointStream(topics.joint_states, joint_time_s, joint_values[:, :n_arm])

    if topics.gripper_source == "joint":
        finger = joint_values[:, n_arm:]
        gripper = GripperStream(topics.joint_states, joint_time_s, finger_opening_closed(finger, topics.gripper_closed_below), finger)
    elif topics.gripper_source == "topic":
        conn = connection(topics.gripper_topic, ("std_msgs/msg/Bool", "std_msgs/msg/Float64"), "gripper")
        rows = [(t, float(m.data)) for t, m in messages(conn)]
        time_s = np.array([t for t, _ in rows])
        value = np.array([v for _, v in rows])
        closed = value > 0.5 if conn.msgtype == "std_msgs/msg/Bool" else value > topics.gripper_closed_above
        gripper = GripperStream(topics.gripper_topic, time_s, closed, np.stack([value, value], axis=1))
    else:
        raise ConversionError(f"gripper_source must be 'joint' or 'topic', got {topics.gripper_source!r}")

    pose = None
    if topics.eef_pose and topics.eef_pose in by_topic:
        rows = [(t, m.pose) for t, m in messages(connection(topics.eef_pose, (POSE_STAMPED,), "end-effector pose"))]
        pose = PoseStream(
            topics.eef_pose,
            np.array([t for t, _ in rows]),
            np.array([[p.position.x, p.position.y, p.position.z] for _, p in rows]).reshape(-1, 3),
            np.array([[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w] for _, p in rows]).reshape(-1, 4),
        )

    cameras = {}
    for name, topic in topics.cameras.items():
        if topic not in by_topic and f"{topic}/compressed" in by_topic:
            topic = f"{topic}/compressed"
        conn = connection(topic, (IMAGE, COMPRESSED_IMAGE), f"camera '{name}'")
        # Keep the raw messages; decoding happens only for the frames the resampled episode uses.
        rows = list(messages(conn))
        if not rows:
            raise ConversionError(f"{source}: camera '{name}' (topic {topic}) has no frames")
        msgs = [m for _, m in rows]
        cameras[name] = CameraStream(topic, np.array([t for t, _ in rows]), _decoder(msgs, source, topic))
    return EpisodeStreams(source, joints, gripper, pose, cameras, start_time_ns=start_ns)


def _decoder(msgs: list, source: str, topic: str):
    def decode(index: int) -> np.ndarray:
        try:
            return decode_image(msgs[index])
        except Exception as err:
            raise ConversionError(f"{source}: topic {topic}: frame {index} cannot be decoded ({err})") from err

    return decode


def decode_image(msg) -> np.ndarray:
    """sensor_msgs Image (rgb8/bgr8/rgba8/bgra8/mono8) or CompressedImage (JPEG/PNG) -> uint8 HxWx3 RGB."""
    import cv2

    if hasattr(msg, "encoding"):
        data = np.asarray(msg.data, dtype=np.uint8)
        channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}.get(msg.encoding)
        if channels is None:
            raise ValueError(f"unsupported image encoding {msg.encoding!r}")
        rows = data.reshape(msg.height, msg.step)[:, : msg.width * channels]
        image = rows.reshape(msg.height, msg.width, channels)
        if msg.encoding.startswith("bgr"):
            image = image[..., 2::-1]
        elif channels == 1:
            image = np.repeat(image, 3, axis=2)
        return np.ascontiguousarray(image[..., :3])
    image = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError("cv2.imdecode failed")
    return np.ascontiguousarray(image[..., ::-1])
