"""bcrl-finetune's checkpoints: LeRobot's layout plus the run's counters, written atomically, and the result's choice.

`checkpoints/<env steps>/{pretrained_model,training_state}`; `checkpoints/last` is what `--resume=true` continues
from, `checkpoints/best` the policy `--select=best_validation` chose. `lerobot-eval --policy.path=...` loads either.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import draccus

from lerobot_bcrl.rl.schedule import ScheduleState

TRAINING_STEP_FILE = "training_step.json"
FINETUNE_CONFIG_NAME = "finetune_config.json"


def checkpoint_name(env_steps: int) -> str:
    return f"{env_steps:09d}"


def point_symlink(checkpoints_dir: Path, name: str, checkpoint_dir: Path) -> None:
    """`checkpoints/<name>` -> `<step>`, replaced atomically."""
    tmp_link = checkpoints_dir / f".{name}_tmp"
    tmp_link.unlink(missing_ok=True)
    tmp_link.symlink_to(checkpoint_dir.name)
    os.replace(tmp_link, checkpoints_dir / name)


def save_checkpoint(cfg, env_steps: int, agent, postprocessor, optimizer, schedule_state: ScheduleState,
                    reward_scaler=None, best: dict | None = None, validations: list[dict] = ()) -> Path:
    """Write `checkpoints/<env_steps>` through a temporary folder and point `last` at it. `best`: the validation
    evaluation that chose the result so far (`--select=best_validation`), and `validations` all of them so far, kept
    for a resume."""
    from lerobot.optim.optimizers import save_optimizer_state
    from lerobot.utils.random_utils import save_rng_state

    checkpoints_dir = cfg.output_dir / "checkpoints"
    final_dir = checkpoints_dir / checkpoint_name(env_steps)
    tmp_dir = checkpoints_dir / f".tmp_{checkpoint_name(env_steps)}"
    shutil.rmtree(tmp_dir, ignore_errors=True)
    pretrained_dir, state_dir = tmp_dir / "pretrained_model", tmp_dir / "training_state"
    agent.policy.save_pretrained(pretrained_dir)
    agent.preprocessor.save_pretrained(pretrained_dir)
    postprocessor.save_pretrained(pretrained_dir)
    with open(pretrained_dir / FINETUNE_CONFIG_NAME, "w") as f, draccus.config_type("json"):
        draccus.dump(cfg, f, indent=2)
    state_dir.mkdir(parents=True)
    save_optimizer_state(optimizer, state_dir)
    save_rng_state(state_dir)
    training_step = {"env_steps": env_steps, "optim_step": schedule_state.optim_step,
                     "ppo_iteration": schedule_state.ppo_iteration, "theta": schedule_state.theta(cfg.schedule),
                     "reward_scaler": reward_scaler.state_dict() if reward_scaler else None, "best": best,
                     "validations": list(validations)}
    (state_dir / TRAINING_STEP_FILE).write_text(json.dumps(training_step, indent=2))
    if final_dir.exists():
        shutil.rmtree(final_dir)
    os.replace(tmp_dir, final_dir)
    point_symlink(checkpoints_dir, "last", final_dir)
    return final_dir


def load_training_state(checkpoint_dir: Path, optimizer) -> dict:
    """Restore the optimizer and the RNGs from a checkpoint; return its `training_step.json`."""
    from lerobot.optim.optimizers import load_optimizer_state
    from lerobot.utils.random_utils import load_rng_state

    state_dir = checkpoint_dir / "training_state"
    load_optimizer_state(optimizer, state_dir)
    load_rng_state(state_dir)
    return json.loads((state_dir / TRAINING_STEP_FILE).read_text())


def better_on_validation(candidate: dict, best: dict | None) -> bool:
    """Higher success rate, then higher return; on a tie the earlier policy stays."""
    return best is None or (candidate["success"], candidate["return"]) > (best["success"], best["return"])


def policy_env_steps(pretrained_path: str | Path | None) -> int:
    """Env steps of fine-tuning behind a policy: those of the bcrl-finetune checkpoint it was saved in, else 0
    (a lerobot-train checkpoint's training state counts optimisation steps, not env steps)."""
    if pretrained_path is None:
        return 0
    step_file = Path(pretrained_path).parent / "training_state" / TRAINING_STEP_FILE
    if not step_file.exists():
        return 0
    return int(json.loads(step_file.read_text()).get("env_steps", 0))
