"""`bcrl-report`: finished bcrl-finetune runs -> the paper's Tables 1 and 2, a success table, a table of the
cube lost after the lift (markdown + JSON) and PNG plots. Runs of one method on one dataset at one env-step
budget (training seeds) share a cell: the tables give their mean and spread, the details table every run.

Demonstrators' return comes from each run's dataset (`episode_return` in the episode metadata); policy return,
success and steps-to-lift from the run's `eval_final.json`; curves from its `logs.csv`.
"""

from __future__ import annotations

import csv
import glob
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np

from lerobot_bcrl.features import LIFT_REWARD
from lerobot_bcrl.rl.logger import TIME_COLUMNS
from lerobot_bcrl.stats import mean_ci95

METHOD_ORDER = ("BC", "BC+RL", "PPO from scratch")


@dataclass
class ReportConfig:
    runs: list[str] = field(default_factory=lambda: ["outputs/rl/*"])  # run dirs or globs (with eval_final.json)
    output_dir: Path = Path("outputs/report")
    smooth: int = 10  # training curves: trailing mean over this many PPO iterations (1: raw)


def wilson_ci95(successes: int, n: int) -> tuple[float, float]:
    """Wilson score interval for a success rate (sound at 0 % and 100 %, unlike mean +/- 1.96 se)."""
    if n == 0:
        return float("nan"), float("nan")
    z, p = 1.96, successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def demonstrators(repo_id: str, root: str) -> dict:
    """The demonstrators' return and success; episodes with a planned miss (bcrl-record --miss_probability)
    are left out (unless every episode has one), so that the bar is the noisy demonstrators' own, not one
    lowered by the misses."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    episodes = LeRobotDatasetMetadata(repo_id, root=root).episodes
    keep = np.ones(len(episodes["episode_return"]), dtype=bool)
    if "planned_miss" in episodes.column_names and not np.all(episodes["planned_miss"]):
        keep = ~np.asarray(episodes["planned_miss"], dtype=bool)
    returns = np.asarray(episodes["episode_return"], dtype=float)[keep]
    noise_std = np.asarray(episodes["noise_std"], dtype=float) if "noise_std" in episodes.column_names else np.full(1, np.nan)
    sigma = float(np.mean(noise_std))
    # several demonstrators of different noise (configs/record_operator_mix.yaml): their range, not a mean
    sigma_label = f"{sigma:g}" if np.ptp(noise_std) == 0 or np.isnan(sigma) else f"{noise_std.min():g}-{noise_std.max():g} (mix)"
    success = np.asarray(episodes["success"], dtype=bool)[keep] if "success" in episodes.column_names else None
    mean, ci = mean_ci95(list(returns))
    return {"sigma": sigma, "sigma_label": sigma_label, "demo_return": mean, "demo_return_ci95": ci, "demo_episodes": len(returns),
            "demo_success": float(np.mean(success)) if success is not None else float("nan")}


def success_rate(episodes: list[dict]) -> tuple[float, tuple[float, float]]:
    successes = sum(bool(e["success"]) for e in episodes)
    return successes / len(episodes), wilson_ci95(successes, len(episodes))


def steps_lost_after_lift(episode: dict) -> float:
    """Steps from the first lift to the end without the cube lifted: it slipped or was let go, and the sparse
    reward stopped. Evaluations before `lifted_steps` was recorded give it through the return (sparse reward)."""
    if not episode["success"]:
        return 0.0
    lifted_steps = episode.get("lifted_steps", episode["episode_return"] / LIFT_REWARD)
    return max(0.0, episode["length"] - episode["steps_to_lift"] + 1 - lifted_steps)


def bc_training_seed(policy_path: str | None) -> int | None:
    """lerobot-train's --seed of the checkpoint a run started from (its train_config.json), so that runs from
    different BC checkpoints tell apart; None for PPO from scratch or a start that was not lerobot-train's."""
    train_config = Path(policy_path) / "train_config.json" if policy_path else None
    if train_config is None or not train_config.is_file():
        return None
    return json.loads(train_config.read_text()).get("seed")


def summarize_run(run_dir: Path) -> dict:
    result = json.loads((run_dir / "eval_final.json").read_text())
    episodes = result["episodes"]
    returns = [e["episode_return"] for e in episodes]
    lifts = [e["steps_to_lift"] for e in episodes if e["steps_to_lift"] is not None]
    lost_steps = [steps_lost_after_lift(e) for e in episodes]
    mean, ci = mean_ci95(returns)
    success, success_ci95 = success_rate(episodes)
    # One dataset, one table row, however a run spelled its path (older runs wrote it relative to their cwd).
    dataset_root = str(Path(result["dataset_root"]).resolve())
    demo = demonstrators(result["dataset_repo_id"], dataset_root)
    return {
        "run": str(run_dir), "dataset_root": dataset_root, "method": result["method"],
        "seed": result.get("seed"),  # bcrl-finetune's --seed (runs before it was recorded: None)
        "bc_seed": bc_training_seed(result.get("policy_path")),
        # an evaluated fine-tuning checkpoint (--total_env_steps=0) counts the env steps it was trained with
        "env_steps": result["env_steps"] + result.get("policy_env_steps", 0), **demo,
        # --select=best_validation: the evaluated policy is the one chosen at these env steps, not the last
        "selected_env_steps": result["selected_env_steps"] + result.get("policy_env_steps", 0) if result.get("validation") else None,
        "return": mean, "return_ci95": ci, "recovered_pct": 100 * mean / demo["demo_return"] if demo["demo_return"] else float("nan"),
        "success": success, "success_ci95": success_ci95,
        "steps_to_lift": float(np.mean(lifts)) if lifts else float("nan"), "episodes": len(episodes),
        "lost_after_lift": sum(steps > 0.5 for steps in lost_steps),  # episodes that lifted the cube and lost it
        "return_lost_after_lift": LIFT_REWARD * float(np.mean(lost_steps)),  # per episode, over all episodes
    }


def success_cell(success: float, ci95: tuple[float, float]) -> str:
    low, high = ci95
    return f"{100 * success:.0f} % ({max(0.0, 100 * low):.0f}-{min(100.0, 100 * high):.0f})"


def column_key(row: dict) -> tuple[str, int]:
    return row["method"], row["env_steps"]


def column_headers(rows: list[dict]) -> dict[tuple[str, int], str]:
    """One column per (method, env steps): a method measured at several budgets (a run and its checkpoint
    evaluated at 192k, say) gets a column per budget instead of one run silently hiding the other."""
    keys = sorted({column_key(r) for r in rows}, key=lambda k: (
        METHOD_ORDER.index(k[0]) if k[0] in METHOD_ORDER else len(METHOD_ORDER), k[0], k[1]))
    budgets = {method: {steps for m, steps in keys if m == method} for method, _ in keys}
    return {(m, steps): m if len(budgets[m]) == 1 else f"{m}, {steps / 1000:g}k" for m, steps in keys}


def aggregate_cell(runs: list[dict]) -> dict:
    """Runs of one method on one dataset at one budget (several training seeds): the mean of the runs' means,
    the spread between runs, and each run's success, so a lucky seed shows as one of several."""
    returns = [r["return"] for r in runs]
    return {"runs": len(runs), "seeds": [r.get("seed") for r in runs], "return": float(np.mean(returns)),
            "return_sd": float(np.std(returns, ddof=1)) if len(runs) > 1 else float("nan"),
            "recovered_pct": float(np.mean([r["recovered_pct"] for r in runs])),
            "recovered_pct_range": (min(r["recovered_pct"] for r in runs), max(r["recovered_pct"] for r in runs)),
            "success": float(np.mean([r["success"] for r in runs])), "success_per_run": [r["success"] for r in runs],
            "lost_after_lift": float(np.mean([r["lost_after_lift"] for r in runs])),
            "lost_after_lift_per_run": [r["lost_after_lift"] for r in runs],
            "return_lost_after_lift": float(np.mean([r["return_lost_after_lift"] for r in runs])),
            "return_lost_after_lift_pct": float(np.mean([100 * r["return_lost_after_lift"] / r["demo_return"] for r in runs]))}


def markdown_tables(rows: list[dict]) -> tuple[str, list[dict]]:
    """Tables 1-3 (a row per dataset, a column per method and budget; a cell with several runs, i.e. seeds,
    gives their mean and spread) and a details table with every run; also the cells, for report.json."""
    datasets = sorted({(r["sigma"], r["dataset_root"]) for r in rows})
    headers = column_headers(rows)
    runs_by_cell: dict[tuple, list[dict]] = {}
    for r in rows:
        runs_by_cell.setdefault(((r["sigma"], r["dataset_root"]), column_key(r)), []).append(r)
    cells = {key: aggregate_cell(runs) for key, runs in runs_by_cell.items()}
    fmt = lambda r, key: f"{r[key]:.1f} +/- {r[key + '_ci95']:.1f}"  # noqa: E731

    def return_cell(key) -> str:
        if key not in cells:
            return "-"
        if cells[key]["runs"] == 1:
            return fmt(runs_by_cell[key][0], "return")
        return f"{cells[key]['return']:.1f} (sd {cells[key]['return_sd']:.1f}, {cells[key]['runs']} runs)"

    def recovered_cell(key) -> str:
        if key not in cells:
            return "-"
        cell = cells[key]
        low, high = cell["recovered_pct_range"]
        return f"{cell['recovered_pct']:.0f} %" + (f" ({low:.0f}-{high:.0f})" if cell["runs"] > 1 else "")

    def success_table_cell(key) -> str:
        if key not in cells:
            return "-"
        if cells[key]["runs"] == 1:
            run = runs_by_cell[key][0]
            return success_cell(run["success"], run["success_ci95"])
        per_run = ", ".join(f"{100 * s:.0f}" for s in cells[key]["success_per_run"])
        return f"{100 * cells[key]['success']:.0f} % (runs: {per_run})"

    def lost_after_lift_cell(key) -> str:
        if key not in cells:
            return "-"
        cell, episodes = cells[key], runs_by_cell[key][0]["episodes"]
        counted = f"{cell['lost_after_lift']:.0f} of {episodes}" if cell["runs"] == 1 else (
            f"{cell['lost_after_lift']:.1f} of {episodes} (runs: {', '.join(map(str, cell['lost_after_lift_per_run']))})")
        return f"{counted}; {cell['return_lost_after_lift']:.1f} ({cell['return_lost_after_lift_pct']:.1f} %)"

    lines = []
    for title, demo_columns, first_columns, cell_text in (
        ("Table 1: mean return (95 % CI; over several runs: their mean and sd), sparse reward, horizon 200 (max 450)",
         ["sigma", "demonstrators"], lambda demo: [demo['sigma_label'], fmt(demo, "demo_return")], return_cell),
        ("Table 2: % of the demonstrators' return recovered (over several runs: their mean, min-max)",
         ["sigma"], lambda demo: [demo['sigma_label']], recovered_cell),
        ("Table 3: success (95 % Wilson interval; over several runs: their mean, and each run's)",
         ["sigma", "demonstrators"], lambda demo: [demo['sigma_label'], f"{100 * demo['demo_success']:.0f} %"],
         success_table_cell),
        ("Table 4: episodes that lifted the cube and lost it again; the return this cost per episode (% of the "
         "demonstrators' return); over several runs: their mean", ["sigma"], lambda demo: [demo['sigma_label']],
         lost_after_lift_cell),
    ):
        lines += ([title, ""] if not lines else ["", title, ""])
        lines += ["| " + " | ".join(demo_columns + list(headers.values())) + " |",
                  "|---" * (len(demo_columns) + len(headers)) + "|"]
        for dataset in datasets:
            demo = next(r for r in rows if (r["sigma"], r["dataset_root"]) == dataset)
            lines.append("| " + " | ".join(first_columns(demo) + [cell_text((dataset, k)) for k in headers]) + " |")
    lines += ["", "Details", "", "| sigma | method | env steps | seed (BC's) | episodes | return (95 % CI) | % recovered |"
              " success (95 % CI) | steps to lift | lost after lift: episodes, return | run |",
              "|---" * 11 + "|"]
    for r in sorted(rows, key=lambda r: (r["sigma"], r["method"], r["env_steps"], str(r.get("seed")))):
        seed = "-" if r.get("seed") is None else r["seed"]
        if r.get("bc_seed") is not None:
            seed = f"{seed} (BC {r['bc_seed']})"
        steps = r["env_steps"] if r.get("selected_env_steps") is None else f"{r['env_steps']} (chosen: {r['selected_env_steps']})"
        to_lift = "-" if math.isnan(r["steps_to_lift"]) else f"{r['steps_to_lift']:.1f}"  # no episode lifted
        lines.append(f"| {r['sigma_label']} | {r['method']} | {steps} | {seed} | {r['episodes']} | {fmt(r, 'return')} |"
                     f" {r['recovered_pct']:.0f} % | {success_cell(r['success'], r['success_ci95'])} |"
                     f" {to_lift} | {r['lost_after_lift']}, {r['return_lost_after_lift']:.1f} | `{r['run']}` |")
    cell_list = [{"sigma": dataset[0], "dataset_root": dataset[1], "method": key[0], "env_steps": key[1],
                  "column": headers[key], **cell} for (dataset, key), cell in sorted(cells.items(), key=lambda kv: str(kv[0]))]
    return "\n".join(lines) + "\n", cell_list


def timing_table(rows: list[dict]) -> str:
    """Where each training run's time went, in seconds per 1,000 env steps (runs whose logs.csv times its parts).

    A row's env steps are its env_steps less the previous row's (0 before the first), so a log that starts with
    the untimed starting validation, holds one iteration, or was resumed is divided by the steps its timed rows
    collected."""
    lines = []
    for r in rows:
        log = read_log(Path(r["run"]))
        timed = np.isfinite(log.get("simulation_s", []))  # training iterations (not the starting validation)
        if not timed.any():  # an evaluation-only run, or one logged before its parts were timed
            continue
        steps_collected = np.diff(log["env_steps"], prepend=0.0)[timed].sum()
        per_1k = 1000.0 / steps_collected
        cells = [f"{per_1k * np.nansum(log[key][timed]):.2f}" if key in log else "-" for key in TIME_COLUMNS]
        seed = "-" if r.get("seed") is None else r["seed"]
        lines.append(f"| {r['method']} | {seed} | " + " | ".join(cells) + f" | `{r['run']}` |")
    if not lines:
        return ""
    header = "| method | seed | " + " | ".join(TIME_COLUMNS.values()) + " | run |"
    return "\n".join(["", "Where the time goes (seconds per 1,000 env steps; the workers' parts are wall time in each"
                      " worker, summed over workers; the learner's are wall time within learn)", "", header,
                      "|---" * (len(TIME_COLUMNS) + 3) + "|", *lines]) + "\n"


def read_log(run_dir: Path) -> dict[str, np.ndarray]:
    path = run_dir / "logs.csv"
    if not path.exists():
        return {}
    rows = list(csv.DictReader(path.open()))
    to_float = lambda v: float(v) if v not in ("", None) else float("nan")  # noqa: E731
    return {key: np.array([to_float(r[key]) for r in rows]) for key in (rows[0] if rows else {})}


def trailing_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the last `window` values at each point (of fewer at the start)."""
    if window <= 1:
        return values
    cumsum = np.concatenate([[0.0], np.cumsum(values)])
    end = np.arange(1, len(values) + 1)
    start = np.maximum(end - window, 0)
    return (cumsum[end] - cumsum[start]) / (end - start)


def plot_runs(runs: list[tuple[str, dict[str, np.ndarray]]], output_dir: Path, smooth: int = 1) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter

    thousands = FuncFormatter(lambda x, _: f"{x / 1000:g}k" if x else "0")  # 300k, not 300000 running into 250000

    figures = {
        "return_success.png": [("train_return", "train return"), ("eval_return", "eval return (deterministic)"),
                               ("train_success", "train success"), ("eval_success", "eval success")],
        "bc_terms.png": [("bc_loss", "BC loss"), ("bc_cosine", "cosine distance of delta_pos"),
                         ("bc_gripper_ce", "gripper CE"), ("bc_rot_l1", "rotation L1")],
        "theta_ppo.png": [("theta", "theta_t"), ("approx_kl", "approx KL"), ("clipfrac", "clip fraction"),
                          ("explained_variance", "explained variance"),
                          ("bc_grad_share", "BC term's share of the policy gradient")],
    }
    written = []
    for filename, panels in figures.items():
        fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4))
        for ax, (key, title) in zip(axes, panels):
            window = 1 if key.startswith("eval") else smooth  # evaluations are plotted as measured
            for i, (label, log) in enumerate(runs):  # a run keeps its colour in panels that others miss
                if key in log and np.isfinite(log[key]).any():
                    mask = np.isfinite(log[key])
                    ax.plot(log["env_steps"][mask], trailing_mean(log[key][mask], window), label=label,
                            color=f"C{i % 10}", marker="." if key.startswith("eval") else None)
            ax.set_title(title if window <= 1 else f"{title} (mean of {window} iterations)", fontsize=9)
            ax.set_xlabel("env steps")
            ax.xaxis.set_major_formatter(thousands)
            ax.grid(alpha=0.3)
        legend = {}  # every run that any panel shows, once
        for ax in axes:
            for handle, label in zip(*ax.get_legend_handles_labels()):
                legend.setdefault(label, handle)
        handles, labels = list(legend.values()), list(legend)
        if labels:  # none where no run has a point yet (a run shorter than one episode)
            fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize=7, frameon=False)
        fig.tight_layout(rect=(0, 0.06 * ((len(labels) + 3) // 4), 1, 1))
        fig.savefig(output_dir / filename, dpi=110, bbox_inches="tight")  # long run labels: keep the legend whole
        plt.close(fig)
        written.append(output_dir / filename)
    return written


def plot_label(row: dict, rows: list[dict]) -> str:
    """Method and sigma; the seed too where other runs would carry the same label, and the BC checkpoint's
    training seed where runs of one seed started from different BC checkpoints."""
    label = f"{row['method']} sigma={row['sigma_label']}"
    twins = [r for r in rows if (r["method"], r["sigma_label"]) == (row["method"], row["sigma_label"])]
    if len(twins) > 1 and row.get("seed") is not None:
        label += f" seed={row['seed']}"
        if len({r.get("bc_seed") for r in twins if r.get("seed") == row["seed"]}) > 1:
            label += f" BC seed={row.get('bc_seed')}"
    return label


def report(cfg: ReportConfig) -> dict:
    run_dirs = sorted({Path(p) for pattern in cfg.runs for p in glob.glob(str(pattern)) if (Path(p) / "eval_final.json").exists()})
    if not run_dirs:
        raise FileNotFoundError(f"no finished runs (with eval_final.json) match {cfg.runs}")
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    rows = [summarize_run(d) for d in run_dirs]
    tables, cells = markdown_tables(rows)
    tables += timing_table(rows)
    (cfg.output_dir / "report.md").write_text(tables)
    (cfg.output_dir / "report.json").write_text(json.dumps({"runs": rows, "cells": cells}, indent=2))
    plots = plot_runs([(plot_label(r, rows), read_log(Path(r["run"]))) for r in rows], cfg.output_dir, cfg.smooth)
    return {"rows": rows, "cells": cells, "tables": tables, "plots": plots}


def main() -> None:
    cfg = draccus.parse(ReportConfig)
    result = report(cfg)
    print(result["tables"])
    print(f"bcrl-report: {len(result['rows'])} runs -> {cfg.output_dir / 'report.md'}, report.json, "
          + ", ".join(p.name for p in result["plots"]))


if __name__ == "__main__":
    main()
