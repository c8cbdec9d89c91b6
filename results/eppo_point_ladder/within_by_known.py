"""Within budget at the last episode K of an `icrl eval` JSON, split by whether
the trajectory had reached its goal in an earlier episode (goal known) or was
still searching at K, over all budgets and over the budgets below 2.5 (where
one hazard contact, 3-4, overspends).

    python3 within_by_known.py LABEL=EVAL_DIR/eppo_LABEL_point.json ...

Prints one line per file: within budget at K (number of (task, budget)
pairs, mean cost at K) for each part.
"""
import json
import sys

import numpy as np

for arg in sys.argv[1:]:
    label, path = arg.split("=", 1)
    result = json.load(open(path))["result"]
    reached = np.array(result["reached_goal"], dtype=float) > 0  # (budgets, tasks, K)
    costs = np.array(result["costs"], dtype=float)
    budgets = np.array([c["ctg"] for c in result["conditions"]])[:, None]
    last = costs.shape[2] - 1
    known = reached[:, :, :last].any(axis=2)
    within = costs[:, :, last] <= budgets
    small = np.broadcast_to(budgets < 2.5, within.shape)

    def part(mask):
        return f"{within[mask].mean():.2f} (n {mask.sum()}, cost {costs[:, :, last][mask].mean():.2f})"

    print(
        f"{label}: all {within.mean():.2f} | goal known {part(known)} | searching {part(~known)}"
        f" | budgets < 2.5: known {part(known & small)}, searching {part(~known & small)}"
    )
