"""`bcrl-convert`: recorded human demonstrations (ROS 1/ROS 2 bags, robomimic HDF5) -> LeRobotDataset v3.

Example:
    bcrl-convert --input=bags/ --urdf=sawyer.urdf --repo_id=local/towel --root=data/towel --fps=30
Actions are derived from proprioception (consecutive measured EEF poses), as in the paper's real-robot data.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shlex
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import draccus
from tqdm import tqdm

from dataset_tools.convert import hdf5, ros_bag
from dataset_tools.convert.align import align
from dataset_tools.convert.episode import episode_frames, pose_from_joints
from dataset_tools.convert.streams import ConversionError, EpisodeStreams, check_streams
from dataset_tools.convert.topics import TopicMap
from dataset_tools.writer import BadEpisodeError, add_episode_columns, atomic_dataset_dir, default_root, write_bcrl_meta, write_episode
from lerobot_bcrl import features as F
from lerobot_bcrl.geometry import MAX_DELTA_POS_M, MAX_DELTA_ROT_RAD
from lerobot_bcrl.robot.kinematics import KinematicsError, UrdfKinematics

DEFAULT_TASK = "Reach and grasp the corner of the folded towel."


@dataclass
class ConvertConfig:
    input: Path = Path(".")  # a bag (.bag file or ROS 2 bag folder), a folder of bags, or an .hdf5 file
    repo_id: str = "local/towel_demos"
    root: Path | None = None  # default $HF_LEROBOT_HOME/<repo_id>
    fps: int = 30  # the dataset's rate, which is the rate the policy must run at
    task: str = DEFAULT_TASK
    urdf: Path | None = None  # needed when poses come from forward kinematics
    eef_link: str = "right_hand"
    tool_offset_pos_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # tool point in eef_link
    tool_offset_quat_xyzw: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0, 1.0])
    use_pose_topic: bool = True  # False: always forward kinematics, even when the pose topic exists
    topics: TopicMap = field(default_factory=TopicMap)
    hdf5: hdf5.Hdf5Keys = field(default_factory=hdf5.Hdf5Keys)
    images: bool = True
    image_size: int = 128
    video: bool = True  # MP4 (True) or PNG frames in parquet (False)
    trim: str = "none"  # "none" or "until_grasp" (keep trim_after_grasp_s after the first gripper close)
    trim_after_grasp_s: float = 0.5
    skip_bad_episodes: bool = False  # report and skip instead of failing the whole conversion
    overwrite: bool = False


def camera_keys(cfg: ConvertConfig) -> dict[str, str]:
    """Camera name -> feature key; 'agentview' maps onto the simulated datasets' image key."""
    return {name: f"{F.IMAGES_PREFIX}{name}" for name in cfg.topics.cameras} if cfg.images else {}


def dataset_features(cfg: ConvertConfig) -> dict[str, dict]:
    features = F.dataset_features(cfg.image_size if cfg.images else None, cfg.video)
    for key in camera_keys(cfg).values():
        features[key] = {**features.get(F.IMAGE_KEY, {}), "dtype": "video" if cfg.video else "image",
                         "shape": (cfg.image_size, cfg.image_size, 3), "names": ["height", "width", "channel"]}  # fmt: skip
    if cfg.images and F.CAMERA_NAME not in cfg.topics.cameras:
        features.pop(F.IMAGE_KEY, None)
    return features


def list_episodes(cfg: ConvertConfig):
    """(label, loader) per episode, in order; loaders read lazily so a bad file fails at its turn."""
    path = Path(cfg.input)
    cameras = list(camera_keys(cfg))
    if hdf5.is_hdf5(path):
        if not path.is_file():
            raise ConversionError(f"{path}: no such file")
        return [(f"{path}:data/{d}", lambda d=d: hdf5.read_demo(path, d, cfg.hdf5, cameras)) for d in hdf5.demo_names(path)]
    bags = ros_bag.find_bags(path)
    if not bags:
        raise ConversionError(f"{path}: no ROS bag (.bag file or folder with metadata.yaml) and not an .hdf5 file")
    topics = TopicMap(**{**asdict(cfg.topics), "cameras": {n: cfg.topics.cameras[n] for n in cameras}})
    return [(str(bag), lambda bag=bag: ros_bag.read_bag(bag, topics)) for bag in bags]


def convert_one(streams: EpisodeStreams, cfg: ConvertConfig, kinematics_factory):
    check_streams(streams)
    if streams.pose is not None and cfg.use_pose_topic:
        pose = streams.pose
    else:
        try:
            pose = pose_from_joints(streams, kinematics_factory())
        except KinematicsError as err:
            raise ConversionError(f"{streams.source}: {err}") from err
    aligned = align(streams, pose, cfg.fps)
    frames, stats = episode_frames(aligned, streams, cfg.image_size if cfg.images else None, camera_keys(cfg), cfg.trim, cfg.trim_after_grasp_s)
    return frames, stats, aligned.report


def convert(cfg: ConvertConfig) -> tuple[Path, list[dict]]:
    """Convert every episode under `cfg.input`; returns (dataset root, one report row per episode)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = Path(cfg.root) if cfg.root is not None else default_root(cfg.repo_id)
    episodes = list_episodes(cfg)
    kinematics: list[UrdfKinematics] = []

    def kinematics_factory() -> UrdfKinematics:
        if not kinematics:
            if cfg.urdf is None:
                raise KinematicsError("no pose topic in the recording: pass --urdf=<robot URDF> for forward kinematics")
            kinematics.append(UrdfKinematics(cfg.urdf, cfg.topics.joint_names, cfg.eef_link, cfg.tool_offset_pos_m, cfg.tool_offset_quat_xyzw))
        return kinematics[0]

    rows, skipped = [], []
    try:
        with atomic_dataset_dir(root, overwrite=cfg.overwrite) as tmp_root:
            dataset = LeRobotDataset.create(repo_id=cfg.repo_id, fps=cfg.fps, features=dataset_features(cfg),
                                            root=tmp_root, robot_type="sawyer", use_videos=cfg.video)  # fmt: skip
            try:
                for label, load in tqdm(episodes, desc="converting episodes", unit="ep"):
                    try:
                        frames, stats, report = convert_one(load(), cfg, kinematics_factory)
                        write_episode(dataset, frames, cfg.task, source=label)
                    except BadEpisodeError as err:  # raised before any frame of it was added
                        if not cfg.skip_bad_episodes:
                            raise
                        skipped.append({"source": label, "error": str(err)})
                        continue
                    rows.append({"episode_index": len(rows), "source": label, **asdict(stats), "alignment": json.dumps(report.as_dict())})
            except BaseException:
                with contextlib.suppress(Exception):
                    dataset.finalize()
                raise
            dataset.finalize()
            if not rows:
                raise ConversionError(f"{cfg.input}: no episode could be converted ({len(skipped)} skipped)")
            add_episode_columns(tmp_root, rows)
            write_bcrl_meta(tmp_root, {
                "source": "recorded demonstrations (proprioception-derived actions)",
                "command": shlex.join(["bcrl-convert", *sys.argv[1:]]),
                "fps": cfg.fps,
                "action_layout": F.ACTION_NAMES_DOC,
                "clamp": {"max_delta_pos_m": MAX_DELTA_POS_M, "max_delta_rot_rad": MAX_DELTA_ROT_RAD},
                "environment_state": "not recorded on a real robot: zeros",
                "skipped_episodes": skipped,
                "convert_config": draccus.encode(cfg),
            })  # fmt: skip
    finally:
        for k in kinematics:
            k.close()
    return root, rows + [{"skipped": s} for s in skipped]


def print_report(root: Path, rows: list[dict]) -> None:
    done = [r for r in rows if "skipped" not in r]
    print(f"\nWrote {len(done)} episode(s) to {root}")
    for r in done:
        a = json.loads(r["alignment"])
        dropped = sum(a["camera_frames_dropped"].values())
        repeated = sum(a["camera_frames_repeated"].values())
        grasp = "no grasp" if r["grasp_time_s"] < 0 else f"grasp at {r['grasp_time_s']:.2f} s"
        print(f"  {r['episode_index']:3d} {Path(r['source']).name}: {r['n_frames']} frames ({r['duration_s']:.2f} s, {grasp}), "
              f"poses from {a['pose_source']}, {a['joint_samples']} joint samples ({a['joint_gaps']} gaps), "
              f"camera dropped {dropped} / repeated {repeated}, clamped {r['n_clamped_actions']}, trimmed {r['n_trimmed_frames']}")  # fmt: skip
    for r in rows:
        if "skipped" in r:
            print(f"  skipped {r['skipped']['source']}: {r['skipped']['error']}")


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(ConvertConfig)
    try:
        root, rows = convert(cfg)
    except BadEpisodeError as err:
        sys.exit(f"bcrl-convert: {err}")
    print_report(root, rows)


if __name__ == "__main__":
    main()
