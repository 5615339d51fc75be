import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _isolated_lerobot_home(tmp_path, monkeypatch):
    """Nothing a test writes lands in the user's ~/.cache/huggingface."""
    monkeypatch.setenv("HF_LEROBOT_HOME", str(tmp_path / "hf_lerobot"))
