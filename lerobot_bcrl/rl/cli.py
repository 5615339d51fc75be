"""`bcrl-finetune`: BC+RL (or PPO from scratch, or "BC only" with --total_env_steps=0) from the command line,
ending with a short summary of the result and where it was written."""

import logging
import math
import os

from lerobot.configs import parser

from lerobot_bcrl.rl.configuration import FinetuneConfig
from lerobot_bcrl.rl.ppo import finetune


@parser.wrap()
def finetune_cli(cfg: FinetuneConfig) -> None:
    result = finetune(cfg)
    interval = "" if math.isnan(result["eval_return_ci95"]) else f" +/- {result['eval_return_ci95']:.1f} (95 % CI)"
    lift = "" if math.isnan(result["eval_steps_to_lift"]) else f", steps to lift {result['eval_steps_to_lift']:.1f}"
    lines = [
        f"\nbcrl-finetune ({result['method']}): {result['env_steps']} env steps, {result['optim_step']} optimisation"
        f" steps, theta_t = {result['theta']:.4f}, {result['wall_s']:.0f} s",
        f"  final evaluation over {result['eval_episodes']} episodes: return {result['eval_return']:.1f}{interval},"
        f" success {100 * result['eval_success']:.0f} %{lift}",
    ]
    if result["validation"]:
        chosen = result["validation"]
        lines.append(f"  the policy at {result['selected_env_steps']} env steps, chosen on {chosen['episodes']} validation"
                     f" episodes (success {100 * chosen['success']:.0f} %, return {chosen['return']:.1f})"
                     + (f" among the {len(chosen['candidates'])} that tied on the first {cfg.eval_episodes}"
                        if "candidates" in chosen else ""))
    checkpoint = "best" if result["validation"] else "last"
    lines += [f"  checkpoint: {cfg.output_dir / 'checkpoints' / checkpoint / 'pretrained_model'}",
              f"  logs: {cfg.output_dir / 'logs.csv'}; evaluation: {cfg.output_dir / 'eval_final.json'}"]
    print("\n".join(lines))


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    os.environ.setdefault("MUJOCO_GL", "egl")
    finetune_cli()


if __name__ == "__main__":
    main()
