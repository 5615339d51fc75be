"""The one LeRobotDataset v3 writer every source funnels into (simulated experts, bags, HDF5).

It checks each episode before writing, derives the auxiliary labels, writes into a temporary folder and
moves the finished dataset into place only when everything succeeded, so that an interrupted or failed
run never leaves a half dataset behind.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd

from lerobot_bcrl import features as F
from lerobot_bcrl.geometry import GRIPPER_CLOSED

BCRL_META_FILE = "meta/bcrl.json"  # how the dataset was made (command, demonstrators, fps, layout)


class BadEpisodeError(ValueError):
    """An episode that must not be written; the message names the source, episode and frame."""


def default_root(repo_id: str) -> Path:
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return Path(HF_LEROBOT_HOME) / repo_id


@contextlib.contextmanager
def atomic_dataset_dir(root: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to `root` (which must not exist yet); rename it to `root` on success."""
    root = Path(root)
    if root.exists() and not overwrite:
        raise FileExistsError(f"{root} already exists; pass --overwrite=true to replace it")
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp_root = root.parent / f".{root.name}.incomplete-{os.getpid()}"
    shutil.rmtree(tmp_root, ignore_errors=True)
    try:
        yield tmp_root
    except BaseException:
        shutil.rmtree(tmp_root, ignore_errors=True)
        raise
    if root.exists():
        shutil.rmtree(root)
    os.replace(tmp_root, root)


def aux_labels(
    eef_pos: np.ndarray, gripper: np.ndarray, imitate: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Grasp position: the EEF position where the gripper first starts closing, for every frame.

    A closing that starts on a planned-mistake frame (`imitate` False: a first grasp missed on purpose) is
    not the grasp; the next one is. Returns `(grasp_pos (T, 3), grasp_valid (T, 1))`; an episode with no
    grasp gets its last EEF position and `grasp_valid = False`, so the loss can mask it.
    """
    closed = np.asarray(gripper).reshape(-1) >= GRIPPER_CLOSED
    onsets = np.flatnonzero(closed & ~np.concatenate([[False], closed[:-1]]))
    if imitate is not None:
        onsets = onsets[np.asarray(imitate).reshape(-1)[onsets]]
    valid = onsets.size > 0
    grasp = eef_pos[onsets[0]] if valid else eef_pos[-1]
    n = len(eef_pos)
    return np.tile(grasp.astype(np.float32), (n, 1)), np.full((n, 1), valid)


def check_episode(frames: dict[str, np.ndarray], source: str, episode_index: int) -> None:
    """Reject NaNs, infinities, bad quaternions and too-short episodes, naming the frame."""
    n = len(frames[F.ACTION_KEY])
    if n < 2:
        raise BadEpisodeError(f"{source}: episode {episode_index} has {n} frame(s); at least 2 are needed")
    for key, values in frames.items():
        if len(values) != n:
            raise BadEpisodeError(
                f"{source}: episode {episode_index}: '{key}' has {len(values)} frames, action has {n}"
            )
        if np.issubdtype(np.asarray(values).dtype, np.floating):
            bad = ~np.isfinite(np.asarray(values).reshape(n, -1)).all(axis=1)
            if bad.any():
                raise BadEpisodeError(
                    f"{source}: episode {episode_index}, frame {int(np.argmax(bad))}: non-finite value in '{key}'"
                )
    quat_norm = np.linalg.norm(frames[F.ACTION_KEY][:, 3:7], axis=1)
    bad = np.abs(quat_norm - 1.0) > 1e-3
    if bad.any():
        frame = int(np.argmax(bad))
        raise BadEpisodeError(
            f"{source}: episode {episode_index}, frame {frame}: action quaternion has norm {quat_norm[frame]:.4f}"
        )


def write_episode(dataset, frames: dict[str, np.ndarray], task: str, source: str) -> None:
    """Add one whole episode (every feature as a (T, ...) array, aux grasp labels derived) and save it.

    `aux.imitate` defaults to True on every frame (no planned mistakes).
    """
    frames = dict(frames)
    frames.setdefault(F.AUX_IMITATE_KEY, np.ones((len(frames[F.ACTION_KEY]), 1), dtype=bool))
    grasp_pos, grasp_valid = aux_labels(
        frames[F.AUX_EEF_POS_KEY], frames[F.ACTION_KEY][:, 7], frames[F.AUX_IMITATE_KEY]
    )
    frames[F.AUX_GRASP_POS_KEY] = grasp_pos
    frames[F.AUX_GRASP_VALID_KEY] = grasp_valid
    check_episode(frames, source, dataset.meta.total_episodes)
    for t in range(len(frames[F.ACTION_KEY])):
        frame = {key: _cast(values[t], dataset.features[key]) for key, values in frames.items()}
        frame["task"] = task
        dataset.add_frame(frame)
    with _no_datasets_progress_bars():
        dataset.save_episode()


@contextlib.contextmanager
def _no_datasets_progress_bars() -> Iterator[None]:
    """LeRobot's save_episode runs a `datasets` map with its own bar; once per episode, it breaks our tqdm line."""
    from datasets.utils import logging as datasets_logging

    was_enabled = datasets_logging.is_progress_bar_enabled()
    datasets_logging.disable_progress_bar()
    try:
        yield
    finally:
        if was_enabled:
            datasets_logging.enable_progress_bar()


def _cast(value, feature: dict):
    if feature["dtype"] in ("image", "video"):
        return np.asarray(value, dtype=np.uint8)
    return np.asarray(value, dtype=np.dtype(feature["dtype"])).reshape(feature["shape"])


def add_episode_columns(root: Path, rows: list[dict]) -> None:
    """Append our per-episode metadata (return, success, sigma, ...) as columns of meta/episodes/*.parquet."""
    extra = pd.DataFrame(rows).set_index("episode_index")
    for path in sorted((Path(root) / "meta" / "episodes").rglob("*.parquet")):
        episodes = pd.read_parquet(path)
        joined = episodes.join(extra, on="episode_index")
        if joined[extra.columns].isna().any().any():
            missing = joined.loc[joined[extra.columns].isna().any(axis=1), "episode_index"].tolist()
            raise ValueError(f"{path}: no metadata given for episodes {missing}")
        joined.to_parquet(path, index=False)


def write_bcrl_meta(root: Path, meta: dict) -> None:
    path = Path(root) / BCRL_META_FILE
    path.write_text(json.dumps(meta, indent=2, default=str) + "\n")


def read_bcrl_meta(root: Path) -> dict:
    path = Path(root) / BCRL_META_FILE
    return json.loads(path.read_text()) if path.exists() else {}
