"""Do Lift policies fail on the same initial states? Count, per held-out evaluation seed, how many of the given
runs' final evaluations (`eval_final.json`: deterministic, and sampled-action where present) failed on it, and
compare the most-failed seeds with what independent failures at each evaluation's own failure rate would give.

    .venv/bin/python scripts/failure_seeds.py outputs/experiments/lowdim_sigma*_n100/bcrl_std3_critic_bigbatch*
"""

from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path

import numpy as np


def evaluations(run_dirs: list[Path]) -> dict[str, dict[int, bool]]:
    """{"<run> det|sampled": {seed: success}} for every run that has a final evaluation."""
    found = {}
    for run_dir in run_dirs:
        path = run_dir / "eval_final.json"
        if not path.exists():
            continue
        result = json.loads(path.read_text())
        for mode, key in (("det", "episodes"), ("sampled", "episodes_sampled")):
            if key in result:
                found[f"{run_dir} {mode}"] = {e["seed"]: bool(e["success"]) for e in result[key]}
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--simulations", type=int, default=2000)
    args = parser.parse_args()
    evals = evaluations(args.runs)
    seeds = sorted(set().union(*(e.keys() for e in evals.values())))
    failures = collections.Counter({seed: 0 for seed in seeds})
    for episodes in evals.values():
        failures.update(seed for seed, success in episodes.items() if not success)
    observed = sorted(failures.values(), reverse=True)
    rng = np.random.default_rng(0)
    rates = [1 - np.mean(list(e.values())) for e in evals.values()]
    simulated = np.sort(sum(rng.random((args.simulations, len(seeds))) < r for r in rates), axis=1)[:, ::-1]
    print(json.dumps({
        "evaluations": len(evals), "seeds": len(seeds),
        "seeds_never_failed": sum(1 for c in failures.values() if c == 0),
        "most_failed": failures.most_common(5),
        "observed_top5": observed[:5],
        "independent_top5_mean": simulated[:, :5].mean(axis=0).round(1).tolist(),
        "independent_max_95th_percentile": float(np.percentile(simulated[:, 0], 95)),
    }))


if __name__ == "__main__":
    main()
