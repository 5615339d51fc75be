"""`bcrl-summary`: what a Lift dataset holds (episodes, success rate, returns, per demonstrator).

Example: bcrl-summary --root=data/lift_sigma0.1
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import draccus
import pandas as pd

from dataset_tools.writer import default_root, read_bcrl_meta
from lerobot_bcrl.stats import mean_ci95


def load_episode_table(root: Path) -> pd.DataFrame:
    paths = sorted((Path(root) / "meta" / "episodes").rglob("*.parquet"))
    if not paths:
        raise FileNotFoundError(f"{root}: no meta/episodes/*.parquet; is this a LeRobotDataset v3 folder?")
    table = pd.concat([pd.read_parquet(p) for p in paths], ignore_index=True)
    return table[[c for c in table.columns if not c.startswith(("stats/", "videos/", "data/", "meta/"))]]


def summarize(root: Path) -> dict:
    root = Path(root)
    info = json.loads((root / "meta" / "info.json").read_text())
    episodes = load_episode_table(root)
    summary = {
        "root": str(root),
        "codebase_version": info.get("codebase_version"),
        "fps": info["fps"],
        "episodes": int(info["total_episodes"]),
        "frames": int(info["total_frames"]),
        "features": sorted(info["features"]),
    }
    if "episode_return" in episodes:
        mean, ci = mean_ci95(episodes["episode_return"])
        lifted = episodes.loc[episodes["steps_to_lift"] >= 0, "steps_to_lift"]
        summary.update(
            success_rate=float(episodes["success"].mean()),
            mean_return=mean,
            return_ci95=ci,
            mean_steps_to_lift=float(lifted.mean()) if len(lifted) else None,
            by_demonstrator=[
                {
                    "demonstrator_id": int(d),
                    "noise_std": float(group["noise_std"].iloc[0]),
                    "episodes": len(group),
                    "success_rate": float(group["success"].mean()),
                    "mean_return": float(group["episode_return"].mean()),
                }
                for d, group in episodes.groupby("demonstrator_id")
            ],
        )
    if "planned_miss" in episodes and episodes["planned_miss"].any():
        planned_miss = episodes["planned_miss"].astype(bool)
        misses = episodes[planned_miss]
        summary.update(
            planned_miss_episodes=len(misses),
            planned_miss_success_rate=float(misses["success"].mean()),
            frames_not_imitated=int(episodes["n_frames_not_imitated"].sum()),
        )
        if "episode_return" in episodes:  # the demonstrators' own return: docs/RESULTS.md's figure for these sets
            first_try_mean, first_try_ci = mean_ci95(episodes.loc[~planned_miss, "episode_return"])
            summary.update(first_try_episodes=int((~planned_miss).sum()), first_try_mean_return=first_try_mean,
                           first_try_return_ci95=first_try_ci)
    meta = read_bcrl_meta(root)
    if meta:
        summary["made_by"] = meta.get("command")
    return summary


def print_summary(summary: dict, root: Path | None = None) -> None:
    print(f"dataset: {summary['root']} (LeRobotDataset {summary['codebase_version']}, {summary['fps']} fps)")
    print(f"  episodes: {summary['episodes']}   frames: {summary['frames']}")
    print(f"  features: {', '.join(summary['features'])}")
    if "success_rate" in summary:
        print(f"  success rate: {summary['success_rate']:.0%}")
        if math.isnan(summary["return_ci95"]):  # a single episode has no interval
            print(f"  return: {summary['mean_return']:.1f} (max 450)")
        else:
            print(f"  mean return: {summary['mean_return']:.1f} +/- {summary['return_ci95']:.1f} (95% CI; max 450)")
        if summary["mean_steps_to_lift"] is not None:
            print(f"  mean steps to lift (successful episodes): {summary['mean_steps_to_lift']:.1f}")
        if len(summary["by_demonstrator"]) > 1:
            for d in summary["by_demonstrator"]:
                print(
                    f"    demonstrator {d['demonstrator_id']}: sigma={d['noise_std']:.3f} episodes={d['episodes']}"
                    f" success={d['success_rate']:.0%} return={d['mean_return']:.1f}"
                )
    if summary.get("planned_miss_episodes"):
        print(
            f"  planned misses: {summary['planned_miss_episodes']} episodes (then retried:"
            f" {summary['planned_miss_success_rate']:.0%} lifted), {summary['frames_not_imitated']} frames not imitated"
        )
        if summary.get("first_try_episodes"):
            print(f"  without a planned miss: {summary['first_try_episodes']} episodes, return"
                  f" {summary['first_try_mean_return']:.1f} +/- {summary['first_try_return_ci95']:.1f} (95% CI)")
    if summary.get("made_by"):
        print(f"  made by: {summary['made_by']}")


@dataclass
class SummaryConfig:
    repo_id: str = "local/bcrl_lift"
    root: Path | None = None  # default $HF_LEROBOT_HOME/<repo_id>
    json: bool = False  # print one JSON line instead of text


def main() -> None:
    cfg = draccus.parse(SummaryConfig)
    summary = summarize(cfg.root if cfg.root is not None else default_root(cfg.repo_id))
    if cfg.json:
        print(json.dumps(summary))
    else:
        print_summary(summary)


if __name__ == "__main__":
    main()
