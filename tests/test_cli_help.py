"""`--help` of every console script in pyproject.toml, and of lerobot-train with our policy and env types.

draccus turns field comments into argparse help, so a stray `%` in a config's comment crashes `--help`.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # ~5 s per command (imports of torch and LeRobot)

BIN = Path(sys.executable).parent
SCRIPTS = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]["scripts"]
# A few options each help must name; a script missing here only has to print a usage line.
EXPECTED = {
    "bcrl-record": ["--repo_id", "--n_episodes", "--sigma", "--demonstrators"],
    "bcrl-summary": ["--root", "--json"],
    "bcrl-hub": ["push", "pull", "--kind", "--repo_id"],
    "bcrl-local-hub": ["--port", "--storage", "--token"],
    "bcrl-viz": ["--root", "--episode"],
    "bcrl-eval-offline": ["--policy.path", "--dataset.root", "--episodes"],
    "bcrl-finetune": ["--policy.path", "--total_env_steps", "--ppo.learning_rate", "--schedule.alpha"],
    "bcrl-report": ["--runs", "--output_dir"],
    "bcrl-convert": ["--input", "--root", "--fps"],
    "bcrl-make-demo-bags": ["--out_dir", "--n_episodes", "--formats"],
}


def run_help(*command: str) -> str:
    result = subprocess.run(list(command), capture_output=True, text=True, timeout=120, env=os.environ.copy())
    output = result.stdout + result.stderr
    assert result.returncode == 0, f"{' '.join(command)} exited {result.returncode}:\n{output[-4000:]}"
    assert "usage" in output.lower(), output[-4000:]
    return output


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_console_script_help(name):
    script = BIN / name
    assert script.exists(), f"{script} missing: reinstall the package (make setup)"
    module, function = SCRIPTS[name].split(":")
    assert re.search(rf"^from {re.escape(module)} import {function}$", script.read_text(), re.M), (
        f"{script} does not call {SCRIPTS[name]} (pyproject.toml's entry): reinstall the package (make setup)"
    )
    output = run_help(str(script), "--help")
    missing = [option for option in EXPECTED.get(name, []) if option not in output]
    assert not missing, f"{name} --help does not mention {missing}:\n{output[-4000:]}"


def test_lerobot_train_help_with_our_policy_and_env():
    """Our policy's and env's config comments become lerobot-train's help too."""
    output = run_help(str(BIN / "lerobot-train"), "--policy.type=bcrl", "--env.type=bcrl_lift", "--help")
    assert "--policy.observation_mode" in output and "--env.obs_type" in output
