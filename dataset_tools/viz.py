"""`bcrl-viz`: look at one episode of a Lift dataset in rerun (images, state, actions as 3D arrows).

    bcrl-viz --repo_id=local/lift_sigma0.1 --root=data/lift_sigma0.1 --episode=3 --save=episode3.rrd
    rerun episode3.rrd
Without `--save` it spawns a rerun viewer (needs a display).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import draccus
from tqdm import tqdm

from dataset_tools.writer import default_root
from lerobot_bcrl.rerun_log import EpisodeLogger


@dataclass
class VizConfig:
    repo_id: str = "local/bcrl_lift"
    root: Path | None = None  # default $HF_LEROBOT_HOME/<repo_id>
    episode: int = 0
    save: Path | None = None  # write an .rrd file instead of spawning a viewer
    video_backend: str | None = None  # "pyav", "torchcodec" or "bcrl_frame_cache"; LeRobot's default when unset


def visualize_episode(cfg: VizConfig) -> Path | None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = Path(cfg.root) if cfg.root is not None else default_root(cfg.repo_id)
    dataset = LeRobotDataset(cfg.repo_id, root=root, episodes=[cfg.episode], video_backend=cfg.video_backend)
    if cfg.episode >= dataset.meta.total_episodes or cfg.episode < 0:
        raise SystemExit(f"bcrl-viz: {root} has episodes 0..{dataset.meta.total_episodes - 1}, not {cfg.episode}")
    logger = EpisodeLogger(f"{cfg.repo_id}/episode_{cfg.episode}", save_path=cfg.save, spawn=cfg.save is None, fps=dataset.fps)
    for i in tqdm(range(len(dataset)), desc=f"logging episode {cfg.episode}", unit="frame"):
        frame = dataset[i]
        logger.log_step(int(frame["frame_index"]), frame)
    logger.close()
    return cfg.save


def main() -> None:
    cfg = draccus.parse(VizConfig)
    saved = visualize_episode(cfg)
    if saved is not None:
        print(f"wrote {saved}; open it with: rerun {saved}")


if __name__ == "__main__":
    main()
