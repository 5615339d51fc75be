"""`bcrl-eval-rig`: a policy trained on converted recordings, run closed-loop through the real robot's command path
(pybullet IK, joint and velocity limits, the watchdog) on the simulated rig's physics, at the dataset's fps.

Example:
    bcrl-eval-rig --policy_path=outputs/lab/bc/checkpoints/last/pretrained_model \\
        --urdf=../shared/robots/sawyer/sawyer.urdf --n_episodes=50 --output_dir=outputs/lab/eval_30hz
Scores per held-out start (cube placements no recording used): reached (tool within 2 cm of the cube centre at
some period), grasped (both finger pads on the cube at the end), lifted (the cube 4 cm above its start at the end).
The loop runs at the fps of the dataset the policy was trained on; `--run_fps`/`--command_fps` other than that are
refused unless `--allow_rate_mismatch=true` (to study what a mismatch does, as the paper met at 30 vs 20 Hz).
"""

import json
import logging
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import draccus
import numpy as np
from tqdm import tqdm

from lerobot_bcrl.features import ENV_STATE_DIM, IMAGES_PREFIX
from lerobot_bcrl.files import write_json_atomically
from lerobot_bcrl.robot.kinematics import KinematicsError

log = logging.getLogger(__name__)


class EvalRigSettingsError(ValueError):
    """Settings that cannot run (a one-line message for the CLI)."""


class RateMismatchError(EvalRigSettingsError):
    """A loop rate other than the dataset's, without `allow_rate_mismatch`."""


@dataclass
class EvalRigConfig:
    policy_path: Path = Path("pretrained_model")  # a lerobot-train checkpoint's pretrained_model folder
    urdf: Path | None = None  # the arm's URDF, for the command path's IK (required)
    dataset_root: Path | None = None  # where the training data is, for its fps; default: the checkpoint's record of it
    n_episodes: int = 50
    start_seed: int = 100_000  # episode i places the cube with seed start_seed + i; recordings use seeds from 0
    episode_s: float = 6.0
    run_fps: float | None = None  # how often the policy acts and each command holds; default: the dataset's fps
    command_fps: float | None = None  # the rate the command path scales velocities for; default: the dataset's fps
    allow_rate_mismatch: bool = False
    output_dir: Path = Path("outputs/eval_rig")
    device: str = "cpu"


def dataset_fps(policy_path: Path, dataset_root: Path | None) -> float:
    """The fps of the data the policy learnt from: `meta/info.json` of the dataset its `train_config.json` names."""
    if dataset_root is None:
        train_config = Path(policy_path) / "train_config.json"
        if not train_config.is_file():
            raise FileNotFoundError(f"{train_config}: not found; pass --dataset_root (the training data, for its fps)")
        root = json.loads(train_config.read_text())["dataset"].get("root")
        if root is None:
            raise FileNotFoundError(f"{train_config}: names no dataset root; pass --dataset_root")
        dataset_root = Path(root)
    info = Path(dataset_root) / "meta" / "info.json"
    if not info.is_file():
        raise FileNotFoundError(f"{info}: not found (the policy's training data); pass --dataset_root")
    return float(json.loads(info.read_text())["fps"])


def loop_rates(cfg: EvalRigConfig, fps: float) -> tuple[float, float]:
    """(run_fps, command_fps), both the dataset's fps unless a mismatch is asked for and allowed."""
    run_fps = cfg.run_fps or fps
    command_fps = cfg.command_fps or fps
    if (run_fps != fps or command_fps != fps) and not cfg.allow_rate_mismatch:
        raise RateMismatchError(
            f"{cfg.policy_path}: trained on {fps:g} fps data, asked to run at {run_fps:g} fps with commands for "
            f"{command_fps:g} fps; a policy must run at its dataset's fps (--allow_rate_mismatch=true to study it)"
        )
    return run_fps, command_fps


def policy_observation(rig, image_key: str | None) -> dict:
    """What the converter wrote for a recording, from the rig now: state, zero object state, the camera."""
    observation = {"agent_pos": rig.state().astype(np.float32), "environment_state": np.zeros(ENV_STATE_DIM, np.float32)}
    if image_key is not None:
        observation["pixels"] = {image_key.removeprefix(IMAGES_PREFIX): rig.render()}
    return observation


def run_episode(rig, runner, path, seed: int, n_periods: int, image_key: str | None) -> dict:
    rig.reset(seed)
    runner.reset()
    path.reset()
    start_s = rig.transport.time_s
    stops_before = path.stops
    velocity_limited = clamped = 0
    for _ in range(n_periods):
        observed_at_s = rig.transport.time_s
        command = path.step(runner.delta_action(policy_observation(rig, image_key)), observed_at_s)
        rig.update_scores()
        velocity_limited += int(command.velocity_limited)
        clamped += int(command.action_clamped)
    return {
        "seed": seed,
        "n_periods": n_periods,
        "duration_s": rig.transport.time_s - start_s,  # simulated time
        "reached": rig.reached,
        "grasped": rig.grasped,
        "lifted": rig.lifted,
        "closest_approach_m": rig.closest_approach_m,
        "watchdog_stops": path.stops - stops_before,
        "velocity_limited_periods": velocity_limited,
        "clamped_actions": clamped,
    }


def eval_rig(cfg: EvalRigConfig) -> dict:
    from lerobot_bcrl.policy_runner import PolicyRunner
    from lerobot_bcrl.robot.command import CommandConfig, DeltaActionCommander
    from lerobot_bcrl.robot.sim_rig import SimulatedLiftRig, sawyer_kinematics
    from lerobot_bcrl.robot.transport import GuardedCommandPath

    if cfg.n_episodes < 1:
        raise EvalRigSettingsError(f"n_episodes must be at least 1, got {cfg.n_episodes}")
    if cfg.urdf is None:
        raise EvalRigSettingsError("--urdf is required (the arm's URDF, for the command path's IK)")
    fps = dataset_fps(cfg.policy_path, cfg.dataset_root)
    run_fps, command_fps = loop_rates(cfg, fps)
    runner = PolicyRunner(str(cfg.policy_path), cfg.device)
    images = [key for key in runner.config.input_features if key.startswith(IMAGES_PREFIX)]
    image_key = images[0] if images else None
    image_size = runner.config.input_features[image_key].shape[-1] if image_key else None
    commander = DeltaActionCommander(sawyer_kinematics(cfg.urdf), CommandConfig(fps=command_fps))
    rig = SimulatedLiftRig(image_size=image_size)
    path = GuardedCommandPath(commander, rig.transport, clock=lambda: rig.transport.time_s, period_s=1.0 / run_fps)
    n_periods = int(round(cfg.episode_s * run_fps))
    episodes = []
    try:
        progress = tqdm(range(cfg.n_episodes), desc=f"bcrl-eval-rig {run_fps:g} Hz", unit="ep")
        for i in progress:
            episodes.append(run_episode(rig, runner, path, cfg.start_seed + i, n_periods, image_key))
            progress.set_postfix(reach=_mean(episodes, "reached"), grasp=_mean(episodes, "grasped"))
        n_velocity_limited = sum(e["velocity_limited_periods"] for e in episodes)
    finally:
        commander.kinematics.close()
        rig.close()
    result = {
        "aggregated": {
            **aggregate_outcomes(episodes),
            "watchdog_stops": int(sum(e["watchdog_stops"] for e in episodes)),
            "velocity_limited_fraction": n_velocity_limited / (n_periods * len(episodes)),
        },
        "rates": {"dataset_fps": fps, "run_fps": run_fps, "command_fps": command_fps},
        "per_episode": episodes,
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()},
    }
    write_json_atomically(Path(cfg.output_dir) / "eval_info.json", result)
    return result


def aggregate_outcomes(episodes: list[dict]) -> dict:
    """Success rates and the median closest approach over episodes scored by `SimulatedLiftRig` (policies here, the
    demonstrator in bcrl-make-demo-bags's outcomes.json)."""
    return {
        "n_episodes": len(episodes),
        **{f"{name}_success": _mean(episodes, name) for name in ("reached", "grasped", "lifted")},
        "median_closest_approach_m": float(np.median([e["closest_approach_m"] for e in episodes])),
    }


def _mean(episodes: list[dict], key: str) -> float:
    return float(np.mean([e[key] for e in episodes])) if episodes else 0.0


def main() -> None:
    logging.basicConfig(level=logging.INFO)
    cfg = draccus.parse(EvalRigConfig)
    try:
        result = eval_rig(cfg)
    except (EvalRigSettingsError, FileNotFoundError, KinematicsError) as err:
        sys.exit(f"bcrl-eval-rig: {err}")
    print(json.dumps({**result["aggregated"], **result["rates"]}))
    print(f"per-episode results: {Path(cfg.output_dir) / 'eval_info.json'}")


if __name__ == "__main__":
    main()
