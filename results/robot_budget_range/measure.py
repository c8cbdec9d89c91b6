"""Budgets that bind on Point and Car (issue 19, deliverable 3).

For each evaluation report of an agent that ignores the budget (trained with
lambda held at 0, or never moved from it), the share of (task, episode) pairs
whose episode cost exceeds a budget drawn uniformly from [lo, hi], for
candidate ranges. A range binds when that share is at least 0.3.

    python3 results/robot_budget_range/measure.py REPORT.json...
"""
import json
import sys

import numpy as np

RANGES = [(2.0, 20.0), (0.5, 5.0), (0.5, 6.0), (0.5, 8.0), (1.0, 8.0)]


def over_budget_share(costs, lo, hi):
    budgets = np.linspace(lo, hi, 1001)
    return float(np.mean([(costs > b).mean() for b in budgets]))


def main(paths):
    print("| report | episodes | mean cost | cost quartiles | " + " | ".join(f"[{lo:g}, {hi:g}]" for lo, hi in RANGES) + " |")
    print("|---|---|---|---|" + "---|" * len(RANGES))
    for path in paths:
        report = json.load(open(path))
        costs = np.asarray(report["result"]["costs"], dtype=float).reshape(-1)
        q = np.percentile(costs, [25, 50, 75])
        shares = " | ".join(f"{over_budget_share(costs, lo, hi):.2f}" for lo, hi in RANGES)
        print(f"| {path} | {costs.size} | {costs.mean():.2f} | {q[0]:g} / {q[1]:g} / {q[2]:g} | {shares} |")


if __name__ == "__main__":
    main(sys.argv[1:])
