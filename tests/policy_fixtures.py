"""Tiny Lift datasets for the policy tests, recorded once per test session with the scripted expert.

Import the fixtures into a test module (`from policy_fixtures import lowdim_dataset_root`).
"""

from __future__ import annotations

from pathlib import Path

import pytest


def record_tiny_dataset(root: Path, images: bool, n_episodes: int, episode_length: int) -> Path:
    from dataset_tools.record import RecordConfig, record

    cfg = RecordConfig(
        repo_id=f"local/{root.name}",
        root=root,
        n_episodes=n_episodes,
        episode_length=episode_length,
        sigma=0.1,
        images=images,
        video=False,  # PNG frames: no video decoding in the tests
    )
    return record(cfg)


@pytest.fixture(scope="session")
def lowdim_dataset_root(tmp_path_factory) -> Path:
    """Two low-dim episodes of 50 steps (the expert closes the gripper after ~30 steps)."""
    return record_tiny_dataset(tmp_path_factory.mktemp("data") / "lowdim", False, 2, 50)


@pytest.fixture(scope="session")
def image_dataset_root(tmp_path_factory) -> Path:
    """One 128x128 image episode of 20 steps."""
    return record_tiny_dataset(tmp_path_factory.mktemp("data") / "images", True, 1, 20)


def load_dataset(root: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(f"local/{root.name}", root=root)


def make_bcrl_policy(dataset, **config_overrides):
    """A `bcrl` policy and its processors built the way lerobot-train builds them."""
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig

    cfg = BCRLConfig(device="cpu", push_to_hub=False, **config_overrides)
    policy = make_policy(cfg, ds_meta=dataset.meta)
    preprocessor, postprocessor = make_pre_post_processors(cfg, dataset_stats=dataset.meta.stats)
    return policy, preprocessor, postprocessor


def whole_dataset_batch(dataset) -> dict:
    import torch

    return next(iter(torch.utils.data.DataLoader(dataset, batch_size=len(dataset), shuffle=False)))


def save_untrained_checkpoint(dataset_root: Path, checkpoint: Path):
    """A fresh `bcrl` policy for the dataset, saved in LeRobot's pretrained_model layout; returns the trio."""
    policy, preprocessor, postprocessor = make_bcrl_policy(load_dataset(dataset_root))
    for part in (policy, preprocessor, postprocessor):
        part.save_pretrained(checkpoint)
    return policy, preprocessor, postprocessor
