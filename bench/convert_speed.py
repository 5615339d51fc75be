"""Benchmark of bcrl-convert (recorded seconds per wall second, with and without video) and of the IK
command path's memory over a long run; prints one JSON line per measurement.

Run: .venv/bin/python bench/convert_speed.py --n_episodes=2 --control_steps=120 --ik_calls=20000
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import draccus
import numpy as np

from dataset_tools.convert.cli import ConvertConfig, convert
from dataset_tools.make_demo_bags import MakeDemoBagsConfig, make_demo_bags
from lerobot_bcrl.robot.command import CommandConfig, DeltaActionCommander
from lerobot_bcrl.robot.sim_rig import sawyer_kinematics


@dataclass
class BenchConfig:
    urdf: Path = Path("/work/shared/robots/sawyer/sawyer.urdf")
    n_episodes: int = 2
    control_steps: int = 120  # 6 s of recording per episode
    camera_size: int = 128  # recorded camera resolution
    image_size: int = 128  # dataset resolution
    ik_calls: int = 20000


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def bench_convert(cfg: BenchConfig, tmp: Path) -> None:
    bags = make_demo_bags(MakeDemoBagsConfig(out_dir=tmp / "bags", n_episodes=cfg.n_episodes, control_steps=cfg.control_steps, image_size=cfg.camera_size))
    for fmt in ("ros1", "ros2"):
        for video in (False, True):
            root = tmp / f"ds_{fmt}_{video}"
            convert_cfg = ConvertConfig(
                input=tmp / "bags" / fmt, root=root, urdf=cfg.urdf, use_pose_topic=False, video=video, image_size=cfg.image_size,
                tool_offset_pos_m=list(GRIP_SITE_IN_RIGHT_HAND_POS_M), tool_offset_quat_xyzw=list(GRIP_SITE_IN_RIGHT_HAND_QUAT_XYZW),
            )  # fmt: skip
            start = time.perf_counter()
            _, rows = convert(convert_cfg)
            wall_s = time.perf_counter() - start
            recorded_s = sum(r["duration_s"] for r in rows)
            print(json.dumps({
                "bench": "convert", "format": fmt, "video": video, "episodes": len(bags[fmt]),
                "recorded_s": round(recorded_s, 2), "wall_s": round(wall_s, 2),
                "recorded_s_per_wall_s": round(recorded_s / wall_s, 2), "image_size": cfg.image_size,
            }), flush=True)  # fmt: skip


def bench_ik_memory(cfg: BenchConfig) -> None:
    rng = np.random.default_rng(0)
    start_qpos = np.array([0.0, -1.18, 0.0, 2.18, 0.0, 0.57, 3.3161])
    with sawyer_kinematics(cfg.urdf) as kin:
        commander = DeltaActionCommander(kin, CommandConfig(fps=30))
        action = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, -1.0])
        samples = []
        start = time.perf_counter()
        for i in range(cfg.ik_calls):
            action[:3] = rng.normal(0, 0.005, 3)
            commander.command(action, start_qpos + rng.normal(0, 0.05, 7))
            if i % (cfg.ik_calls // 10) == 0:
                samples.append(round(rss_mb(), 2))
        wall_s = time.perf_counter() - start
    print(json.dumps({
        "bench": "command_path_memory", "commands": cfg.ik_calls, "ms_per_command": round(1e3 * wall_s / cfg.ik_calls, 3),
        "rss_mb_samples": samples, "rss_growth_mb_after_first_10pct": round(samples[-1] - samples[1], 2),
    }), flush=True)  # fmt: skip


def main() -> None:
    cfg = draccus.parse(BenchConfig)
    with tempfile.TemporaryDirectory() as tmp:
        bench_convert(cfg, Path(tmp))
    bench_ik_memory(cfg)


if __name__ == "__main__":
    main()
