"""`bcrl-make-demo-bags`: drive the simulated Sawyer through a reach-and-grasp demo and write it as ROS bags.

The demonstrator drives the arm through robosuite's controller (`--drive=osc`) or, as in a lab, through the real
robot's command path to the arm under physics (`--drive=command_path`, configs/record_lab_bags.yaml).

Writes what a real Sawyer rig records (joint states ~100 Hz, a camera ~30 Hz with jitter and dropped
frames, an optional end-effector pose topic) as a ROS 1 bag and a ROS 2 bag (MCAP), plus the ground truth
(the MuJoCo grip-site pose at every physics step) in an .npz kept aside, so converters can be checked.
Example: bcrl-make-demo-bags --out_dir=data/demo_bags --n_episodes=2
"""

import json
import logging
import os
import shutil
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import draccus
import mujoco
import numpy as np
from tqdm import tqdm

from dataset_tools.experts import ScriptedLiftExpert
from dataset_tools.noise import DemonstratorConfig, DemonstratorNoise
from lerobot_bcrl import geometry
from lerobot_bcrl.envs import controller
from lerobot_bcrl.files import write_json_atomically
from lerobot_bcrl.robot.mujoco_sawyer import MujocoSawyer
from lerobot_bcrl.robot.kinematics import SAWYER_ARM_JOINTS, KinematicsError

BAG_START_NS = 1_700_000_000 * 10**9  # an epoch time, as on a real rig
URDF_FINGER_JOINTS = ("right_gripper_l_finger_joint", "right_gripper_r_finger_joint")
SETTINGS_FILE = "recording_config.json"  # the settings the folder's episodes were recorded with
OUTCOMES_FILE = "outcomes.json"
CLOSE_TIME_S = 0.4  # the demonstrator holds "close" this long before lifting (8 steps at 20 Hz)
EXTRA_JOINTS = ("head_pan",)  # Intera's joint_states carries the head too; converters must pick by name


@dataclass
class DemoTopics:
    joint_states: str = "/robot/joint_states"
    eef_pose: str = "/robot/limb/right/endpoint_pose"
    camera: str = "/camera/color/image_raw"  # ROS 2 bags get `<camera>/compressed` (JPEG)
    gripper_command: str = "/bcrl/gripper_command"  # std_msgs/Float64: the operator's command, +1 closed


DRIVES = ("osc", "command_path")


class RecordingSettingsError(ValueError):
    """Settings that cannot record (a one-line message for the CLI)."""


@dataclass
class MakeDemoBagsConfig:
    out_dir: Path = Path("demo_bags")
    n_episodes: int = 1
    seed: int = 0
    formats: list[str] = field(default_factory=lambda: ["ros1", "ros2"])  # ros2 is written as MCAP
    # "osc": the scripted expert through robosuite's controller at 20 Hz. "command_path": a lab's recording: the
    # operator's deltas go through the real robot's command path (IK -> joint velocities at command_fps) to the
    # arm under physics in joint-velocity mode, so what the arm does is not what was commanded.
    drive: str = "osc"
    command_fps: float = 30.0  # drive=command_path: the teleoperation rate
    urdf: Path | None = None  # drive=command_path: the arm's URDF, for the command path's IK
    control_steps: int = 60  # the demonstrator's steps (approach, descend, close, lift): 20 Hz or command_fps
    # The demonstrator's skill and noise (controller units, as in bcrl-record); the default is the plain expert.
    operator: DemonstratorConfig = field(default_factory=DemonstratorConfig)
    joint_rate_hz: float = 100.0
    camera_rate_hz: float = 30.0
    timing_jitter_s: float = 0.002  # std of each sample's time around its nominal tick
    camera_drop_prob: float = 0.05  # fraction of camera frames that never arrive
    image_size: int = 64
    publish_eef_pose: bool = True
    topics: DemoTopics = field(default_factory=DemoTopics)

    def check(self) -> None:
        """Raise RecordingSettingsError for settings that cannot record (a one-line message for the CLI)."""
        unknown = set(self.formats) - {"ros1", "ros2"}
        if unknown:
            raise RecordingSettingsError(f"unknown formats {sorted(unknown)}; choose from ros1, ros2 (or none: --formats=[])")
        if self.drive not in DRIVES:
            raise RecordingSettingsError(f"drive must be one of {DRIVES}, got {self.drive!r}")
        if self.drive == "command_path" and self.urdf is None:
            raise RecordingSettingsError("drive=command_path needs --urdf (the arm's URDF, for the command path's IK)")

    @property
    def control_fps(self) -> float:
        return self.command_fps if self.drive == "command_path" else 20.0


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
    command_time_s: np.ndarray  # (K,) when each control period began
    command_delta_action: np.ndarray  # (K, 8) what the demonstrator commanded for it (not what the arm did)
    # drive=command_path: the rig's scores at the end (reached, grasped, lifted, closest_approach_m), as bcrl-eval-rig's
    outcome: dict[str, float] = field(default_factory=dict)


class PhysicsRecorder:
    """What the rig's sensors saw: the arm after every physics step, the camera at its (jittered, dropped) ticks."""

    def __init__(self, model, data, renderer, camera_ticks_s: np.ndarray):
        self.model, self.data, self.renderer = model, data, renderer
        self.sawyer = MujocoSawyer(model)
        self.start_time_s = float(data.time)
        self.camera_ticks_s = camera_ticks_s + self.start_time_s
        self.gripper_command = geometry.GRIPPER_OPEN
        self.rows: dict[str, list] = {"t": [], "q": [], "f": [], "g": []}
        self.frames: list[tuple[float, np.ndarray]] = []
        self.commands: list[tuple[float, np.ndarray]] = []

    def command(self, delta_action: np.ndarray) -> None:
        """The driver's action for the control period starting now."""
        self.commands.append((float(self.data.time), np.asarray(delta_action, dtype=np.float64)))
        self.gripper_command = float(delta_action[7])

    def after_physics_step(self) -> None:
        data = self.data
        self.rows["t"].append(data.time)
        self.rows["q"].append(self.sawyer.joint_pos_rad(data))
        self.rows["f"].append(self.sawyer.finger_pos_m(data))
        self.rows["g"].append(self.gripper_command)
        ticks = self.camera_ticks_s
        while len(self.frames) < len(ticks) and data.time >= ticks[len(self.frames)]:
            self.frames.append((float(ticks[len(self.frames)]), self.renderer.render(data).copy()))

    def demo(self, outcome: dict[str, float] | None = None) -> SimulatedDemo:
        joint_pos = np.stack(self.rows["q"])
        eef_pos, eef_quat = _ground_truth_poses(self.model, self.sawyer, joint_pos)
        return SimulatedDemo(
            time_s=np.asarray(self.rows["t"]) - self.start_time_s,
            joint_pos_rad=joint_pos,
            finger_pos_m=np.stack(self.rows["f"]),
            gripper_command=np.asarray(self.rows["g"]),
            eef_pos_base_m=eef_pos,
            eef_quat_base_xyzw=eef_quat,
            camera_time_s=np.array([t for t, _ in self.frames]) - self.start_time_s,
            camera_frames=np.stack([f for _, f in self.frames]),
            command_time_s=np.array([t for t, _ in self.commands]) - self.start_time_s,
            command_delta_action=np.stack([a for _, a in self.commands]),
            outcome=outcome or {},
        )


def simulate_demo(cfg: MakeDemoBagsConfig, seed: int) -> SimulatedDemo:
    """Roll out the demonstrator (per `cfg.drive`), recording the arm at every physics step and the camera at its ticks."""
    rng = np.random.default_rng([seed, 1])
    camera_ticks = _jittered_ticks(cfg.control_steps / cfg.control_fps + 1.0, cfg.camera_rate_hz, cfg.timing_jitter_s, rng)
    camera_ticks = camera_ticks[rng.random(len(camera_ticks)) >= cfg.camera_drop_prob]
    expert = ScriptedLiftExpert(close_steps=int(round(CLOSE_TIME_S * cfg.control_fps)))
    expert.reset(skill=cfg.operator, rng=np.random.default_rng([seed, 3]))
    noise = DemonstratorNoise(cfg.operator, controller.CONTROLLER_ACTION_DIM, [seed, 4])

    def operator_action(observation: dict) -> np.ndarray:
        action, _ = controller.controller_to_delta_action(np.clip(expert.act(observation) + noise.sample(), -1, 1))
        return action

    if cfg.drive == "command_path":
        return _simulate_through_command_path(cfg, seed, camera_ticks, operator_action)
    return _simulate_through_osc(cfg, seed, camera_ticks, operator_action)


def _simulate_through_osc(cfg: MakeDemoBagsConfig, seed: int, camera_ticks: np.ndarray, operator_action) -> SimulatedDemo:
    from lerobot_bcrl.envs.lift import LiftEnv
    from lerobot_bcrl.envs.rendering import CameraRenderer
    from lerobot_bcrl.features import CAMERA_NAME

    env = LiftEnv(obs_type="agent_pos", sim_step="robosuite")  # robosuite's step calls sim.step2, hooked below
    sim = env.sim_env.sim
    model, data = sim.model._model, sim.data._data
    renderer = CameraRenderer(model, CAMERA_NAME, cfg.image_size, cfg.image_size)
    original_step2 = sim.step2
    try:
        observation, _ = env.reset(seed=seed)
        recorder = PhysicsRecorder(model, data, renderer, camera_ticks)

        def recording_step2():
            original_step2()
            recorder.after_physics_step()

        sim.step2 = recording_step2
        for _ in range(cfg.control_steps):
            action = operator_action(observation)
            recorder.command(action)
            observation, *_ = env.step(action)
    finally:
        sim.step2 = original_step2
        renderer.close()
        env.close()
    return recorder.demo()


def _simulate_through_command_path(
    cfg: MakeDemoBagsConfig, seed: int, camera_ticks: np.ndarray, operator_action
) -> SimulatedDemo:
    from lerobot_bcrl.robot.command import CommandConfig, DeltaActionCommander
    from lerobot_bcrl.robot.sim_rig import SimulatedLiftRig, sawyer_kinematics
    from lerobot_bcrl.robot.transport import GuardedCommandPath

    commander = DeltaActionCommander(sawyer_kinematics(cfg.urdf), CommandConfig(fps=cfg.command_fps))
    rig = SimulatedLiftRig(image_size=cfg.image_size)
    try:
        rig.reset(seed)
        recorder = PhysicsRecorder(rig.model, rig.data, rig.camera, camera_ticks)
        rig.transport.on_physics_step = recorder.after_physics_step
        path = GuardedCommandPath(commander, rig.transport, clock=lambda: rig.transport.time_s)
        for _ in range(cfg.control_steps):
            observed_at_s = rig.transport.time_s
            action = operator_action(rig.privileged_observation())
            recorder.command(action)
            command = path.step(action, observed_at_s)
            if command.stopped_because is not None:
                raise RuntimeError(f"seed {seed}: the command path stopped the arm: {command.stopped_because}")
            rig.update_scores()
        outcome = {"reached": rig.reached, "grasped": rig.grasped, "lifted": rig.lifted,
                   "closest_approach_m": rig.closest_approach_m}  # fmt: skip
    finally:
        commander.kinematics.close()
        rig.close()
    return recorder.demo(outcome)


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
        command_time_s=demo.command_time_s,
        command_delta_action=demo.command_delta_action,
        first_close_time_s=demo.time_s[closed[0]] if closed.size else np.nan,
        **{f"outcome_{name}": value for name, value in demo.outcome.items()},
    )


def commanded_and_done_m(truth) -> tuple[np.ndarray, np.ndarray]:
    """Per control period of a recording's ground truth (.npz): the commanded position delta and what the grip site
    did over that period (its track interpolated at the periods' starts), both (K - 1, 3) in metres, base frame."""
    starts = truth["command_time_s"]
    track = np.stack([np.interp(starts, truth["time_s"], truth["eef_pos_base_m"][:, i]) for i in range(3)], axis=1)
    return truth["command_delta_action"][:-1, :3], np.diff(track, axis=0)


def outcome_summary(ground_truth_paths: list[Path]) -> dict:
    """The demonstrator's scores over the episodes (drive=command_path), as bcrl-eval-rig aggregates a policy's."""
    episodes = []
    for path in ground_truth_paths:
        with np.load(path) as truth:
            outcome = {k.removeprefix("outcome_"): truth[k].item() for k in truth.files if k.startswith("outcome_")}
        if outcome:
            episodes.append({"episode": path.stem, **outcome})
    if not episodes:
        return {}
    from lerobot_bcrl.robot.eval_rig import aggregate_outcomes

    return {**aggregate_outcomes(episodes), "per_episode": episodes}


def make_demo_bags(cfg: MakeDemoBagsConfig) -> dict[str, list[Path]]:
    """Write `n_episodes` demos; returns the paths written per format (and 'ground_truth').

    Each episode's files are written under `<out_dir>/.partial/` and moved into place when complete, so a folder
    holds whole episodes only; a rerun keeps the episodes already there and records the rest.
    """
    cfg.check()
    out_dir = Path(cfg.out_dir)
    check_resumable(cfg)
    partial_dir = out_dir / ".partial"
    shutil.rmtree(partial_dir, ignore_errors=True)  # what a crashed run left
    names = [*cfg.formats, "ground_truth"]
    written: dict[str, list[Path]] = {name: [] for name in names}
    for name in names:
        (out_dir / name).mkdir(parents=True, exist_ok=True)
        (partial_dir / name).mkdir(parents=True)
    suffix = {"ros1": ".bag", "ros2": "", "ground_truth": ".npz"}
    for episode in tqdm(range(cfg.n_episodes), desc="simulating demos", unit="ep"):
        seed = cfg.seed + episode
        stem = f"episode_{episode:03d}"
        paths = {name: out_dir / name / f"{stem}{suffix[name]}" for name in names}
        if not all(path.exists() for path in paths.values()):
            demo = simulate_demo(cfg, seed)
            staged = {name: partial_dir / name / path.name for name, path in paths.items()}
            for name in cfg.formats:
                write_bag(staged[name], demo, cfg, ros1=name == "ros1", seed=seed)
            save_ground_truth(staged["ground_truth"], demo)
            for name, path in paths.items():
                if path.is_dir():
                    shutil.rmtree(path)
                os.replace(staged[name], path)
        for name, path in paths.items():
            written[name].append(path)
    shutil.rmtree(partial_dir)
    summary = outcome_summary(written["ground_truth"])
    if summary:
        write_json_atomically(out_dir / OUTCOMES_FILE, summary)
    return written


class RecordingMismatchError(RecordingSettingsError):
    """`out_dir` holds episodes recorded with other settings: resuming would mix two recordings."""


def recording_settings(cfg: MakeDemoBagsConfig) -> dict:
    """What must be equal for a rerun to add episodes to a folder: everything but its size and place."""
    settings = {k: v for k, v in asdict(cfg).items() if k not in ("n_episodes", "out_dir")}
    return json.loads(json.dumps(settings, default=str))


def check_resumable(cfg: MakeDemoBagsConfig) -> None:
    """Refuse a folder whose episodes were recorded with other settings; record this run's settings in it."""
    out_dir = Path(cfg.out_dir)
    settings_file = out_dir / SETTINGS_FILE
    current = recording_settings(cfg)
    if any((out_dir / "ground_truth").glob("episode_*.npz")):
        recorded = json.loads(settings_file.read_text()) if settings_file.is_file() else None
        if recorded != current:
            differ = f"no {SETTINGS_FILE}" if recorded is None else ", ".join(
                sorted(k for k in current.keys() | recorded.keys() if recorded.get(k) != current.get(k))
            )
            raise RecordingMismatchError(
                f"{out_dir}: holds episodes recorded with other settings ({differ}); use another --out_dir or remove it"
            )
    (out_dir / "ground_truth").mkdir(parents=True, exist_ok=True)
    (out_dir / OUTCOMES_FILE).unlink(missing_ok=True)  # rewritten from the episodes at the end
    write_json_atomically(settings_file, current)


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(MakeDemoBagsConfig)
    try:
        written = make_demo_bags(cfg)
    except (RecordingSettingsError, KinematicsError) as err:
        sys.exit(f"bcrl-make-demo-bags: {err}")
    for name, paths in written.items():
        print(f"{name:>12}: {len(paths)} -> {Path(cfg.out_dir) / name}")
    outcomes = Path(cfg.out_dir) / OUTCOMES_FILE
    if outcomes.is_file():
        summary = json.loads(outcomes.read_text())
        print(f"    outcomes: reached {summary['reached_success']:.0%}, grasped {summary['grasped_success']:.0%}, "
              f"lifted {summary['lifted_success']:.0%} of {summary['n_episodes']} -> {Path(cfg.out_dir) / 'outcomes.json'}")


if __name__ == "__main__":
    main()
