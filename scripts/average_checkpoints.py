"""Average the weights of several checkpoints of one run (uniform; e.g. the last two or three of a BC+RL run)
into a new pretrained_model folder, with the processors and config of the last one given, so that
lerobot-eval, bcrl-finetune --total_env_steps=0 or scripts/diagnose_lift_episodes.py evaluate it.

    .venv/bin/python scripts/average_checkpoints.py --output=/tmp/avg_last2 \
        outputs/.../checkpoints/000089600/pretrained_model outputs/.../checkpoints/000102400/pretrained_model
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

WEIGHTS_FILE = "model.safetensors"


def average_state_dicts(states: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """The element-wise mean of floating-point tensors; any other tensor is taken from the last state."""
    keys = set(states[-1])
    for i, state in enumerate(states[:-1]):
        if set(state) != keys:
            raise ValueError(f"checkpoint {i} has other tensors than the last one: {sorted(set(state) ^ keys)[:5]}")
    return {key: torch.stack([s[key].float() for s in states]).mean(0).to(value.dtype) if value.is_floating_point()
            else value for key, value in states[-1].items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+", type=Path, help="pretrained_model folders of one run")
    parser.add_argument("--output", required=True, type=Path)
    args = parser.parse_args()
    for checkpoint in args.checkpoints:
        if not (checkpoint / WEIGHTS_FILE).is_file():
            raise FileNotFoundError(f"{checkpoint / WEIGHTS_FILE} does not exist: give pretrained_model folders")
    averaged = average_state_dicts([load_file(str(c / WEIGHTS_FILE)) for c in args.checkpoints])
    args.output.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{args.output.name}_", dir=args.output.parent))
    shutil.copytree(args.checkpoints[-1], tmp, dirs_exist_ok=True)
    save_file(averaged, str(tmp / WEIGHTS_FILE))
    if args.output.exists():
        shutil.rmtree(args.output)
    os.replace(tmp, args.output)
    print(f"{args.output}: the mean of {len(args.checkpoints)} checkpoints")


if __name__ == "__main__":
    main()
