"""bcrl-convert against simulated Sawyer demos written as ROS 1 / ROS 2 (MCAP) bags and robomimic HDF5:
deltas match the ground truth, the dataset loads in LeRobot, and bad input fails cleanly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dataset_tools.convert.align import interpolate_poses
from dataset_tools.convert.cli import ConvertConfig, convert, convert_one
from dataset_tools.convert.hdf5 import read_demo
from dataset_tools.convert.ros_bag import read_bag
from dataset_tools.convert.streams import ConversionError, PoseStream
from dataset_tools.convert.topics import TopicMap
from dataset_tools.make_demo_bags import (
    BAG_START_NS,
    MakeDemoBagsConfig,
    _MessageFactory,
    bag_messages,
    simulate_demo,
    write_bag,
    write_messages,
)
from lerobot_bcrl import features as F
from lerobot_bcrl import geometry as G
from lerobot_bcrl.robot.mujoco_sawyer import GRIP_SITE_IN_RIGHT_HAND_POS_M, GRIP_SITE_IN_RIGHT_HAND_QUAT_XYZW
from lerobot_bcrl.robot.sim_rig import sawyer_kinematics

URDF = Path("/work/shared/robots/sawyer/sawyer.urdf")
POS_TOL_M = 1e-3  # the bound per step
ROT_TOL_RAD = 0.01

@pytest.fixture(scope="module")
def demo_and_bags(tmp_path_factory):
    out = tmp_path_factory.mktemp("bags")
    cfg = MakeDemoBagsConfig(out_dir=out, control_steps=60, image_size=32)
    demo = simulate_demo(cfg, seed=3)
    ros1 = write_bag(out / "ep0.bag", demo, cfg, ros1=True, seed=3)
    ros2 = write_bag(out / "ep0_mcap", demo, cfg, ros1=False, seed=3)
    return demo, cfg, ros1, ros2

def convert_cfg(tmp_path, input_path, **kw) -> ConvertConfig:
    base = dict(
        input=input_path, root=tmp_path / "ds", urdf=URDF, image_size=32, video=False,
        tool_offset_pos_m=list(GRIP_SITE_IN_RIGHT_HAND_POS_M), tool_offset_quat_xyzw=list(GRIP_SITE_IN_RIGHT_HAND_QUAT_XYZW),
    )  # fmt: skip
    base.update(kw)
    return ConvertConfig(**base)

def kinematics_factory():
    return sawyer_kinematics(URDF)

def ground_truth_actions(demo, grid_time_s):
    gt = PoseStream("gt", demo.time_s, demo.eef_pos_base_m, demo.eef_quat_base_xyzw)
    pos, quat = interpolate_poses(gt, grid_time_s)  # 500 Hz truth: interpolation error is negligible
    return pos, quat

def delta_errors(action, gt_pos, gt_quat):
    n = len(action)
    gt_dpos = gt_pos[1 : n + 1] - gt_pos[:n]
    gt_dquat = G.quat_multiply(gt_quat[1 : n + 1], G.quat_conjugate(gt_quat[:n]))
    pos_err = np.linalg.norm(action[:, :3] - gt_dpos, axis=1)
    rot_err = G.quat_angle(G.quat_multiply(action[:, 3:7], G.quat_conjugate(gt_dquat)))
    return pos_err, rot_err

@pytest.mark.parametrize("which,use_pose_topic", [("ros1", False), ("ros2", False), ("ros1", True)])
def test_deltas_match_ground_truth(demo_and_bags, tmp_path, which, use_pose_topic):
    demo, _, ros1, ros2 = demo_and_bags
    path = ros1 if which == "ros1" else ros2
    cfg = convert_cfg(tmp_path, path, use_pose_topic=use_pose_topic)
    streams = read_bag(path, cfg.topics)
    frames, stats, report = convert_one(streams, cfg, kinematics_factory)
    aligned_time_s = report.start_s + np.arange(report.n_frames) / cfg.fps
    gt_time_s = aligned_time_s + (streams.start_time_ns - BAG_START_NS) / 1e9
    gt_pos, gt_quat = ground_truth_actions(demo, gt_time_s)
    pos_err, rot_err = delta_errors(frames[F.ACTION_KEY], gt_pos, gt_quat)
    assert pos_err.max() < POS_TOL_M, pos_err.max()
    assert rot_err.max() < ROT_TOL_RAD, rot_err.max()
    # the arm really moved, so the comparison is not vacuous
    assert np.linalg.norm(frames[F.ACTION_KEY][:, :3], axis=1).sum() > 0.1
    assert np.all(frames[F.ACTION_KEY][:, 6] >= 0)  # canonical cover
    # absolute EEF position: FK on Rethink's URDF vs MuJoCo's model agree within a millimetre
    assert np.abs(frames[F.AUX_EEF_POS_KEY] - gt_pos[: stats.n_frames]).max() < 1.5e-3
    # grasp at the expert's first close command, within the fingers' closing time
    first_close_s = demo.time_s[np.flatnonzero(demo.gripper_command > 0)[0]]
    grasp_s = stats.grasp_time_s + (streams.start_time_ns - BAG_START_NS) / 1e9
    assert 0.0 <= grasp_s - first_close_s < 0.5
    assert report.camera_frames_repeated["agentview"] > 0  # dropped camera frames were filled in
    # frames received inside the episode's span that no grid frame uses (a grid end may use one just outside it)
    assert 0 <= report.camera_frames_dropped["agentview"] < report.camera_frames_received["agentview"]

def test_resampling_to_another_fps_keeps_deltas_consistent(demo_and_bags, tmp_path):
    demo, _, ros1, _ = demo_and_bags
    cfg = convert_cfg(tmp_path, ros1, fps=20, use_pose_topic=False)
    streams = read_bag(ros1, cfg.topics)
    frames, _, report = convert_one(streams, cfg, kinematics_factory)
    grid = report.start_s + np.arange(report.n_frames) / 20 + (streams.start_time_ns - BAG_START_NS) / 1e9
    pos_err, rot_err = delta_errors(frames[F.ACTION_KEY], *ground_truth_actions(demo, grid))
    assert pos_err.max() < POS_TOL_M and rot_err.max() < ROT_TOL_RAD

def test_end_to_end_dataset_loads_with_same_features_as_simulated(demo_and_bags, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

    _, _, ros1, ros2 = demo_and_bags
    folder = tmp_path / "bags"
    folder.mkdir()
    (folder / "a.bag").symlink_to(ros1)
    (folder / "b_mcap").symlink_to(ros2, target_is_directory=True)
    cfg = convert_cfg(tmp_path, folder, trim="until_grasp", trim_after_grasp_s=0.2, task="grasp the towel corner")
    root, rows = convert(cfg)
    ds = LeRobotDataset("local/towel_demos", root=root)
    assert ds.num_episodes == 2
    expected = F.dataset_features(32, use_videos=False)
    for key, feature in expected.items():
        assert ds.features[key]["dtype"] == feature["dtype"]
        assert tuple(ds.features[key]["shape"]) == tuple(feature["shape"])
    item = ds[0]
    assert item["task"] == "grasp the towel corner"
    assert item[F.IMAGE_KEY].shape == (3, 32, 32)
    assert all(r["n_trimmed_frames"] > 0 for r in rows)  # cut after the grasp
    assert bool(ds[len(ds) - 1][F.AUX_GRASP_VALID_KEY])
    episodes = LeRobotDatasetMetadata("local/towel_demos", root=root).episodes
    assert "n_clamped_actions" in episodes.column_names

def test_hdf5_robomimic_demo(demo_and_bags, tmp_path):
    import h5py

    demo, *_ = demo_and_bags
    step = 25  # the 500 Hz record taken at 20 Hz, as robomimic stores it
    idx = np.arange(0, len(demo.time_s), step)
    cam_idx = np.searchsorted(demo.camera_time_s, demo.time_s[idx]).clip(0, len(demo.camera_frames) - 1)
    path = tmp_path / "demo.hdf5"
    with h5py.File(path, "w") as f:
        obs = f.create_group("data/demo_0/obs")
        obs["robot0_joint_pos"] = demo.joint_pos_rad[idx]
        obs["robot0_eef_pos"] = demo.eef_pos_base_m[idx]
        obs["robot0_eef_quat"] = demo.eef_quat_base_xyzw[idx]
        obs["robot0_gripper_qpos"] = demo.finger_pos_m[idx]
        obs["agentview_image"] = demo.camera_frames[cam_idx]
    cfg = convert_cfg(tmp_path, path, fps=20)
    cfg.hdf5.eef_pos = ""  # force FK from the joints
    streams = read_demo(path, "demo_0", cfg.hdf5, ["agentview"])
    frames, _, report = convert_one(streams, cfg, kinematics_factory)
    pos_err, rot_err = delta_errors(frames[F.ACTION_KEY], *ground_truth_actions(demo, demo.time_s[idx] - demo.time_s[0]))
    assert report.n_frames == len(idx)
    assert pos_err.max() < POS_TOL_M and rot_err.max() < ROT_TOL_RAD
    root, _ = convert(convert_cfg(tmp_path, path, fps=20))
    assert (root / "meta" / "info.json").exists()

# -- bad input -----------------------------------------------------------------------------------------
def rewrite(demo, cfg, path: Path, mutate, empty_topics=None) -> Path:
    factory = _MessageFactory(ros1=True)
    messages = mutate(bag_messages(demo, cfg, factory, seed=3), factory)
    return write_messages(path, messages, factory, empty_topics)

def assert_fails_cleanly(cfg: ConvertConfig, *fragments: str):
    with pytest.raises(ConversionError) as info:
        convert(cfg)
    for fragment in fragments:
        assert fragment in str(info.value), str(info.value)
    assert not cfg.root.exists()
    assert not list(cfg.root.parent.glob(f".{cfg.root.name}.incomplete-*"))

def test_truncated_bag(demo_and_bags, tmp_path):
    _, _, ros1, ros2 = demo_and_bags
    bad = tmp_path / "truncated.bag"
    bad.write_bytes(ros1.read_bytes()[: ros1.stat().st_size // 2])
    assert_fails_cleanly(convert_cfg(tmp_path, bad), "truncated.bag", "truncated or corrupt")
    mcap = next(ros2.glob("*.mcap"))
    bad2 = tmp_path / "bad_mcap"
    bad2.mkdir()
    (bad2 / "metadata.yaml").write_text((ros2 / "metadata.yaml").read_text())
    (bad2 / mcap.name).write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 3])
    assert_fails_cleanly(convert_cfg(tmp_path, bad2), "bad_mcap")

def test_missing_topic(demo_and_bags, tmp_path):
    _, _, ros1, _ = demo_and_bags
    cfg = convert_cfg(tmp_path, ros1, topics=TopicMap(joint_states="/nope/joint_states"))
    assert_fails_cleanly(cfg, str(ros1), "/nope/joint_states", "not in the bag")

def test_zero_norm_quaternion(demo_and_bags, tmp_path):
    demo, cfg, _, _ = demo_and_bags

    def zero_quat(messages, factory):
        poses = [i for i, m in enumerate(messages) if m[0] == cfg.topics.eef_pose]
        i = poses[40]
        stamp = messages[i][1].header.stamp
        t_ns = stamp.sec * 10**9 + stamp.nanosec
        messages[i] = (messages[i][0], factory.pose(t_ns, [0.5, 0, 0.1], [0.0, 0.0, 0.0, 0.0]), messages[i][2])
        return messages

    bad = rewrite(demo, cfg, tmp_path / "zero_quat.bag", zero_quat)
    assert_fails_cleanly(convert_cfg(tmp_path, bad), "zero_quat.bag", cfg.topics.eef_pose, "zero or non-finite norm", "t=")

def test_joint_names_not_in_urdf(demo_and_bags, tmp_path):
    _, _, ros1, _ = demo_and_bags
    names = [f"right_j{i}" for i in range(6)] + ["right_gripper_l_finger_joint"]  # in the bag, not in the URDF
    cfg = convert_cfg(tmp_path, ros1, use_pose_topic=False, topics=TopicMap(joint_names=names))
    assert_fails_cleanly(cfg, str(ros1), "sawyer.urdf", "right_gripper_l_finger_joint", "not in the URDF")

def test_non_monotonic_timestamps(demo_and_bags, tmp_path):
    demo, cfg, _, _ = demo_and_bags

    def swap(messages, factory):
        joints = [i for i, m in enumerate(messages) if m[0] == cfg.topics.joint_states]
        a, b = joints[50], joints[51]
        messages[a][1].header.stamp, messages[b][1].header.stamp = messages[b][1].header.stamp, messages[a][1].header.stamp
        return messages

    bad = rewrite(demo, cfg, tmp_path / "backwards.bag", swap)
    assert_fails_cleanly(convert_cfg(tmp_path, bad), "backwards.bag", cfg.topics.joint_states, "non-monotonic", "message 51")

def test_camera_without_frames(demo_and_bags, tmp_path):
    demo, cfg, _, _ = demo_and_bags
    bad = rewrite(
        demo, cfg, tmp_path / "blind.bag", lambda ms, f: [m for m in ms if m[0] != cfg.topics.camera],
        empty_topics={cfg.topics.camera: "sensor_msgs/msg/Image"},
    )  # fmt: skip
    assert_fails_cleanly(convert_cfg(tmp_path, bad), "blind.bag", "camera 'agentview'", "no frames")

def test_too_short_episode_and_skip_option(demo_and_bags, tmp_path):
    demo, cfg, ros1, _ = demo_and_bags
    t_end = BAG_START_NS + int(0.05e9)
    short = rewrite(demo, cfg, tmp_path / "short.bag", lambda ms, f: [m for m in ms if m[2] < t_end])
    assert_fails_cleanly(convert_cfg(tmp_path, short), "short.bag", "fewer than 2 frames")
    folder = tmp_path / "mixed"
    folder.mkdir()
    (folder / "a_good.bag").symlink_to(ros1)
    (folder / "b_short.bag").symlink_to(short)
    root, rows = convert(convert_cfg(tmp_path, folder, skip_bad_episodes=True))
    assert [r["source"] for r in rows if "skipped" not in r] == [str(folder / "a_good.bag")]
    assert "b_short.bag" in rows[-1]["skipped"]["source"]
