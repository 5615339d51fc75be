"""Simulated operators: each skill knob moves the scripted expert the way it says, the default skill is the plain
expert, and a recording of the operator mix is reproducible."""

from dataclasses import asdict
from pathlib import Path

import draccus
import numpy as np
import pytest

from dataset_tools import record as rec
from dataset_tools.experts import Phase, ScriptedLiftExpert
from dataset_tools.noise import DemonstratorConfig, DemonstratorNoise
from lerobot_bcrl import features as F
from lerobot_bcrl import geometry
from lerobot_bcrl.envs.lift import LiftEnv

MIX_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "record_operator_mix.yaml"


class TracedExpert(ScriptedLiftExpert):
    """The scripted expert, keeping its phase after each action."""

    def reset(self, *args, **kwargs):
        super().reset(*args, **kwargs)
        self.phases = []

    def act(self, observation):
        action = super().act(observation)
        self.phases.append(self.phase)
        return action


@pytest.fixture(scope="module")
def env():
    env = LiftEnv(obs_type="agent_pos", horizon=120)
    yield env
    env.close()


def _episode(env, skill=DemonstratorConfig(), stream=0, seed=101):
    expert = TracedExpert()
    noise = DemonstratorNoise(skill, 7, [0, stream])
    frames, stats = rec.record_episode(env, expert, noise, seed, None, np.random.default_rng([0, stream, 2]))
    return frames, stats, expert


def _close_onsets(frames):
    closed = frames[F.ACTION_KEY][:, 7] > 0
    return np.flatnonzero(closed & ~np.concatenate([[False], closed[:-1]]))


def _eef_minus_cube(frames):
    return frames[F.STATE_KEY][:, F.STATE_EEF_POS] - frames[F.ENV_STATE_KEY][:, 0:3]


def _still_and_open(frames):
    """Steps commanding no motion with the gripper open: a pause (the expert's own still steps close the gripper)."""
    action = frames[F.ACTION_KEY]
    return np.all(action[:, :3] == 0, axis=1) & np.all(action[:, 3:7] == [0, 0, 0, 1], axis=1) & (action[:, 7] < 0)


def _yaw_error(frames, t):
    return geometry.cube_yaw_error(frames[F.STATE_KEY][t, F.STATE_EEF_QUAT], frames[F.ENV_STATE_KEY][t, 3:7])


def test_default_skill_is_the_plain_expert(env):
    """Whatever stream it is given, the default skill draws nothing that changes an action."""
    noise_std = 0.1
    plain_expert, skilled_expert = ScriptedLiftExpert(), ScriptedLiftExpert()
    noise = lambda: DemonstratorNoise(DemonstratorConfig(noise_std), 7, [0, 1])  # noqa: E731
    plain, plain_stats = rec.record_episode(env, plain_expert, noise(), 101)
    skilled, _ = rec.record_episode(env, skilled_expert, noise(), 101, None, np.random.default_rng(123))
    assert plain_stats["success"]
    for key in (F.ACTION_KEY, F.STATE_KEY, F.ENV_STATE_KEY):
        assert plain[key].tobytes() == skilled[key].tobytes(), key
    assert not DemonstratorConfig(noise_std=0.1, noise_mean=0.02).has_skill
    assert DemonstratorConfig(speed=0.8).has_skill and DemonstratorConfig(retry_probability=0.5).has_skill


def test_slower_operator_moves_less_per_step_and_lifts_later(env):
    plain, plain_stats, _ = _episode(env)
    slow, slow_stats, _ = _episode(env, DemonstratorConfig(speed=0.5))
    step_m = lambda frames: np.linalg.norm(frames[F.ACTION_KEY][:, :3], axis=1)  # noqa: E731
    assert step_m(plain).max() == pytest.approx(geometry.MAX_DELTA_POS_M)
    assert step_m(slow).max() <= 0.5 * geometry.MAX_DELTA_POS_M + 1e-9
    # reaches the hover point (xy within 1 cm of the cube) later, and lifts later
    above = lambda frames: int(np.argmax(np.linalg.norm(_eef_minus_cube(frames)[:, :2], axis=1) < 0.01))  # noqa: E731
    assert above(slow) > above(plain) + 5
    assert plain_stats["success"] and slow_stats["success"]
    assert slow_stats["steps_to_lift"] > plain_stats["steps_to_lift"] + 10


def test_hesitation_pauses_whole_blocks(env):
    frames, stats, _ = _episode(env, DemonstratorConfig(hesitation_probability=0.1, hesitation_steps=6))
    plain, plain_stats, _ = _episode(env)
    assert not _still_and_open(plain).any()
    paused = np.flatnonzero(_still_and_open(frames))
    blocks = np.split(paused, np.flatnonzero(np.diff(paused) > 1) + 1)
    assert len(blocks) >= 2
    for block in blocks:  # whole pauses (back-to-back ones join), unless the episode ended in one
        assert len(block) % 6 == 0 or block[-1] == len(frames[F.ACTION_KEY]) - 1
    assert stats["success"] and stats["steps_to_lift"] >= plain_stats["steps_to_lift"] + len(paused) // 2


def test_closing_too_high_misses_and_the_retry_probability_decides_what_follows(env):
    misses = dict(close_too_high_probability=1.0)  # every attempt closes 3-4.5 cm above the grasp point
    gives_up, gives_up_stats, gives_up_expert = _episode(env, DemonstratorConfig(**misses, retry_probability=0.0))
    retries, retries_stats, retries_expert = _episode(env, DemonstratorConfig(**misses, retry_probability=1.0))
    plain, _, _ = _episode(env)
    height_at_close = lambda frames: _eef_minus_cube(frames)[_close_onsets(frames)[0], 2]  # noqa: E731
    assert height_at_close(plain) < 0.015
    assert height_at_close(gives_up) > 0.025 and height_at_close(retries) > 0.025
    assert not gives_up_stats["success"] and not retries_stats["success"]
    # retry probability 0: one grasp, then it hovers above the cube, open, to the end
    assert len(_close_onsets(gives_up)) == 1
    assert gives_up_expert.phases[-1] == Phase.GIVE_UP
    assert np.all(gives_up[F.ACTION_KEY][-20:, 7] < 0)
    assert _eef_minus_cube(gives_up)[-1, 2] == pytest.approx(ScriptedLiftExpert.hover_height_m, abs=0.02)
    # retry probability 1: back above the cube and closes again
    assert len(_close_onsets(retries)) >= 2 and Phase.GIVE_UP not in retries_expert.phases
    assert np.all(retries[F.AUX_IMITATE_KEY])  # an operator's mistakes are not flagged


def test_alignment_error_moves_where_and_how_the_fingers_close(env):
    # stream 3 draws one attempt, aimed 1 cm off and turned 0.12 rad, that grasps at once
    frames, _, expert = _episode(env, DemonstratorConfig(grasp_offset_std_m=0.02, yaw_error_std_rad=0.3), stream=3)
    plain, _, _ = _episode(env, stream=3)
    offset_m, yaw_rad = expert._attempt_offset_m[:2], expert._attempt_yaw_rad
    assert len(_close_onsets(frames)) == 1 and np.linalg.norm(offset_m) > 0.01 and abs(yaw_rad) > 0.1
    close, plain_close = _close_onsets(frames)[0], _close_onsets(plain)[0]
    moved_m = _eef_minus_cube(frames)[close, :2] - _eef_minus_cube(plain)[plain_close, :2]
    np.testing.assert_allclose(moved_m, offset_m, atol=0.003)
    assert abs(_yaw_error(plain, plain_close)) < 0.03
    assert _yaw_error(frames, close) == pytest.approx(-yaw_rad, abs=0.03)  # turned to the face, off by its error


def test_operator_mix_recording_is_reproducible_with_its_operators_in_the_metadata(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from dataset_tools.summary import load_episode_table

    def recorded(name, seed=0):
        cfg = draccus.parse(
            rec.RecordConfig, config_path=str(MIX_CONFIG),
            args=[f"--root={tmp_path / name}", "--n_episodes=6", "--episode_length=60", f"--seed={seed}"],
        )
        rec.record(cfg)
        ds = LeRobotDataset("local/lift_operator_mix", root=cfg.root)
        return cfg, ds.hf_dataset.with_format("numpy")[:], load_episode_table(cfg.root)

    cfg, a, episodes = recorded("a")
    _, b, _ = recorded("b")
    _, c, _ = recorded("c", seed=1)
    for key in (F.ACTION_KEY, F.STATE_KEY, F.ENV_STATE_KEY):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert np.abs(a[F.ACTION_KEY] - c[F.ACTION_KEY]).max() > 1e-3
    assert np.all(a[F.AUX_IMITATE_KEY])
    assert list(episodes["demonstrator_id"]) == list(range(6))
    for i, operator in enumerate(cfg.demonstrators):
        for knob, value in asdict(operator).items():
            assert episodes[knob][i] == pytest.approx(value), knob


def test_skill_knobs_are_checked():
    with pytest.raises(ValueError, match="retry_probability must be in"):
        DemonstratorConfig(retry_probability=1.5)
    with pytest.raises(ValueError, match="speed must be > 0"):
        DemonstratorConfig(speed=0.0)
    with pytest.raises(ValueError, match="scripted expert only"):
        rec.RecordConfig(expert="outputs/some/pretrained_model", demonstrators=[DemonstratorConfig(speed=0.5)])
