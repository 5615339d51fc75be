"""bcrl-record: LeRobotDataset v3 round trips, episode metadata, noise, atomic writes."""

import json
import subprocess
import sys
from dataclasses import asdict

import numpy as np
import pytest
import torch

from dataset_tools import record as rec
from dataset_tools.experts import ScriptedLiftExpert, fingers_closed_on_nothing
from dataset_tools.noise import DemonstratorConfig, DemonstratorNoise
from dataset_tools.writer import BadEpisodeError, check_episode
from lerobot_bcrl import features as F
from lerobot_bcrl.envs.lift import LiftEnv
from policy_fixtures import lowdim_dataset_root  # noqa: F401  (a tiny recorded dataset)


def _cfg(root, **kw):
    defaults = dict(repo_id="local/test", root=root, n_episodes=2, episode_length=30, seed=7, sigma=0.1, image_size=64)
    defaults.update(kw)
    return rec.RecordConfig(**defaults)


def _reference_episodes(cfg):
    """Re-run the recorder's episodes in a fresh env: the simulation is deterministic."""
    env = LiftEnv(obs_type="pixels_agent_pos" if cfg.images else "agent_pos", image_size=cfg.image_size, horizon=cfg.episode_length)
    demonstrators = cfg.resolved_demonstrators()
    episodes = []
    for i in range(cfg.n_episodes):
        noise = DemonstratorNoise(demonstrators[i % len(demonstrators)], 7, [cfg.seed, i])
        episodes.append(rec.record_episode(env, rec.make_expert(cfg), noise, cfg.seed + i)[0])
    env.close()
    return episodes


def _load(root, **kw):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset("local/test", root=root, **kw)


@pytest.fixture(scope="module")
def image_dataset(tmp_path_factory):
    cfg = _cfg(tmp_path_factory.mktemp("ds") / "lift_png", video=False)
    rec.record(cfg)
    return cfg


def test_round_trip_through_upstream_lerobot_dataset(image_dataset):
    cfg = image_dataset
    ds = _load(cfg.root)
    assert ds.meta.info.codebase_version == "v3.0"
    assert ds.num_episodes == 2 and ds.num_frames == 60 and ds.fps == 20
    expected = F.dataset_features(64, use_videos=False)
    for key, feature in expected.items():
        assert ds.features[key]["dtype"] == feature["dtype"], key
        assert tuple(ds.features[key]["shape"]) == tuple(feature["shape"]), key
    reference = _reference_episodes(cfg)
    for episode_index, frames in enumerate(reference):
        for t in (0, 13, 29):
            item = ds[episode_index * 30 + t]
            assert item["episode_index"] == episode_index and item["frame_index"] == t
            for key in (F.STATE_KEY, F.ENV_STATE_KEY, F.ACTION_KEY, F.AUX_EEF_POS_KEY, F.AUX_PROPRIO_ACTION_KEY):
                assert item[key].dtype == torch.float32
                np.testing.assert_array_equal(item[key].numpy(), frames[key][t].astype(np.float32), err_msg=key)
            assert item[F.REWARD_KEY].item() == pytest.approx(frames[F.REWARD_KEY][t][0])
            assert bool(item[F.DONE_KEY]) == (t == 29)
            image = (item[F.IMAGE_KEY].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            np.testing.assert_array_equal(image, frames[F.IMAGE_KEY][t])  # PNG is lossless


def test_actions_follow_the_layout_and_aux_labels(image_dataset):
    ds = _load(image_dataset.root)
    actions = torch.stack([ds[i][F.ACTION_KEY] for i in range(60)]).numpy()
    assert np.all(np.linalg.norm(actions[:, :3], axis=1) <= 0.05 + 1e-6)
    np.testing.assert_allclose(np.linalg.norm(actions[:, 3:7], axis=1), 1.0, atol=1e-5)
    assert np.all(actions[:, 6] >= 0) and set(np.unique(actions[:, 7])) <= {-1.0, 1.0}
    for episode in range(2):
        rows = [ds[episode * 30 + t] for t in range(30)]
        gripper = np.array([r[F.ACTION_KEY][7].item() for r in rows])
        grasp = np.stack([r[F.AUX_GRASP_POS_KEY].numpy() for r in rows])
        assert np.all(grasp == grasp[0])  # one grasp location per episode
        if (gripper > 0).any():
            first_close = int(np.argmax(gripper > 0))
            np.testing.assert_array_equal(grasp[0], rows[first_close][F.AUX_EEF_POS_KEY].numpy())
            assert bool(rows[0][F.AUX_GRASP_VALID_KEY])


def test_episode_metadata(image_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    meta = LeRobotDatasetMetadata("local/test", root=image_dataset.root)
    episodes = meta.episodes
    ds = _load(image_dataset.root)
    for i in range(2):
        rewards = [ds[i * 30 + t][F.REWARD_KEY].item() for t in range(30)]
        assert episodes["episode_return"][i] == pytest.approx(sum(rewards), rel=1e-6)
        assert episodes["success"][i] == any(r > 0 for r in rewards)
        assert episodes["noise_std"][i] == pytest.approx(0.1)
        assert episodes["seed"][i] == 7 + i and episodes["demonstrator_id"][i] == 0
    made_by = json.loads((image_dataset.root / "meta" / "bcrl.json").read_text())
    assert made_by["demonstrators"] == [asdict(DemonstratorConfig(noise_std=0.1))]


@pytest.mark.parametrize("backend", ["pyav", "torchcodec"])
def test_video_dataset_decodes_close_to_recorded_frames(tmp_path, backend):
    cfg = _cfg(tmp_path / "lift_video", n_episodes=1, video=True)
    rec.record(cfg)
    assert list((cfg.root / "videos").rglob("*.mp4"))
    reference = _reference_episodes(cfg)[0][F.IMAGE_KEY]
    ds = _load(cfg.root, video_backend=backend)
    for t in (0, 15, 29):
        decoded = ds[t][F.IMAGE_KEY].permute(1, 2, 0).numpy() * 255
        assert decoded.shape == (64, 64, 3)
        # lossy codec: close on average, and frames are not shifted in time
        errors = [np.abs(decoded - reference[s].astype(np.float32)).mean() for s in range(30)]
        assert errors[t] < 8.0, errors[t]
        assert int(np.argmin(errors)) == t or errors[t] <= min(errors) + 0.5


def test_lowdim_recording_is_reproducible_and_sigma_matters(tmp_path):
    a = _cfg(tmp_path / "a", images=False, n_episodes=1)
    b = _cfg(tmp_path / "b", images=False, n_episodes=1)
    c = _cfg(tmp_path / "c", images=False, n_episodes=1, sigma=0.0)
    for cfg in (a, b, c):
        rec.record(cfg)
    actions = [torch.stack([x[F.ACTION_KEY] for x in _load(cfg.root)]).numpy() for cfg in (a, b, c)]
    assert F.IMAGE_KEY not in _load(a.root).features
    np.testing.assert_array_equal(actions[0], actions[1])
    assert np.abs(actions[0] - actions[2]).max() > 1e-3


def test_several_demonstrators_are_assigned_round_robin(tmp_path):
    demonstrators = [DemonstratorConfig(noise_std=0.0), DemonstratorConfig(noise_std=0.2, noise_mean=0.05, noise_correlation=0.8)]
    cfg = _cfg(tmp_path / "multi", images=False, n_episodes=3, demonstrators=demonstrators, episode_length=10)
    rec.record(cfg)
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    episodes = LeRobotDatasetMetadata("local/test", root=cfg.root).episodes
    assert list(episodes["demonstrator_id"]) == [0, 1, 0]
    assert list(episodes["noise_std"]) == pytest.approx([0.0, 0.2, 0.0])


def test_planned_miss_is_flagged_then_retried_and_lifted(tmp_path):
    cfg = _cfg(tmp_path / "miss", images=False, n_episodes=2, episode_length=100, miss_probability=1.0)
    rec.record(cfg)
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    episodes = LeRobotDatasetMetadata("local/test", root=cfg.root).episodes
    assert list(episodes["planned_miss"]) == [True, True] and list(episodes["success"]) == [True, True]
    ds = _load(cfg.root)
    for episode in range(2):
        rows = [ds[episode * 100 + t] for t in range(100)]
        imitate = np.array([bool(r[F.AUX_IMITATE_KEY]) for r in rows])
        closed = np.array([r[F.ACTION_KEY][7].item() > 0 for r in rows])
        cube_z = np.array([r[F.ENV_STATE_KEY][2].item() for r in rows])
        eef = np.stack([r[F.AUX_EEF_POS_KEY].numpy() for r in rows])
        miss = np.flatnonzero(~imitate)
        assert episodes["n_frames_not_imitated"][episode] == len(miss) > 0
        assert miss[0] == 0 and np.all(np.diff(miss) == 1)  # one block from the start: approach, descend, close
        assert np.argmax(closed) in miss  # the first close is part of the miss
        after = np.arange(miss[-1] + 1, 100)
        reopened = after[~closed[after]]
        assert len(reopened) > 0, "the expert never opened the gripper after the miss"
        regrasp = reopened[0] + int(np.argmax(closed[reopened[0]:]))
        assert closed[regrasp] and regrasp > reopened[0]
        assert cube_z[: reopened[0]].max() - cube_z[0] < 0.005  # the miss did not move the cube up
        assert cube_z.max() - cube_z[0] > 0.04  # the retry lifted it
        # the grasp label is where the retry closed, not the miss
        np.testing.assert_array_equal(rows[0][F.AUX_GRASP_POS_KEY].numpy(), eef[regrasp])
    from dataset_tools.summary import summarize

    summary = summarize(cfg.root)
    assert summary["planned_miss_episodes"] == 2 and summary["planned_miss_success_rate"] == 1.0
    assert summary["frames_not_imitated"] == sum(episodes["n_frames_not_imitated"])


def _miss_episode(reopen_on_empty_grasp, miss_offset_m, noise_std=0.0):
    env = LiftEnv(obs_type="agent_pos", horizon=100)
    try:
        expert = ScriptedLiftExpert(reopen_on_empty_grasp=reopen_on_empty_grasp)
        noise = DemonstratorNoise(DemonstratorConfig(noise_std=noise_std), 7, [0, 3])
        return rec.record_episode(env, expert, noise, 103, miss_offset_m)
    finally:
        env.close()


def _first_reopen(frames):
    """Index of the first open command after the first close."""
    closed = frames[F.ACTION_KEY][:, 7] > 0
    first_close = int(np.argmax(closed))
    return first_close + int(np.argmax(~closed[first_close:]))


def test_empty_grasp_check_reopens_low_where_the_rise_rule_lifts_first():
    # closes on air beside the cube, 1.5 cm above its centre (found by sampling the wide, low miss range)
    offset = np.array([0.029, -0.013, 0.015])
    checked, checked_stats = _miss_episode(True, offset)
    unchecked, _ = _miss_episode(False, offset)
    for frames in (checked, unchecked):
        miss = np.flatnonzero(~frames[F.AUX_IMITATE_KEY][:, 0])
        assert miss[0] == 0 and np.all(np.diff(miss) == 1)
        assert int(np.argmax(frames[F.ACTION_KEY][:, 7] > 0)) in miss  # the air close is the miss
    reopen, reopen_unchecked = _first_reopen(checked), _first_reopen(unchecked)
    gripper_qpos = checked[F.STATE_KEY][reopen, F.STATE_GRIPPER_QPOS]
    assert fingers_closed_on_nothing(gripper_qpos)  # it opened because the fingers met nothing
    eef_above_cube = checked[F.STATE_KEY][:, 2] - checked[F.ENV_STATE_KEY][:, 2]
    eef_above_cube_unchecked = unchecked[F.STATE_KEY][:, 2] - unchecked[F.ENV_STATE_KEY][:, 2]
    assert eef_above_cube[reopen] < 0.025  # reopened low, where it closed
    assert eef_above_cube_unchecked[reopen_unchecked] > eef_above_cube[reopen] + 0.005  # the old rule rose first
    assert reopen < reopen_unchecked
    assert checked_stats["success"] and checked_stats["steps_to_lift"] > reopen  # then grasped and lifted


def test_empty_grasp_check_leaves_a_held_grasp_alone():
    """Without a miss the fingers close on the cube: with or without the check, the same episode."""
    checked, stats = _miss_episode(True, None, noise_std=0.1)
    unchecked, _ = _miss_episode(False, None, noise_std=0.1)
    assert stats["success"]
    np.testing.assert_array_equal(checked[F.ACTION_KEY], unchecked[F.ACTION_KEY])
    np.testing.assert_array_equal(checked[F.STATE_KEY], unchecked[F.STATE_KEY])


def test_planned_misses_need_the_scripted_expert_and_a_probability():
    with pytest.raises(ValueError, match="miss_probability must be in"):
        rec.RecordConfig(miss_probability=1.5)
    with pytest.raises(ValueError, match="scripted expert"):
        rec.RecordConfig(miss_probability=0.2, expert="outputs/some/pretrained_model")
    with pytest.raises(ValueError, match=r"miss_height_range_m must be .*got \[0.05, 0.01\]"):
        rec.RecordConfig(miss_height_range_m=(0.05, 0.01))
    with pytest.raises(ValueError, match="miss_max_aside_m >= 0"):
        rec.RecordConfig(miss_max_aside_m=-0.01)
    with pytest.raises(ValueError, match="reopen_on_empty_grasp is a behaviour of the scripted expert"):
        rec.RecordConfig(reopen_on_empty_grasp=True, expert="outputs/some/pretrained_model")


def test_correlated_noise_statistics():
    d = DemonstratorConfig(noise_std=0.1, noise_mean=0.02, noise_correlation=0.9)
    noise = DemonstratorNoise(d, action_dim=7, seed=0)
    samples = np.stack([noise.sample() for _ in range(20000)])
    assert samples[:, :6].mean() == pytest.approx(0.02, abs=0.01)
    assert samples[:, -1].mean() == pytest.approx(0.0, abs=0.01)  # no bias on the gripper
    assert samples[:, 0].std() == pytest.approx(0.1, rel=0.1)
    centred = samples[:, 0] - samples[:, 0].mean()
    lag1 = np.dot(centred[1:], centred[:-1]) / np.dot(centred, centred)
    assert lag1 == pytest.approx(0.9, abs=0.03)
    white = DemonstratorNoise(DemonstratorConfig(noise_std=0.1), 7, seed=0)
    np.testing.assert_array_equal(white.sample(), DemonstratorNoise(DemonstratorConfig(noise_std=0.1), 7, seed=0).sample())


def test_interrupted_recording_leaves_nothing_behind(tmp_path, monkeypatch):
    cfg = _cfg(tmp_path / "out" / "lift", images=False, n_episodes=3, episode_length=10)
    calls = {"n": 0}
    real_record_episode = rec.record_episode

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real_record_episode(*args, **kwargs)

    monkeypatch.setattr(rec, "record_episode", interrupted)
    with pytest.raises(KeyboardInterrupt):
        rec.record(cfg)
    assert calls["n"] == 2
    assert list((tmp_path / "out").iterdir()) == []  # neither the dataset nor a temporary folder


def test_existing_dataset_is_not_overwritten_by_default(tmp_path):
    cfg = _cfg(tmp_path / "lift", images=False, n_episodes=1, episode_length=5)
    rec.record(cfg)
    with pytest.raises(FileExistsError, match="overwrite"):
        rec.record(cfg)
    cfg.overwrite = True
    cfg.n_episodes = 2
    rec.record(cfg)
    assert _load(cfg.root).num_episodes == 2


def test_bad_episode_errors_name_source_episode_and_frame():
    frames = {F.ACTION_KEY: np.tile([0, 0, 0, 0, 0, 0, 1.0, -1], (5, 1)), F.STATE_KEY: np.zeros((5, 16))}
    frames[F.STATE_KEY][3, 2] = np.nan
    with pytest.raises(BadEpisodeError, match=r"demo\.bag: episode 4, frame 3: non-finite value in 'observation.state'"):
        check_episode(frames, "demo.bag", 4)
    frames[F.STATE_KEY][3, 2] = 0
    frames[F.ACTION_KEY][2, 3:7] = [0, 0, 0, 2.0]
    with pytest.raises(BadEpisodeError, match="episode 4, frame 2: action quaternion has norm 2.0000"):
        check_episode(frames, "demo.bag", 4)
    with pytest.raises(BadEpisodeError, match="1 frame"):
        check_episode({F.ACTION_KEY: frames[F.ACTION_KEY][:1]}, "demo.bag", 0)


@pytest.mark.slow
def test_bcrl_record_cli_and_summary(tmp_path):
    root = tmp_path / "cli"
    bin_dir = __import__("pathlib").Path(sys.executable).parent
    out = subprocess.run(
        [str(bin_dir / "bcrl-record"), "--repo_id=local/cli", f"--root={root}", "--n_episodes=2",
         "--episode_length=20", "--images=false", "--sigma=0.01"],
        capture_output=True, text=True, check=True,
    ).stdout
    assert "episodes: 2" in out and "success rate" in out
    summary = json.loads(
        subprocess.run([str(bin_dir / "bcrl-summary"), f"--root={root}", "--json=true"], capture_output=True, text=True, check=True).stdout
    )
    assert summary["episodes"] == 2 and summary["frames"] == 40 and 0.0 <= summary["success_rate"] <= 1.0


def test_summary_gives_the_return_of_the_episodes_without_a_planned_miss(tmp_path, capsys):
    """The recipe's sets are scored against the episodes the expert did not miss on purpose: the summary gives them."""
    import pandas as pd

    from dataset_tools.summary import print_summary, summarize

    returns, missed = [300.0, 340.0, 320.0, 350.0], [True, False, True, False]
    (tmp_path / "meta" / "episodes" / "chunk-000").mkdir(parents=True)
    (tmp_path / "meta" / "info.json").write_text(json.dumps(
        {"codebase_version": "v3.0", "fps": 20, "total_episodes": 4, "total_frames": 800, "features": {}}))
    pd.DataFrame({"episode_index": range(4), "episode_return": returns, "success": [True] * 4,
                  "steps_to_lift": [67, 49, 58, 45], "demonstrator_id": [0] * 4, "noise_std": [0.01] * 4,
                  "planned_miss": missed, "n_frames_not_imitated": [30, 0, 25, 0]}
                 ).to_parquet(tmp_path / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    summary = summarize(tmp_path)
    assert summary["mean_return"] == pytest.approx(327.5)  # every episode
    assert summary["first_try_episodes"] == 2 and summary["first_try_mean_return"] == pytest.approx(345.0)
    assert summary["first_try_return_ci95"] == pytest.approx(1.96 * np.std([340.0, 350.0], ddof=1) / np.sqrt(2))
    print_summary(summary)
    assert "without a planned miss: 2 episodes, return 345.0" in capsys.readouterr().out


def test_any_lerobot_policy_checkpoint_can_be_the_expert(lowdim_dataset_root, tmp_path):
    """`--expert=<pretrained_model>`: a policy's 8-D actions, in controller units, plus the demonstrator's noise."""
    from policy_fixtures import save_untrained_checkpoint

    checkpoint = tmp_path / "pretrained_model"
    save_untrained_checkpoint(lowdim_dataset_root, checkpoint)
    cfg = _cfg(tmp_path / "policy_demos", images=False, n_episodes=1, episode_length=12, sigma=0.0, expert=str(checkpoint))
    rec.record(cfg)
    recorded = torch.stack([x[F.ACTION_KEY] for x in _load(cfg.root)]).numpy()
    # the recorded actions are the policy's own (no noise at sigma 0), replayed through the same env
    env = LiftEnv(obs_type="agent_pos", horizon=12)
    obs, _ = env.reset(seed=cfg.seed)
    expert = rec.make_expert(cfg)
    expert.reset()
    from lerobot_bcrl.envs.controller import controller_to_delta_action

    for t in range(12):
        action, _ = controller_to_delta_action(expert.act(obs))
        np.testing.assert_allclose(recorded[t], action.astype(np.float32), atol=1e-6)
        obs, *_ = env.step(action)
    env.close()
