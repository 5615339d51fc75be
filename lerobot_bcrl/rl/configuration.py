"""bcrl-finetune's command line: a draccus config, like lerobot-train's, read from `--config_path` and flags.

`--policy.path=<pretrained_model>` fine-tunes a checkpoint (its config, with `--policy.*` overrides on top);
`--policy.type=bcrl` starts from scratch. The ready configs are in configs/ (configs/README.md).
"""

import time
from dataclasses import dataclass, field
from pathlib import Path

from lerobot.configs import parser
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.configs import EnvConfig

from lerobot_bcrl.envs.configuration_lift import LiftEnvConfig
from lerobot_bcrl.rl.checkpoint import policy_env_steps
from lerobot_bcrl.rl.ppo import PPOConfig
from lerobot_bcrl.rl.rollout import MAX_WORKER_FAILURES, WORKER_TIMEOUT_S
from lerobot_bcrl.rl.schedule import ScheduleConfig

SELECTIONS = ("last", "best_validation")
ROLLOUT_BACKENDS = ("process", "ray")


@dataclass
class DemoDatasetConfig:
    repo_id: str = "local/lift"  # the demonstrations of the BC term (and the feature shapes/stats from scratch)
    root: str | None = None
    episodes: list[int] | None = None  # None: all episodes
    video_backend: str | None = None


@dataclass
class RolloutConfig:
    backend: str = "process"  # "process": subprocesses of this one; "ray": Ray actors, here or on a cluster
    ray_address: str | None = None  # a running Ray cluster (`ray start --head`'s address); None: a Ray started here
    n_workers: int = 2  # subprocesses or actors; 0 runs the envs in this process (process backend)
    envs_per_worker: int = 2
    steps_per_env: int = 128  # rollout length per env per iteration
    # PPO's rollouts on robosuite's shaped reward (reaching, grasping, then 2.25 lifted) where the env's is sparse;
    # validation, the choice and the test keep the env's reward, so results stay comparable
    dense_reward: bool = False
    # The exploration noise's color: its power spectrum ~ 1 / f^beta over an episode's steps, each step still N(0, 1)
    # times the policy's std (rl/colored_noise.py). 0: PPO's i.i.d. white noise; 0.5: colored noise in PPO (Hollenstein
    # et al., AAAI 2024); 1: pink noise. Only the sampled training actions change, never the deterministic policy.
    # The recipe's config sets 0.5; 0.5 against 0 on the weak expert, the operator mix and the near-optimal sets:
    # docs/RESULTS.md, "Colored exploration noise".
    noise_color_beta: float = 0.0
    timeout_s: float = WORKER_TIMEOUT_S  # a worker silent this long in a collect or evaluation is killed and replaced
    max_worker_failures: int = MAX_WORKER_FAILURES  # a worker failing this many calls in a row stops the run

    def __post_init__(self):
        if self.backend not in ROLLOUT_BACKENDS:
            raise ValueError(f"--rollout.backend={self.backend!r}: choose one of {ROLLOUT_BACKENDS}")
        if self.backend == "ray" and self.n_workers < 1:
            raise ValueError("--rollout.backend=ray runs the envs in actors: give --rollout.n_workers >= 1")
        if self.ray_address and self.backend != "ray":
            raise ValueError("--rollout.ray_address is for --rollout.backend=ray")
        if self.noise_color_beta < 0:
            raise ValueError(f"--rollout.noise_color_beta={self.noise_color_beta}: give 0 (white noise) or more")

    @property
    def n_envs(self) -> int:
        return max(self.n_workers, 1) * self.envs_per_worker

    @property
    def steps_per_iteration(self) -> int:  # env steps one PPO iteration collects; a run ends on a whole iteration
        return self.n_envs * self.steps_per_env


@dataclass
class FinetuneConfig:
    dataset: DemoDatasetConfig = field(default_factory=DemoDatasetConfig)
    env: EnvConfig = field(default_factory=lambda: LiftEnvConfig(obs_type="agent_pos"))
    # `--policy.path=<BC pretrained_model>` fine-tunes a checkpoint; `--policy.type=bcrl` starts from scratch.
    policy: PreTrainedConfig | None = None
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    rollout: RolloutConfig = field(default_factory=RolloutConfig)
    total_env_steps: int = 300_000  # 0: no training, only the final evaluation (the "BC only" baseline)
    bc_batch_size: int = 256  # demo minibatch size for the BC term
    # Torch threads of the learner's update, while the rollout workers wait for its weights (each worker process is
    # single-threaded; collect and update take turns). 1 keeps a run's bits the same on any number of cores; an image
    # run on a CPU leaves the other cores idle during its update, where the CNN's backward pass is most of its time.
    learner_threads: int = 1
    output_dir: Path | None = None
    resume: bool = False
    seed: int = 1000
    label: str | None = None  # method name in the report; default: BC / BC+RL / PPO from scratch
    eval_freq: int = 50_000  # env steps between periodic evaluations, on validation seeds (0: only the final one)
    eval_episodes: int = 10
    # The run's result (the final evaluation on the test seeds, `checkpoints/best`): "last", or "best_validation":
    # the policy of the periodic evaluation with the highest success rate, then return (the earliest of equals),
    # the starting policy included (evaluated before the first update), like robomimic's best-rollout checkpoints.
    select: str = "last"
    # With best_validation: the checkpoints whose validation tied the chosen one's success are evaluated on this many
    # further validation seeds at the end, and the best over all its validation episodes becomes the result (0: the
    # first choice stands). A fixed set of eval_episodes seeds can be solved by policies that fail elsewhere.
    reselect_episodes: int = 0
    final_eval_episodes: int = 50
    save_freq: int = 50_000  # env steps between checkpoints (and one at the end)
    # Log every evaluation episode to <output_dir>/eval_rrd/*.rrd: what happened, the policy's predicted
    # actions and values, and theta_t and the env step count at that evaluation (open with `rerun`).
    eval_rerun: bool = False
    tensorboard: bool = True  # also log to <output_dir>/tensorboard if tensorboard is installed
    wandb: bool = False

    def __post_init__(self):
        policy_path = parser.get_path_arg("policy")
        if policy_path:  # like lerobot-train: the checkpoint's config, with --policy.* overrides on top
            self.policy = PreTrainedConfig.from_pretrained(policy_path, cli_overrides=parser.get_cli_overrides("policy"))
            self.policy.pretrained_path = Path(policy_path)
        if self.output_dir is None:
            self.output_dir = Path("outputs/finetune") / time.strftime("%Y-%m-%d_%H-%M-%S")
        self.output_dir = Path(self.output_dir)

    @classmethod
    def __get_path_fields__(cls) -> list[str]:
        return ["policy"]

    def validate(self) -> None:
        """Refuse a run that cannot do what it says, before anything is written."""
        if self.policy is None:
            raise ValueError("give --policy.path=<BC pretrained_model> or --policy.type=bcrl (PPO from scratch)")
        if self.select not in SELECTIONS:
            raise ValueError(f"--select={self.select!r}: choose one of {SELECTIONS}")
        if self.select == "best_validation" and self.total_env_steps > 0 and not self.eval_freq:
            raise ValueError("--select=best_validation chooses among the periodic evaluations: give --eval_freq > 0")
        if self.reselect_episodes and self.select != "best_validation":
            raise ValueError("--reselect_episodes evaluates the candidates of --select=best_validation again: give both")
        if self.learner_threads < 1:
            raise ValueError(f"--learner_threads={self.learner_threads}: give 1 or more")
        if self.rollout.dense_reward and "dense_reward" not in self.env.gym_kwargs:
            raise ValueError(f"--rollout.dense_reward=true: env {self.env.type!r} has no dense reward to train on")
        checkpoints = self.output_dir / "checkpoints"
        if self.resume and not (checkpoints / "last").exists():
            raise FileNotFoundError(f"--resume=true but there is no checkpoint at {checkpoints / 'last'}")
        if not self.resume and checkpoints.exists():
            raise FileExistsError(f"{self.output_dir} already holds checkpoints: pass --resume=true or another --output_dir")

    @property
    def method(self) -> str:
        if self.label:
            return self.label
        if self.total_env_steps == 0:  # an evaluation: of a BC checkpoint, or of one fine-tuned by bcrl-finetune
            return "BC+RL" if self.policy.pretrained_path and policy_env_steps(self.policy.pretrained_path) else "BC"
        if not self.policy.pretrained_path:
            return "PPO from scratch"
        floor, target_kl = self.schedule.floor, self.ppo.target_kl
        return "BC+RL" + (f", theta_t >= {floor:g}" if floor > 0 else "") + (f", KL stop {target_kl:g}" if target_kl else "")
