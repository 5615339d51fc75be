import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
# Ray started by a test stays on loopback (Ray resolves 127.0.0.1 to the machine's address while multi-node is on)
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")

import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _isolated_lerobot_home(tmp_path, monkeypatch):
    """Nothing a test writes lands in the user's ~/.cache/huggingface."""
    monkeypatch.setenv("HF_LEROBOT_HOME", str(tmp_path / "hf_lerobot"))
