"""The simulated lab loop: the arm under physics in joint-velocity mode, demonstrations recorded through the command
path into bags and converted, and policies run back through the command path at the dataset's fps."""

import json
from pathlib import Path

import numpy as np
import pytest
from policy_fixtures import image_dataset_root, save_untrained_checkpoint  # noqa: F401

from dataset_tools.experts import ScriptedLiftExpert
from dataset_tools.noise import DemonstratorConfig
from lerobot_bcrl import geometry as G
from lerobot_bcrl.envs import controller
from lerobot_bcrl.robot.command import CommandConfig, DeltaActionCommander
from lerobot_bcrl.robot.eval_rig import EvalRigConfig, RateMismatchError, dataset_fps, eval_rig, loop_rates, run_episode
from lerobot_bcrl.robot.sim_rig import SimulatedLiftRig, sawyer_kinematics
from lerobot_bcrl.robot.transport import GuardedCommandPath

URDF = Path("/work/shared/robots/sawyer/sawyer.urdf")
FPS = 30.0
TELEOPERATOR = DemonstratorConfig(speed=0.2)  # at most 1 cm per period, as configs/record_lab_bags.yaml


@pytest.fixture(scope="module")
def rig():
    rig = SimulatedLiftRig()
    yield rig
    rig.close()


@pytest.fixture(scope="module")
def command_path(rig):
    commander = DeltaActionCommander(sawyer_kinematics(URDF), CommandConfig(fps=FPS))
    yield GuardedCommandPath(commander, rig.transport, clock=lambda: rig.transport.time_s)
    commander.kinematics.close()


def test_the_arm_lags_its_velocity_commands_then_tracks_them(rig):
    rig.reset(seed=0)
    transport = rig.transport
    command = np.array([0.3, 0.0, -0.2, 0.0, 0.0, 0.0, 0.0])  # rad/s on joints 0 and 2
    transport.send(command, gripper_closed=False)
    start = transport.read_joint_positions()
    transport.wait_period(1 / FPS)
    first = transport.read_joint_positions() - start
    # The first period falls short of the commanded motion (a velocity loop accelerating the arm) ...
    assert np.all(np.abs(first[[0, 2]]) < 0.8 * np.abs(command[[0, 2]]) / FPS)
    for _ in range(4):
        transport.wait_period(1 / FPS)
    # ... and within a few periods the joints move at the commanded velocities, the others hold still.
    velocity = rig.data.qvel[rig.sawyer.arm_dof_adr]
    np.testing.assert_allclose(velocity[[0, 2]], command[[0, 2]], rtol=0.05)
    assert np.all(np.abs(velocity[[1, 3, 4, 5, 6]]) < 0.05 * 0.3)


def test_the_gripper_closes_and_opens(rig):
    def fingers_after(gripper_closed: bool) -> np.ndarray:
        rig.transport.send(np.zeros(7), gripper_closed)
        for _ in range(15):
            rig.transport.wait_period(1 / FPS)
        return rig.state()[7:9]

    rig.reset(seed=0)
    open_fingers, closed_fingers, reopened_fingers = fingers_after(False), fingers_after(True), fingers_after(False)
    # Open they read about +/-0.011 (as robosuite's open gripper, after the start's +/-0.021 settles); closed on nothing they cross over
    # (dataset_tools.experts.EMPTY_GRASP_FINGER_GAP).
    assert open_fingers[0] - open_fingers[1] > 0.015 and closed_fingers[0] - closed_fingers[1] < -0.015
    assert reopened_fingers[0] - reopened_fingers[1] > 0.015


def test_the_state_quaternion_keeps_its_sign_as_bcrl_convert_writes_it(rig, command_path):
    rig.reset(seed=0)
    command_path.reset()
    turn = np.array([0.0, 0.0, 0.0, *G.rotvec_to_quat(np.array([0.0, 0.0, -G.MAX_DELTA_ROT_RAD])), -1.0])
    state_quats, raw_quats = [], []
    for _ in range(120):  # ~220 degrees of yaw: MuJoCo's raw quaternion of the tool changes its cover on the way
        command_path.step(turn, rig.transport.time_s)
        state_quats.append(rig.state()[3:7])
        raw_quats.append(rig.sawyer.grip_site_pose_base(rig.data)[1])
    raw_flips = sum(np.dot(a, b) < 0 for a, b in zip(raw_quats, raw_quats[1:]))
    assert raw_flips >= 1
    assert all(np.dot(a, b) > 0.9 for a, b in zip(state_quats, state_quats[1:]))
    np.testing.assert_allclose(np.abs(np.sum(np.array(state_quats) * np.array(raw_quats), axis=1)), 1.0, rtol=1e-9)


class ScriptedOperatorOnRig:
    """The scripted teleoperator behind the runner's policy interface (it sees the cube through the rig)."""

    def __init__(self, rig):
        self.rig, self.expert = rig, ScriptedLiftExpert(close_steps=12)

    def reset(self):
        self.expert.reset(skill=TELEOPERATOR)

    def delta_action(self, observation):
        action, _ = controller.controller_to_delta_action(self.expert.act(self.rig.privileged_observation()))
        return action


class StillPolicy:
    def reset(self):
        pass

    def delta_action(self, observation):
        return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, -1.0])


def test_the_rig_scores_a_teleoperator_and_a_still_arm(rig, command_path):
    n_periods = int(5 * FPS)
    operator = run_episode(rig, ScriptedOperatorOnRig(rig), command_path, seed=100_000, n_periods=n_periods, image_key=None)
    assert operator["reached"] and operator["grasped"] and operator["lifted"], operator
    assert operator["watchdog_stops"] == 0
    still = run_episode(rig, StillPolicy(), command_path, seed=100_000, n_periods=n_periods, image_key=None)
    assert not (still["reached"] or still["grasped"] or still["lifted"]), still
    assert still["closest_approach_m"] > 0.05


def test_the_runner_runs_at_the_dataset_fps_unless_a_mismatch_is_allowed(tmp_path):
    dataset = tmp_path / "data"
    (dataset / "meta").mkdir(parents=True)
    (dataset / "meta" / "info.json").write_text(json.dumps({"fps": 30}))
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    (checkpoint / "train_config.json").write_text(json.dumps({"dataset": {"root": str(dataset)}}))
    assert dataset_fps(checkpoint, None) == 30.0
    cfg = EvalRigConfig(policy_path=checkpoint)
    assert loop_rates(cfg, 30.0) == (30.0, 30.0)
    with pytest.raises(RateMismatchError, match=r"pretrained_model: trained on 30 fps data, asked to run at 20 fps"):
        loop_rates(EvalRigConfig(policy_path=checkpoint, run_fps=20), 30.0)
    assert loop_rates(EvalRigConfig(run_fps=20, allow_rate_mismatch=True), 30.0) == (20.0, 30.0)
    with pytest.raises(FileNotFoundError, match="info.json: not found"):
        dataset_fps(checkpoint, tmp_path / "elsewhere")


@pytest.mark.slow
def test_eval_rig_runs_a_saved_image_policy_through_the_command_path(image_dataset_root, tmp_path):  # noqa: F811
    checkpoint = tmp_path / "pretrained_model"
    save_untrained_checkpoint(image_dataset_root, checkpoint)
    common = dict(policy_path=checkpoint, urdf=URDF, dataset_root=image_dataset_root, n_episodes=2, episode_s=0.5)
    result = eval_rig(EvalRigConfig(**common, output_dir=tmp_path / "eval"))
    written = json.loads((tmp_path / "eval" / "eval_info.json").read_text())
    assert written["aggregated"] == result["aggregated"] and result["aggregated"]["n_episodes"] == 2
    assert result["rates"] == {"dataset_fps": 20.0, "run_fps": 20.0, "command_fps": 20.0}
    assert [e["seed"] for e in result["per_episode"]] == [100_000, 100_001]
    for episode in result["per_episode"]:
        assert episode["n_periods"] == 10 and episode["duration_s"] == pytest.approx(0.5, abs=0.002)
    # At another rate (allowed for the study) the policy acts half as often, each command held twice as long.
    slow = eval_rig(EvalRigConfig(**common, run_fps=10, allow_rate_mismatch=True, output_dir=tmp_path / "slow"))
    assert slow["rates"] == {"dataset_fps": 20.0, "run_fps": 10.0, "command_fps": 20.0}
    for episode in slow["per_episode"]:
        assert episode["n_periods"] == 5 and episode["duration_s"] == pytest.approx(0.5, abs=0.002)


@pytest.mark.slow
def test_a_recording_through_the_command_path_converts_at_its_fps(rig, tmp_path):
    from dataset_tools.convert.cli import ConvertConfig, convert
    from dataset_tools.make_demo_bags import MakeDemoBagsConfig, commanded_and_done_m, make_demo_bags
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    cfg = MakeDemoBagsConfig(
        out_dir=tmp_path / "bags", drive="command_path", urdf=URDF, command_fps=FPS, control_steps=150,
        operator=TELEOPERATOR, formats=["ros1"], image_size=32,
    )  # fmt: skip
    written = make_demo_bags(cfg)
    truth = np.load(written["ground_truth"][0])
    assert np.isfinite(truth["first_close_time_s"])  # the teleoperator got to the grasp
    outcomes = json.loads((tmp_path / "bags" / "outcomes.json").read_text())  # scored by the rig, as bcrl-eval-rig
    assert outcomes["n_episodes"] == 1 and outcomes["per_episode"][0]["reached"] == truth["outcome_reached"].item()
    # Each period is whole physics steps (2 ms), on a 1/30 s grid: the mean rate is 30 Hz, not 1 / 34 ms.
    np.testing.assert_allclose(truth["command_time_s"], np.arange(150) / FPS, atol=0.0011)
    convert(ConvertConfig(input=written["ros1"][0], repo_id="local/lab", root=tmp_path / "ds", urdf=URDF, fps=int(FPS),
                          image_size=32, video=False))  # fmt: skip
    dataset = LeRobotDataset("local/lab", root=tmp_path / "ds")
    assert dataset.meta.fps == FPS and abs(dataset.num_frames - 150) <= 3
    # The runner's observation.state is the converter's: the same start, read off the rig, at rest
    rig.reset(seed=cfg.seed)
    np.testing.assert_allclose(dataset[0]["observation.state"].numpy(), rig.state(), atol=2e-3)
    # The dataset's actions are what the arm did between measured poses, not what the operator commanded: the
    # arm lags the commands (it starts at rest), then follows them within some percent, and goes where they sent it.
    commanded, done = commanded_and_done_m(truth)
    assert np.linalg.norm(done[0]) < 0.6 * np.linalg.norm(commanded[0])
    moving = np.linalg.norm(commanded, axis=1) > 1e-3
    relative_error = np.linalg.norm(done[moving] - commanded[moving], axis=1).sum() / np.linalg.norm(commanded[moving], axis=1).sum()
    assert moving.sum() > 20 and 0.02 < relative_error < 0.3
    travel = np.linalg.norm(commanded.sum(axis=0))
    assert np.linalg.norm(done.sum(axis=0) - commanded.sum(axis=0)) < 0.1 * travel
    # and the dataset's actions are those measured deltas, resampled on its own 30 fps grid
    derived = np.stack([dataset[i]["action"].numpy() for i in range(dataset.num_frames)])[:, :3]
    assert np.linalg.norm(derived.sum(axis=0) - done.sum(axis=0)) < 0.1 * travel


def test_recording_bags_moves_whole_episodes_into_place_and_resumes(tmp_path):
    from dataset_tools.make_demo_bags import MakeDemoBagsConfig, RecordingMismatchError, make_demo_bags

    cfg = MakeDemoBagsConfig(out_dir=tmp_path, n_episodes=2, control_steps=5, image_size=16, formats=["ros1"])
    first = make_demo_bags(cfg)
    kept = first["ros1"][0].stat().st_mtime_ns
    first["ground_truth"][1].unlink()  # as if the run had died while writing episode 1
    (tmp_path / ".partial" / "ros1").mkdir(parents=True)
    (tmp_path / ".partial" / "ros1" / "episode_001.bag").write_bytes(b"half a bag")
    again = make_demo_bags(cfg)
    assert again == first and all(path.exists() for paths in again.values() for path in paths)
    assert first["ros1"][0].stat().st_mtime_ns == kept  # episode 0 was not recorded again
    assert not (tmp_path / ".partial").exists()
    assert sorted(p.name for p in (tmp_path / "ros1").iterdir()) == ["episode_000.bag", "episode_001.bag"]
    assert first["ros1"][1].read_bytes() != b"half a bag"
    # A rerun with other settings would mix two recordings in one folder: refused, naming the folder and the setting.
    with pytest.raises(RecordingMismatchError, match=r"holds episodes recorded with other settings \(seed\)"):
        make_demo_bags(MakeDemoBagsConfig(out_dir=tmp_path, n_episodes=2, control_steps=5, image_size=16, formats=["ros1"], seed=7))
