"""bcrl-viz and rollout logging: .rrd files read back with rerun's own API."""

import subprocess
import sys
from pathlib import Path

import numpy as np

from lerobot_bcrl import features as F
from lerobot_bcrl.rerun_log import EpisodeLogger, read_entity_rows
from policy_fixtures import image_dataset_root, lowdim_dataset_root  # noqa: F401  (tiny recorded datasets)


def test_bcrl_viz_logs_every_frame_of_the_episode(image_dataset_root, tmp_path):
    out = tmp_path / "episode0.rrd"
    result = subprocess.run(
        [str(Path(sys.executable).parent / "bcrl-viz"), f"--repo_id=local/{image_dataset_root.name}",
         f"--root={image_dataset_root}", "--episode=0", f"--save={out}"],
        capture_output=True, text=True, check=True,
    )
    assert "rerun" in result.stdout and out.stat().st_size > 10_000
    rows = read_entity_rows(out)
    n = 20
    for entity in ("/camera/agentview", "/state", "/world/eef", "/world/eef_path", "/world/action/delta_pos",
                   "/world/cube", "/signals/reward", "/signals/success", "/signals/gripper"):
        assert rows.get(entity) == n, (entity, rows.get(entity))
    assert rows["/action"] == n + 1  # + the static series names
    assert rows.get("/world/grasp", 0) in (0, 1)  # one static point, if the gripper closed


def test_rollout_logger_records_policy_outputs(tmp_path):
    out = tmp_path / "rollout.rrd"
    logger = EpisodeLogger("rollout", save_path=out)
    for t in range(7):
        logger.log_step(
            t,
            {
                F.STATE_KEY: np.random.rand(16).astype(np.float32),
                F.IMAGE_KEY: np.zeros((32, 32, 3), np.uint8),
                F.ACTION_KEY: np.array([0.01, 0, 0, 0, 0, 0, 1, -1], np.float32),
                "policy.action": np.array([0.02, 0, 0, 0, 0, 0, 1, 1], np.float32),
                "policy.value": np.float32(t),
                "theta_t": 0.5,
                F.REWARD_KEY: 2.25,
            },
        )
    logger.close()
    rows = read_entity_rows(out)
    for entity in ("/policy/action", "/signals/value", "/signals/theta_t", "/world/policy/delta_pos", "/camera/agentview"):
        assert rows.get(entity) == 7, (entity, rows.get(entity))


def test_lerobot_eval_rollouts_logged_with_policy_predictions(lowdim_dataset_root, tmp_path):
    """lerobot-eval, unmodified, with our env logging episodes and our policy logging its predictions."""
    from policy_fixtures import save_untrained_checkpoint

    checkpoint = tmp_path / "pretrained_model"
    save_untrained_checkpoint(lowdim_dataset_root, checkpoint)
    rerun_dir = tmp_path / "rollouts"
    subprocess.run(
        [str(Path(sys.executable).parent / "lerobot-eval"), f"--policy.path={checkpoint}", "--env.type=bcrl_lift",
         "--env.obs_type=agent_pos", "--env.episode_length=8", f"--env.rerun_dir={rerun_dir}",
         "--eval.n_episodes=1", "--eval.batch_size=1", "--eval.use_async_envs=false", "--policy.device=cpu",
         f"--output_dir={tmp_path / 'eval'}"],
        capture_output=True, text=True, check=True,
    )
    files = sorted(rerun_dir.glob("*.rrd"))
    assert files
    rows = read_entity_rows(files[0])
    assert rows["/state"] == 8 and rows["/signals/reward"] == 8
    assert rows["/policy/action"] == 8 and rows["/signals/value"] == 8  # predictions beside what happened
