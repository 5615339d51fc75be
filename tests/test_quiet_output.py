"""Our processes keep robosuite's start-up advice out of their output and still show its errors."""

from __future__ import annotations

import os
import subprocess
import sys


def test_robosuite_start_up_chatter_is_silenced_but_its_errors_show():
    # A fresh interpreter: robosuite speaks once, when it is first imported.
    code = (
        "import lerobot_bcrl.envs.lift\n"
        "from robosuite.utils.log_utils import ROBOSUITE_DEFAULT_LOGGER\n"
        "ROBOSUITE_DEFAULT_LOGGER.error('a real error')\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                            env=os.environ.copy())
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-4000:]
    for chatter in ("private macro file", "robosuite_models", "mink-based whole-body IK"):
        assert chatter not in output, output[-4000:]
    assert "a real error" in output
