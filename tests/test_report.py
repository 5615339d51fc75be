"""bcrl-report: Tables 1-2 from finished runs (values recomputed from the episodes), Wilson intervals, plots."""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from policy_fixtures import lowdim_dataset_root  # noqa: F401

from dataset_tools.report import (ReportConfig, demonstrators, plot_label, report, steps_lost_after_lift, trailing_mean,
                                  wilson_ci95)
from lerobot_bcrl.features import LIFT_REWARD
from lerobot_bcrl.rl.logger import LOG_COLUMNS, TIME_COLUMNS
from lerobot_bcrl.rl.rollout import EpisodeStats


def episode_dicts(returns: list[float]) -> list[dict]:
    return [{"episode_return": r, "length": 200, "success": r > 0, "steps_to_lift": 50 if r > 0 else None, "seed": i}
            for i, r in enumerate(returns)]


def fake_run(run_dir: Path, dataset_root: Path, method: str, returns: list[float], env_steps: int,
             policy_env_steps: int = 0, seed: int | None = 1000,
             policy_path: Path | None = None) -> Path:
    run_dir.mkdir(parents=True)
    result = {"method": method, "env_steps": env_steps, "dataset_root": str(dataset_root),
              "dataset_repo_id": f"local/{dataset_root.name}", "episodes": episode_dicts(returns),
              "policy_env_steps": policy_env_steps, "seed": seed, "policy_path": str(policy_path) if policy_path else None}
    (run_dir / "eval_final.json").write_text(json.dumps(result))
    with (run_dir / "logs.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, LOG_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for i in range(1, 6):
            writer.writerow({"env_steps": 512 * i, "theta": 1 - i / 10, "train_return": 10 * i, "train_success": 0.5,
                             "eval_return": 20 * i if i % 2 == 0 else "", "bc_loss": 1 / i})
    return run_dir


def test_report_tables_recompute_returns_recovered_share_and_wilson_intervals(lowdim_dataset_root, tmp_path):
    bc = fake_run(tmp_path / "bc", lowdim_dataset_root, "BC", [100.0, 0.0, 200.0, 100.0], 0)
    bcrl = fake_run(tmp_path / "bcrl", lowdim_dataset_root, "BC+RL", [300.0, 300.0, 0.0, 300.0], 2560)
    # an evaluation-only run (--total_env_steps=0) of a checkpoint fine-tuned for 1024 env steps
    evaluated = fake_run(tmp_path / "evaluated", lowdim_dataset_root, "BC+RL (checkpoint)", [300.0], 0,
                         policy_env_steps=1024)
    result = report(ReportConfig(runs=[str(bc), str(bcrl), str(evaluated)], output_dir=tmp_path / "report", smooth=3))

    rows = {r["method"]: r for r in result["rows"]}
    assert rows["BC"]["return"] == pytest.approx(100.0) and rows["BC+RL"]["return"] == pytest.approx(225.0)
    assert [rows[m]["env_steps"] for m in ("BC", "BC+RL", "BC+RL (checkpoint)")] == [0, 2560, 1024]
    demo = rows["BC"]["demo_return"]
    assert demo > 0 and rows["BC+RL"]["recovered_pct"] == pytest.approx(100 * 225.0 / demo)
    assert rows["BC"]["success"] == 0.75 and rows["BC"]["success_ci95"] == pytest.approx(wilson_ci95(3, 4))
    low, high = wilson_ci95(3, 4)
    assert 0.2 < low < 0.75 < high < 1.0  # Wilson: inside [0, 1], around the rate
    assert wilson_ci95(0, 50)[0] == pytest.approx(0.0, abs=1e-12) and wilson_ci95(0, 50)[1] > 0.05
    tables = (tmp_path / "report" / "report.md").read_text()
    assert "| BC | BC+RL |" in tables and f"{100 * 225.0 / demo:.0f} %" in tables
    bcrl_line = next(line for line in tables.splitlines() if "| BC+RL |" in line and "`" in line)
    low, high = wilson_ci95(3, 4)
    assert f"| 75 % ({100 * low:.0f}-{100 * high:.0f}) |" in bcrl_line
    for name in ("return_success.png", "bc_terms.png", "theta_ppo.png"):
        assert (tmp_path / "report" / name).stat().st_size > 10_000, name


def write_timed_log(run: Path, env_steps: list[int], timed_from: int) -> dict[str, float]:
    """logs.csv with rows at env_steps, each from index timed_from on timing its parts; the seconds per row."""
    seconds = dict(collect_s=3.0, learn_s=4.0, simulation_s=2.0, rendering_s=0.5, policy_s=1.0, learner_data_s=0.1,
                   bc_term_s=0.2, update_s=0.3)
    with (run / "logs.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, LOG_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for i, steps in enumerate(env_steps):
            writer.writerow({"env_steps": steps, "eval_return": 5, **(seconds if i >= timed_from else {})})
    return seconds


def time_cells(tables: str, run: Path) -> dict[str, float]:
    (line,) = [line for line in tables.split("Where the time goes")[1].splitlines() if f"`{run}`" in line]
    cells = [c.strip() for c in line.split("|")[1:-1]]
    return {"seed": cells[1], **{key: float(cell) for key, cell in zip(TIME_COLUMNS, cells[2:-1], strict=True)}}


def test_where_the_time_goes_is_per_thousand_env_steps_of_the_timed_iterations(lowdim_dataset_root, tmp_path):
    # 5 iterations of 512 env steps after the starting policy's untimed validation at 0
    full = fake_run(tmp_path / "full", lowdim_dataset_root, "BC+RL", [300.0], 2560)
    seconds = write_timed_log(full, [0, 512, 1024, 1536, 2048, 2560], timed_from=1)
    # runs resumed from older logs whose rows before the checkpoint predate the timings: three timed iterations,
    # and one (its env_steps, 1536, is not its iteration's steps)
    resumed = fake_run(tmp_path / "resumed", lowdim_dataset_root, "BC+RL", [300.0], 2560, seed=None)
    write_timed_log(resumed, [0, 512, 1024, 1536, 2048, 2560], timed_from=3)
    single = fake_run(tmp_path / "single", lowdim_dataset_root, "BC+RL", [300.0], 1536)
    write_timed_log(single, [0, 512, 1024, 1536], timed_from=3)
    bc = fake_run(tmp_path / "bc", lowdim_dataset_root, "BC", [100.0], 0)  # logs without timings: no row
    tables = report(ReportConfig(runs=[str(full), str(resumed), str(single), str(bc)],
                                 output_dir=tmp_path / "report"))["tables"]
    for run in (full, resumed, single):  # every part, each run: its seconds per iteration over 512 env steps
        cells = time_cells(tables, run)
        for key, per_iteration in seconds.items():
            assert cells[key] == pytest.approx(1000 / 512 * per_iteration, abs=0.01), (run.name, key)
    assert time_cells(tables, full)["seed"] == "1000" and time_cells(tables, resumed)["seed"] == "-"
    assert f"`{bc}`" not in tables.split("Where the time goes")[1]


def test_runs_on_one_dataset_share_a_row_however_its_root_was_spelled(lowdim_dataset_root, tmp_path, monkeypatch):
    monkeypatch.chdir(lowdim_dataset_root.parent)
    bc = fake_run(tmp_path / "bc", Path(lowdim_dataset_root.name), "BC", [100.0, 0.0], 0)  # relative, as typed
    bcrl = fake_run(tmp_path / "bcrl", lowdim_dataset_root, "BC+RL", [300.0, 0.0], 2560)  # absolute
    result = report(ReportConfig(runs=[str(bc), str(bcrl)], output_dir=tmp_path / "report"))
    assert {r["dataset_root"] for r in result["rows"]} == {str(lowdim_dataset_root.resolve())}
    table_1 = (tmp_path / "report" / "report.md").read_text().split("Table 2")[0]
    assert len([line for line in table_1.splitlines() if line.startswith("| 0")]) == 1, table_1


def table(tables: str, title: str) -> list[str]:
    """The lines of one markdown table of report.md, from its title to the blank line after it."""
    lines = tables.split(title, 1)[1].split("\n\n")[1].splitlines()
    assert lines[0].startswith("|"), lines
    return lines


def test_seeds_share_a_cell_and_budgets_get_their_own_columns(lowdim_dataset_root, tmp_path):
    runs = [fake_run(tmp_path / "bc", lowdim_dataset_root, "BC", [100.0, 100.0, 0.0, 100.0], 0),
            # two training seeds at 102k: one cell with their mean, not the last one read
            fake_run(tmp_path / "seed1", lowdim_dataset_root, "BC+RL", [300.0, 300.0, 300.0, 300.0], 102400, seed=1),
            fake_run(tmp_path / "seed2", lowdim_dataset_root, "BC+RL", [200.0, 200.0, 0.0, 0.0], 102400, seed=2),
            # the same method at another budget: its own column
            fake_run(tmp_path / "long", lowdim_dataset_root, "BC+RL", [250.0, 250.0, 250.0, 0.0], 297600, seed=1)]
    result = report(ReportConfig(runs=[str(r) for r in runs], output_dir=tmp_path / "report"))
    tables = result["tables"]
    header, _, row = table(tables, "Table 1")
    assert header == "| sigma | demonstrators | BC | BC+RL, 102.4k | BC+RL, 297.6k |"
    seed_means = [300.0, 100.0]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[3] == f"{np.mean(seed_means):.1f} (sd {np.std(seed_means, ddof=1):.1f}, 2 runs)"
    assert cells[2].startswith("75.0 +/- ") and cells[4].startswith("187.5 +/- ")  # one run each: its own CI
    demo = result["rows"][0]["demo_return"]
    _, _, recovered = table(tables, "Table 2")
    low, high = sorted(100 * m / demo for m in seed_means)
    assert f"| {100 * np.mean(seed_means) / demo:.0f} % ({low:.0f}-{high:.0f}) |" in recovered
    _, _, success = table(tables, "Table 3")
    low, high = wilson_ci95(3, 4)
    one_run = f"75 % ({100 * low:.0f}-{100 * high:.0f})"
    assert [c.strip() for c in success.strip("|").split("|")][2:] == [one_run, "75 % (runs: 100, 50)", one_run]
    cell = next(c for c in result["cells"] if c["column"] == "BC+RL, 102.4k")
    assert cell["runs"] == 2 and cell["seeds"] == [1, 2] and cell["return"] == pytest.approx(200.0)
    saved = json.loads((tmp_path / "report" / "report.json").read_text())
    assert len(saved["runs"]) == 4 and len(saved["cells"]) == 3
    details = table(tables, "Details")
    assert sum("| BC+RL | 102400 |" in line for line in details) == 2  # every run still listed, with its seed
    assert any("| BC+RL | 102400 | 2 |" in line for line in details)


def test_demonstrators_leave_out_planned_misses_and_a_mix_shows_its_noise_range(lowdim_dataset_root, tmp_path):
    import shutil

    import pandas as pd

    root = tmp_path / "with_misses"
    shutil.copytree(lowdim_dataset_root, root)
    (path,) = sorted((root / "meta" / "episodes").rglob("*.parquet"))
    episodes = pd.read_parquet(path)
    assert len(episodes) >= 2
    all_episodes = demonstrators("local/with_misses", str(root))
    assert all_episodes["demo_return"] == pytest.approx(episodes["episode_return"].mean())
    episodes["planned_miss"] = [True] + [False] * (len(episodes) - 1)
    episodes.loc[0, "episode_return"] = -1000.0  # a miss's return must not pull the bar down
    episodes.to_parquet(path, index=False)
    demo = demonstrators("local/with_misses", str(root))
    assert demo["demo_episodes"] == len(episodes) - 1
    assert demo["demo_return"] == pytest.approx(episodes["episode_return"][1:].mean())
    episodes["planned_miss"] = True  # nothing else to compare with: every episode counts
    episodes.to_parquet(path, index=False)
    assert demonstrators("local/with_misses", str(root))["demo_episodes"] == len(episodes)
    # several demonstrators of different noise: the row names their range, not the mean
    episodes["noise_std"] = [0.02] + [0.1] * (len(episodes) - 1)
    episodes.to_parquet(path, index=False)
    assert demonstrators("local/with_misses", str(root))["sigma_label"] == "0.02-0.1 (mix)"


def test_trailing_mean_matches_a_loop():
    values = np.random.default_rng(0).normal(size=37)
    expected = [values[max(0, i - 4) : i + 1].mean() for i in range(len(values))]
    np.testing.assert_allclose(trailing_mean(values, 5), expected)
    np.testing.assert_array_equal(trailing_mean(values, 1), values)


def test_episode_stats_count_lifted_steps_after_the_first_lift():
    stats = EpisodeStats(0.0, 0, False, None)
    for lifted in [False, True, True, False, False, True]:  # lifted at step 2, lost at 4-5, lifted again at 6
        stats.record_step(LIFT_REWARD if lifted else 0.0, {"is_success": lifted})
    assert (stats.length, stats.steps_to_lift, stats.lifted_steps) == (6, 2, 3)
    assert stats.success and stats.episode_return == pytest.approx(3 * LIFT_REWARD)
    assert steps_lost_after_lift(asdict(stats)) == 2  # steps 4 and 5
    never = EpisodeStats(0.0, 0, False, None)
    never.record_step(0.0, {})
    assert steps_lost_after_lift(asdict(never)) == 0 and never.steps_to_lift is None


def test_table_4_counts_the_cube_lost_after_the_lift(lowdim_dataset_root, tmp_path):
    kept = {"episode_return": 151 * LIFT_REWARD, "length": 200, "success": True, "steps_to_lift": 50, "lifted_steps": 151}
    lost = {**kept, "episode_return": 51 * LIFT_REWARD, "lifted_steps": 51}  # held 51 steps, then 100 without it
    # an evaluation written before `lifted_steps` was recorded: the lifted steps come from the sparse return
    lost_old = {key: value for key, value in lost.items() if key != "lifted_steps"}
    failed = {"episode_return": 0.0, "length": 200, "success": False, "steps_to_lift": None, "lifted_steps": 0}
    runs = []
    for name, seed, episodes in (("a", 1, [kept, lost, failed, kept]), ("b", 2, [kept, lost_old, lost, kept])):
        run = fake_run(tmp_path / name, lowdim_dataset_root, "BC+RL", [0.0], 1024, seed=seed)
        result = json.loads((run / "eval_final.json").read_text())
        (run / "eval_final.json").write_text(json.dumps({**result, "episodes": episodes}))
        runs.append(run)
    result = report(ReportConfig(runs=[str(r) for r in runs], output_dir=tmp_path / "report"))
    rows = {r["seed"]: r for r in result["rows"]}
    assert rows[1]["lost_after_lift"] == 1 and rows[2]["lost_after_lift"] == 2
    assert rows[1]["return_lost_after_lift"] == pytest.approx(100 * LIFT_REWARD / 4)
    assert rows[2]["return_lost_after_lift"] == pytest.approx(200 * LIFT_REWARD / 4)
    demo = rows[1]["demo_return"]
    _, _, row = table(result["tables"], "Table 4")
    mean_lost = 150 * LIFT_REWARD / 4
    assert f"| 1.5 of 4 (runs: 1, 2); {mean_lost:.1f} ({100 * mean_lost / demo:.1f} %) |" in row
    details = table(result["tables"], "Details")
    assert any(f"| 1, {100 * LIFT_REWARD / 4:.1f} |" in line for line in details)


def test_a_run_whose_result_was_chosen_on_validation_says_when(lowdim_dataset_root, tmp_path):
    bcrl = fake_run(tmp_path / "bcrl", lowdim_dataset_root, "BC+RL", [300.0, 310.0], 102400)
    result = json.loads((bcrl / "eval_final.json").read_text())
    result.update(select="best_validation", selected_env_steps=64000,
                  validation={"env_steps": 64000, "success": 1.0, "return": 305.0, "seed_offset": 2_000_000, "episodes": 20})
    (bcrl / "eval_final.json").write_text(json.dumps(result))
    last = fake_run(tmp_path / "last", lowdim_dataset_root, "BC+RL, last", [300.0], 102400)
    rows = {r["method"]: r for r in report(ReportConfig(runs=[str(bcrl), str(last)], output_dir=tmp_path / "report"))["rows"]}
    assert rows["BC+RL"]["env_steps"] == 102400 and rows["BC+RL"]["selected_env_steps"] == 64000  # the budget, then the pick
    assert rows["BC+RL, last"]["selected_env_steps"] is None
    details = (tmp_path / "report" / "report.md").read_text().split("Details")[1]
    assert "| 102400 (chosen: 64000) |" in details and details.count("(chosen:") == 1


def test_details_name_the_bc_checkpoints_training_seed(lowdim_dataset_root, tmp_path):
    bc_checkpoints = []
    for bc_seed in (1000, 3):  # two lerobot-train checkpoints: train_config.json holds their --seed
        checkpoint = tmp_path / f"bc_seed{bc_seed}" / "pretrained_model"
        checkpoint.mkdir(parents=True)
        (checkpoint / "train_config.json").write_text(json.dumps({"seed": bc_seed, "steps": 3000}))
        bc_checkpoints.append(checkpoint)
    runs = [fake_run(tmp_path / f"bcrl_from_{c.parent.name}", lowdim_dataset_root, "BC+RL", [300.0, 200.0], 102400,
                     seed=1000, policy_path=c) for c in bc_checkpoints]
    runs.append(fake_run(tmp_path / "scratch", lowdim_dataset_root, "PPO from scratch", [0.0, 0.0], 102400, seed=2))
    details = table(report(ReportConfig(runs=[str(r) for r in runs], output_dir=tmp_path / "report"))["tables"], "Details")
    assert "| seed (BC's) |" in details[0]
    rows = {line.split("`")[-2]: line for line in details[2:]}
    assert "| 1000 (BC 1000) |" in rows[str(runs[0])] and "| 1000 (BC 3) |" in rows[str(runs[1])]
    assert "| 2 |" in rows[str(runs[2])]  # no BC checkpoint behind it


def test_plot_labels_tell_runs_apart_by_seed_and_then_by_bc_seed():
    def row(seed, bc_seed, sigma="0"):
        return {"method": "BC+RL", "sigma_label": sigma, "seed": seed, "bc_seed": bc_seed}
    rows = [row(1000, 1000), row(1000, 3), row(2, 3), row(1000, 3, sigma="0.1")]
    labels = [plot_label(r, rows) for r in rows]
    assert labels == ["BC+RL sigma=0 seed=1000 BC seed=1000", "BC+RL sigma=0 seed=1000 BC seed=3",
                      "BC+RL sigma=0 seed=2", "BC+RL sigma=0.1"]
