"""`bcrl-record`: roll out a (noisy) expert in the Lift env and write a LeRobotDataset v3.

Example:
    bcrl-record --repo_id=local/lift_sigma0.1 --root=data/lift_sigma0.1 --n_episodes=50 --sigma=0.1
Every episode is kept, failures included: the data is non-optimal on purpose (method.md section 1).
"""

from __future__ import annotations

import contextlib
import logging
import shlex
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import draccus
import numpy as np
from tqdm import tqdm

from lerobot_bcrl import features as F
from lerobot_bcrl.envs import controller
from lerobot_bcrl.geometry import delta_action_from_poses
from dataset_tools.experts import (
    MISS_HEIGHT_RANGE_M,
    MISS_MAX_ASIDE_M,
    Expert,
    PolicyExpert,
    ScriptedLiftExpert,
    sample_miss_offset,
)
from dataset_tools.noise import DemonstratorConfig, DemonstratorNoise, beta_demonstrators
from dataset_tools.summary import print_summary, summarize
from dataset_tools.writer import (
    add_episode_columns,
    atomic_dataset_dir,
    default_root,
    write_bcrl_meta,
    write_episode,
)


@dataclass
class BetaDemonstratorsConfig:
    n: int = 0  # number of simulated operators with Beta-distributed noise (0: off)
    max_std: float = 0.2  # noise std of operator i is max_std * Beta(a, b)
    a: float = 2.0  # the Beta distribution's shape parameters
    b: float = 5.0
    max_abs_mean: float = 0.0  # per-operator bias drawn uniformly in [-max_abs_mean, max_abs_mean]


@dataclass
class RecordConfig:
    repo_id: str = "local/bcrl_lift"  # dataset id (also the folder name under $HF_LEROBOT_HOME)
    root: Path | None = None  # where to write; default $HF_LEROBOT_HOME/<repo_id>
    n_episodes: int = 10  # episodes to record
    seed: int = 0  # episode i resets the env with seed + i; noise is seeded from (seed, i)
    sigma: float = 0.1  # the paper's single demonstrator: N(0, sigma) on every controller action
    # Several demonstrators (overrides sigma); episode i is recorded by demonstrator i mod their number.
    demonstrators: list[DemonstratorConfig] = field(default_factory=list)
    beta_demonstrators: BetaDemonstratorsConfig = field(default_factory=BetaDemonstratorsConfig)
    expert: str = "scripted"  # "scripted", or the path of a LeRobot policy checkpoint (pretrained_model)
    # Share of episodes (scripted expert) whose first grasp is a planned miss, then a retry: recoveries that
    # first-try demonstrations never show. The miss's frames get aux.imitate = False (BC skips them).
    miss_probability: float = 0.0
    miss_height_range_m: tuple[float, float] = MISS_HEIGHT_RANGE_M  # how far above the grasp point a miss closes
    miss_max_aside_m: float = MISS_MAX_ASIDE_M  # and how far aside (uniform over the disc)
    # The scripted expert checks its fingers after closing: closed on nothing, it opens at once and hovers
    # above the cube again (the recovery then starts from low, closed-on-air states too, not only after a rise).
    reopen_on_empty_grasp: bool = False
    images: bool = True  # record the agentview camera (False: low-dim dataset)
    video: bool = True  # images as MP4 video (True) or PNG frames in the parquet files (False)
    image_size: int = 128
    episode_length: int = 200  # the paper's horizon
    cheap_render: bool = True  # simplified meshes, no shadows/reflections (docs/environment.md)
    dense_reward: bool = False  # store robosuite's shaped reward instead of the sparse one
    sim_step: str = "fast"  # or "robosuite": robosuite's own env.step (the same frames: docs/environment.md)
    overwrite: bool = False  # replace an existing dataset at root
    device: str = "cpu"  # for a policy expert

    def __post_init__(self):
        if not 0.0 <= self.miss_probability <= 1.0:
            raise ValueError(f"miss_probability must be in [0, 1], got {self.miss_probability}")
        if self.miss_probability > 0 and self.expert != "scripted":
            raise ValueError("miss_probability needs the scripted expert (a policy expert cannot plan a miss)")
        low, high = self.miss_height_range_m
        if not 0.0 <= low <= high or self.miss_max_aside_m < 0.0:
            raise ValueError(
                f"miss_height_range_m must be [low, high] with 0 <= low <= high and miss_max_aside_m >= 0, "
                f"got {list(self.miss_height_range_m)} and {self.miss_max_aside_m}"
            )
        if self.reopen_on_empty_grasp and self.expert != "scripted":
            raise ValueError("reopen_on_empty_grasp is a behaviour of the scripted expert")
        if self.expert != "scripted" and any(d.has_skill for d in self.demonstrators):
            raise ValueError("operator skill knobs (speed, hesitation, ...) are read by the scripted expert only")

    def resolved_demonstrators(self) -> list[DemonstratorConfig]:
        if self.demonstrators:
            return list(self.demonstrators)
        b = self.beta_demonstrators
        if b.n > 0:
            return beta_demonstrators(b.n, b.max_std, b.a, b.b, b.max_abs_mean, seed=self.seed)
        return [DemonstratorConfig(noise_std=self.sigma)]


def make_expert(cfg: RecordConfig) -> Expert:
    if cfg.expert == "scripted":
        return ScriptedLiftExpert(reopen_on_empty_grasp=cfg.reopen_on_empty_grasp)
    return PolicyExpert(cfg.expert, device=cfg.device)


def record_episode(
    env,
    expert: Expert,
    noise: DemonstratorNoise,
    seed: int,
    miss_offset_m: np.ndarray | None = None,
    skill_rng: np.random.Generator | None = None,
) -> tuple[dict, dict]:
    """One episode: (frames as arrays keyed by dataset feature, episode statistics).

    `miss_offset_m` (scripted expert only) plans a missed first grasp; its frames are flagged not to imitate.
    A scripted expert acts with the skill of the noise's demonstrator, drawing its mistakes from `skill_rng`;
    those mistakes are not flagged (every frame imitated).
    """
    observation, _ = env.reset(seed=seed)
    if isinstance(expert, ScriptedLiftExpert):
        expert.reset(miss_offset_m=miss_offset_m, skill=noise.demonstrator, rng=skill_rng)
    else:
        expert.reset()
    columns: dict[str, list] = {
        k: [] for k in (F.STATE_KEY, F.ENV_STATE_KEY, F.ACTION_KEY, F.AUX_EEF_POS_KEY, F.AUX_IMITATE_KEY)
    }
    columns.update({F.REWARD_KEY: [], F.DONE_KEY: [], F.SUCCESS_KEY: []})
    if "pixels" in observation:
        columns[F.IMAGE_KEY] = []
    proprio_actions = []
    n_clamped = 0
    steps_to_lift = -1
    done = False
    while not done:
        noisy = np.clip(expert.act(observation) + noise.sample(), -1.0, 1.0)
        columns[F.AUX_IMITATE_KEY].append([not getattr(expert, "acting_on_planned_miss", False)])
        action, clamped = controller.controller_to_delta_action(noisy)
        n_clamped += int(clamped)
        next_observation, reward, terminated, truncated, info = env.step(action)
        done = terminated or truncated
        columns[F.STATE_KEY].append(observation["agent_pos"])
        columns[F.ENV_STATE_KEY].append(observation["environment_state"])
        columns[F.AUX_EEF_POS_KEY].append(observation["agent_pos"][F.STATE_EEF_POS])
        columns[F.ACTION_KEY].append(action)
        columns[F.REWARD_KEY].append([reward])
        columns[F.DONE_KEY].append([done])
        columns[F.SUCCESS_KEY].append([info["is_success"]])
        if F.IMAGE_KEY in columns:
            columns[F.IMAGE_KEY].append(observation["pixels"][F.CAMERA_NAME])
        proprio_action, _ = delta_action_from_poses(
            observation["agent_pos"][F.STATE_EEF_POS],
            observation["agent_pos"][F.STATE_EEF_QUAT],
            next_observation["agent_pos"][F.STATE_EEF_POS],
            next_observation["agent_pos"][F.STATE_EEF_QUAT],
            action[7],
        )
        proprio_actions.append(proprio_action)
        if info["is_success"] and steps_to_lift < 0:
            steps_to_lift = len(columns[F.ACTION_KEY])
        observation = next_observation
    frames = {k: np.stack(v) for k, v in columns.items()}
    frames[F.AUX_PROPRIO_ACTION_KEY] = np.stack(proprio_actions)
    stats = {
        "episode_return": float(frames[F.REWARD_KEY].sum()),
        "success": bool(frames[F.SUCCESS_KEY].any()),
        "steps_to_lift": steps_to_lift,
        "n_clamped_actions": n_clamped,
        "planned_miss": miss_offset_m is not None,
        "n_frames_not_imitated": int((~frames[F.AUX_IMITATE_KEY]).sum()),
    }
    return frames, stats


def record(cfg: RecordConfig) -> Path:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_bcrl.envs.lift import TASK_DESCRIPTION, LiftEnv

    root = Path(cfg.root) if cfg.root is not None else default_root(cfg.repo_id)
    demonstrators = cfg.resolved_demonstrators()
    env = LiftEnv(
        obs_type="pixels_agent_pos" if cfg.images else "agent_pos",
        image_size=cfg.image_size,
        cheap_render=cfg.cheap_render,
        dense_reward=cfg.dense_reward,
        horizon=cfg.episode_length,
        sim_step=cfg.sim_step,
    )
    expert = make_expert(cfg)
    rows = []
    try:
        with atomic_dataset_dir(root, overwrite=cfg.overwrite) as tmp_root:
            dataset = LeRobotDataset.create(
                repo_id=cfg.repo_id,
                fps=env.metadata["render_fps"],
                features=F.dataset_features(cfg.image_size if cfg.images else None, cfg.video),
                root=tmp_root,
                robot_type="sawyer",
                use_videos=cfg.video,
            )
            try:
                progress = tqdm(range(cfg.n_episodes), desc="recording episodes", unit="ep")
                for episode_index in progress:
                    demonstrator_id = episode_index % len(demonstrators)
                    demonstrator = demonstrators[demonstrator_id]
                    noise = DemonstratorNoise(demonstrator, controller.CONTROLLER_ACTION_DIM, [cfg.seed, episode_index])
                    env_seed = cfg.seed + episode_index
                    # Its own stream: the noise and the env seed are the same whatever miss_probability is.
                    miss_rng = np.random.default_rng([cfg.seed, episode_index, 1])
                    miss = None
                    if miss_rng.uniform() < cfg.miss_probability:
                        miss = sample_miss_offset(miss_rng, cfg.miss_height_range_m, cfg.miss_max_aside_m)
                    skill_rng = np.random.default_rng([cfg.seed, episode_index, 2])
                    frames, stats = record_episode(env, expert, noise, env_seed, miss, skill_rng)
                    write_episode(dataset, frames, TASK_DESCRIPTION, source=f"bcrl-record (env seed {env_seed})")
                    rows.append(
                        {
                            "episode_index": episode_index,
                            **stats,
                            "demonstrator_id": demonstrator_id,
                            **asdict(demonstrator),  # its noise and skill knobs
                            "seed": env_seed,
                        }
                    )
                    n_success = sum(r["success"] for r in rows)
                    progress.set_postfix(success=f"{n_success}/{len(rows)}", ret=f"{stats['episode_return']:.0f}")
            except BaseException:
                # Close LeRobot's open writers now: left to the garbage collector they would write
                # into the temporary folder after it has been removed, and leave it behind.
                with contextlib.suppress(Exception):
                    dataset.finalize()
                raise
            dataset.finalize()
            add_episode_columns(tmp_root, rows)
            write_bcrl_meta(
                tmp_root,
                {
                    "source": "simulated expert (robosuite Lift, Sawyer)",
                    "command": shlex.join(["bcrl-record", *sys.argv[1:]]),
                    "expert": cfg.expert,
                    "demonstrators": [asdict(d) for d in demonstrators],
                    "fps": env.metadata["render_fps"],
                    "action_layout": F.ACTION_NAMES_DOC,
                    "record_config": draccus.encode(cfg),
                },
            )
    finally:
        env.close()
    return root


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(RecordConfig)
    root = record(cfg)
    print_summary(summarize(root), root)


if __name__ == "__main__":
    main()
