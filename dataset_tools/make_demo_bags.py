"""`bcrl-make-demo-bags`: drive the simulated Sawyer through a reach-and-grasp demo and write it as ROS bags.

Writes what a real Sawyer rig records (joint states ~100 Hz, a camera ~30 Hz with jitter and dropped
frames, an optional end-effector pose topic) as a ROS 1 bag and a ROS 2 bag (MCAP), plus the ground truth
(the MuJoCo grip-site pose at every physics step) in an .npz kept aside, so converters can be checked.
Example: bcrl-make-demo-bags --out_dir=data/demo_bags --n_episodes=2
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import mujoco
import numpy as np
from tqdm import tqdm

from lerobot_bcrl.envs import controller
from lerobot_bcrl.robot.mujoco_sawyer import MujocoSawyer
from lerobot_bcrl.robot.kinematics import SAWYER_ARM_JOINTS

BAG_START_NS = 1_700_000_000 * 10**9  # an epoch time, as on a real rig
URDF_FINGER_JOINTS = ("right_gripper_l_finger_joint", "right_gripper_r_finger_joint")
EXTRA_JOINTS = ("head_pan",)  # Intera's joint_states carries the head too; converters must pick by name


@dataclass
class DemoTopics:
    joint_states: str = "/robot/joint_states"
    eef_pose: str = "/robot/limb/right/endpoint_pose"
    camera: str = "/camera/color/image_raw"  # ROS 2 bags get `<camera>/compressed` (JPEG)
    gripper_command: str = "/bcrl/gripper_command"  # std_msgs/Float64: the operator's command, +1 closed


@dataclass
class MakeDemoBagsConfig:
    out_dir: Path = Path("demo_bags")
    n_episodes: int = 1
    seed: int = 0
    formats: list[str] = field(default_factory=lambda: ["ros1", "ros2"])  # ros2 is written as MCAP
    control_steps: int = 60  # scripted expert steps at 20 Hz (approach, descend, close, lift)
    joint_rate_hz: float = 100.0
    camera_rate_hz: float = 30.0
    timing_jitter_s: float = 0.002  # std of each sample's time around its nominal tick
    camera_drop_prob: float = 0.05  # fraction of camera frames that never arrive
    image_size: int = 64
    publish_eef_pose: bool = True
    topics: DemoTopics = field(default_factory=DemoTopics)


@dataclass
class SimulatedDemo:
    """Physics-rate record of one demo (2 ms steps) plus the camera frames rendered at their ticks."""

    time_s: np.ndarray  # (N,)
    joint_pos_rad: np.ndarray  # (N, 7)
    finger_pos_m: np.ndarray  # (N, 2)
    gripper_command: np.ndarray  # (N,) +1 closed / -1 open, what the expert commanded
    eef_pos_base_m: np.ndarray  # (N, 3) ground truth: the grip site in the robot base frame
    eef_quat_base_xyzw: np.ndarray  # (N, 4)
    camera_time_s: np.ndarray  # (M,)
    camera_frames: np.ndarray  # (M, H, W, 3) uint8


def simulate_demo(cfg: MakeDemoBagsConfig, seed: int) -> SimulatedDemo:
    """Roll out the scripted Lift expert, recording the arm at every physics step and the camera at its ticks."""
    from dataset_tools.experts import ScriptedLiftExpert
    from lerobot_bcrl.envs.lift import LiftEnv
    from lerobot_bcrl.envs.rendering import CameraRenderer
    from lerobot_bcrl.features import CAMERA_NAME

    rng = np.random.default_rng([seed, 1])
    env = LiftEnv(obs_type="agent_pos", sim_step="robosuite")  # robosuite's step calls sim.step2, hooked below
    sim = env.sim_env.sim
    model, data = sim.model._model, sim.data._data
    sawyer = MujocoSawyer(model)
    renderer = CameraRenderer(model, CAMERA_NAME, cfg.image_size, cfg.image_size)
    camera_ticks = _jittered_ticks(cfg.control_steps / 20.0 + 1.0, cfg.camera_rate_hz, cfg.timing_jitter_s, rng)
    camera_ticks = camera_ticks[rng.random(len(camera_ticks)) >= cfg.camera_drop_prob]
    rows: dict[str, list] = {"t": [], "q": [], "f": [], "g": []}
    frames: list[tuple[float, np.ndarray]] = []
    gripper_now = [-1.0]
    original_step2 = sim.step2

    def recording_step2():
        original_step2()
        rows["t"].append(data.time)
        rows["q"].append(sawyer.joint_pos_rad(data))
        rows["f"].append(sawyer.finger_pos_m(data))
        rows["g"].append(gripper_now[0])
        while len(frames) < len(camera_ticks) and data.time >= camera_ticks[len(frames)]:
            frames.append((float(camera_ticks[len(frames)]), renderer.render(data).copy()))

    try:
        observation, _ = env.reset(seed=seed)
        start_time_s = data.time
        camera_ticks += start_time_s
        sim.step2 = recording_step2
        expert = ScriptedLiftExpert()
        expert.reset()
        for _ in range(cfg.control_steps):
            action, _ = controller.controller_to_delta_action(expert.act(observation))
            gripper_now[0] = float(action[7])
            observation, *_ = env.step(action)
    finally:
        sim.step2 = original_step2
        renderer.close()
        env.close()
    time_s = np.asarray(rows["t"]) - start_time_s
    joint_pos = np.stack(rows["q"])
    eef_pos, eef_quat = _ground_truth_poses(model, sawyer, joint_pos)
    return SimulatedDemo(
        time_s=time_s,
        joint_pos_rad=joint_pos,
        finger_pos_m=np.stack(rows["f"]),
        gripper_command=np.asarray(rows["g"]),
        eef_pos_base_m=eef_pos,
        eef_quat_base_xyzw=eef_quat,
        camera_time_s=np.array([t for t, _ in frames]) - start_time_s,
        camera_frames=np.stack([f for _, f in frames]),
    )


def _ground_truth_poses(model: mujoco.MjModel, sawyer: MujocoSawyer, joint_pos_rad: np.ndarray):
    data = mujoco.MjData(model)
    positions, quats = [], []
    for q in joint_pos_rad:
        data.qpos[sawyer.arm_qpos_adr] = q
        mujoco.mj_kinematics(model, data)
        pos, quat = sawyer.grip_site_pose_base(data)
        positions.append(pos)
        quats.append(quat)
    return np.stack(positions), np.stack(quats)


def _jittered_ticks(duration_s: float, rate_hz: float, jitter_s: float, rng: np.random.Generator) -> np.ndarray:
    nominal = np.arange(0.0, duration_s, 1.0 / rate_hz)
    jitter = np.clip(rng.normal(0.0, jitter_s, len(nominal)), -0.4 / rate_hz, 0.4 / rate_hz)
    return np.maximum(nominal + jitter, 0.0)


def joint_sample_indices(demo: SimulatedDemo, cfg: MakeDemoBagsConfig, rng: np.random.Generator) -> np.ndarray:
    """Physics steps at which the joint-state publisher sampled the arm (jittered ~joint_rate_hz)."""
    ticks = _jittered_ticks(demo.time_s[-1], cfg.joint_rate_hz, cfg.timing_jitter_s, rng)
    indices = np.searchsorted(demo.time_s, ticks).clip(0, len(demo.time_s) - 1)
    return np.unique(indices)


# -- writing -------------------------------------------------------------------------------------------
class _MessageFactory:
    """Builds the messages of one bag with its typestore (ROS 1 headers have a `seq`, ROS 2 ones do not)."""

    def __init__(self, ros1: bool):
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = ros1
        self.typestore = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        self.types = self.typestore.types
        self._seq = 0

    def serialize(self, msg) -> bytes:
        if self.ros1:
            return self.typestore.serialize_ros1(msg, msg.__msgtype__)
        return self.typestore.serialize_cdr(msg, msg.__msgtype__)

    def header(self, stamp_ns: int, frame_id: str = "base"):
        stamp = self.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        self._seq += 1
        if self.ros1:
            return self.types["std_msgs/msg/Header"](seq=self._seq, stamp=stamp, frame_id=frame_id)
        return self.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def joint_state(self, stamp_ns: int, joint_pos_rad: np.ndarray, finger_pos_m: np.ndarray):
        names = [*EXTRA_JOINTS, *SAWYER_ARM_JOINTS, *URDF_FINGER_JOINTS]
        position = np.concatenate([[0.0], joint_pos_rad, finger_pos_m])
        zeros = np.zeros_like(position)
        return self.types["sensor_msgs/msg/JointState"](
            header=self.header(stamp_ns), name=names, position=position, velocity=zeros, effort=zeros
        )

    def pose(self, stamp_ns: int, pos_m: np.ndarray, quat_xyzw: np.ndarray):
        t = self.types
        point = t["geometry_msgs/msg/Point"](x=float(pos_m[0]), y=float(pos_m[1]), z=float(pos_m[2]))
        quat = t["geometry_msgs/msg/Quaternion"](*[float(v) for v in quat_xyzw])
        return t["geometry_msgs/msg/PoseStamped"](
            header=self.header(stamp_ns), pose=t["geometry_msgs/msg/Pose"](position=point, orientation=quat)
        )

    def image(self, stamp_ns: int, frame_rgb: np.ndarray):
        height, width, _ = frame_rgb.shape
        return self.types["sensor_msgs/msg/Image"](
            header=self.header(stamp_ns, "camera"), height=height, width=width, encoding="rgb8",
            is_bigendian=0, step=width * 3, data=np.ascontiguousarray(frame_rgb).reshape(-1),
        )  # fmt: skip

    def compressed_image(self, stamp_ns: int, frame_rgb: np.ndarray):
        import cv2

        ok, jpeg = cv2.imencode(".jpg", frame_rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        assert ok
        return self.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp_ns, "camera"), format="rgb8; jpeg compressed bgr8", data=jpeg.reshape(-1)
        )

    def float64(self, value: float):
        return self.types["std_msgs/msg/Float64"](data=float(value))


def bag_messages(demo: SimulatedDemo, cfg: MakeDemoBagsConfig, factory: _MessageFactory, seed: int):
    """(topic, msgtype, log_time_ns, message) in log-time order; header stamps are the sample times."""
    rng = np.random.default_rng([seed, 2])
    topics = cfg.topics
    messages = []

    def stamp_ns(time_s: float) -> int:
        return BAG_START_NS + int(round(time_s * 1e9))

    def latency_ns() -> int:  # transport delay between sampling and logging
        return int(rng.uniform(0.5e-3, 4e-3) * 1e9)

    for i in joint_sample_indices(demo, cfg, rng):
        t_ns = stamp_ns(demo.time_s[i])
        messages.append((topics.joint_states, factory.joint_state(t_ns, demo.joint_pos_rad[i], demo.finger_pos_m[i]), t_ns + latency_ns()))
        messages.append((topics.gripper_command, factory.float64(demo.gripper_command[i]), t_ns + latency_ns()))
        if cfg.publish_eef_pose:
            pose = factory.pose(t_ns, demo.eef_pos_base_m[i], demo.eef_quat_base_xyzw[i])
            messages.append((topics.eef_pose, pose, t_ns + latency_ns()))
    camera_topic = topics.camera if factory.ros1 else f"{topics.camera}/compressed"
    for time_s, frame in zip(demo.camera_time_s, demo.camera_frames, strict=True):
        t_ns = stamp_ns(time_s)
        msg = factory.image(t_ns, frame) if factory.ros1 else factory.compressed_image(t_ns, frame)
        messages.append((camera_topic, msg, t_ns + int(rng.uniform(5e-3, 15e-3) * 1e9)))
    # One publisher's messages arrive in order (TCPROS/DDS keep order per connection): log times per
    # topic never go backwards, even when latency jitters more than the sample period.
    last_log_ns: dict[str, int] = {}
    for k, (topic, msg, log_ns) in enumerate(messages):
        log_ns = max(log_ns, last_log_ns.get(topic, 0) + 1)
        last_log_ns[topic] = log_ns
        messages[k] = (topic, msg, log_ns)
    messages.sort(key=lambda m: m[2])
    return messages


def write_bag(path: Path, demo: SimulatedDemo, cfg: MakeDemoBagsConfig, ros1: bool, seed: int) -> Path:
    factory = _MessageFactory(ros1)
    return write_messages(path, bag_messages(demo, cfg, factory, seed), factory)


def write_messages(path: Path, messages, factory: _MessageFactory, empty_topics: dict[str, str] | None = None) -> Path:
    """Write (topic, message, log_time_ns) in order; `empty_topics` (topic -> msgtype) get a connection only."""
    if factory.ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    connections = {}
    with writer:
        for topic, msgtype in (empty_topics or {}).items():
            connections[topic] = writer.add_connection(topic, msgtype, typestore=factory.typestore)
        for topic, msg, log_ns in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=factory.typestore)
            writer.write(connections[topic], log_ns, factory.serialize(msg))
    return path


def save_ground_truth(path: Path, demo: SimulatedDemo) -> None:
    closed = np.flatnonzero(demo.gripper_command > 0)
    np.savez(
        path,
        time_s=demo.time_s,
        bag_start_ns=BAG_START_NS,
        eef_pos_base_m=demo.eef_pos_base_m,
        eef_quat_base_xyzw=demo.eef_quat_base_xyzw,
        joint_pos_rad=demo.joint_pos_rad,
        gripper_command=demo.gripper_command,
        first_close_time_s=demo.time_s[closed[0]] if closed.size else np.nan,
    )


def make_demo_bags(cfg: MakeDemoBagsConfig) -> dict[str, list[Path]]:
    """Write `n_episodes` demos; returns the paths written per format (and 'ground_truth')."""
    unknown = set(cfg.formats) - {"ros1", "ros2"}
    if unknown:
        raise ValueError(f"unknown formats {sorted(unknown)}; choose from ros1, ros2")
    out_dir = Path(cfg.out_dir)
    written: dict[str, list[Path]] = {name: [] for name in [*cfg.formats, "ground_truth"]}
    for name in written:
        (out_dir / name).mkdir(parents=True, exist_ok=True)
    for episode in tqdm(range(cfg.n_episodes), desc="simulating demos", unit="ep"):
        seed = cfg.seed + episode
        demo = simulate_demo(cfg, seed)
        stem = f"episode_{episode:03d}"
        if "ros1" in cfg.formats:
            written["ros1"].append(write_bag(out_dir / "ros1" / f"{stem}.bag", demo, cfg, ros1=True, seed=seed))
        if "ros2" in cfg.formats:
            written["ros2"].append(write_bag(out_dir / "ros2" / stem, demo, cfg, ros1=False, seed=seed))
        gt_path = out_dir / "ground_truth" / f"{stem}.npz"
        save_ground_truth(gt_path, demo)
        written["ground_truth"].append(gt_path)
    return written


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(MakeDemoBagsConfig)
    written = make_demo_bags(cfg)
    for name, paths in written.items():
        print(f"{name:>12}: {len(paths)} -> {Path(cfg.out_dir) / name}")


if __name__ == "__main__":
    main()
