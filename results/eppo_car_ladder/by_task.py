"""Where an `icrl eval` JSON loses its budget: within budget at the last
episode K by budget and by task, the mean cost at K by task, and the share of
budgets in which each task's goal was found before K.

    python3 by_task.py EVAL_DIR/eppo_LABEL_car.json ...
"""
import json
import sys

import numpy as np

for path in sys.argv[1:]:
    result = json.load(open(path))["result"]
    costs = np.array(result["costs"], dtype=float)  # (budgets, tasks, K)
    budgets = np.array([c["ctg"] for c in result["conditions"]])
    within = costs[:, :, -1] <= budgets[:, None]
    reached = np.array(result["reached_goal"], dtype=float) > 0
    print(path, "budgets", np.round(budgets, 2))
    print(" within by budget", np.round(within.mean(1), 2))
    print(" within by task  ", np.round(within.mean(0), 2))
    print(" cost at K by task", np.round(costs[:, :, -1].mean(0), 1))
    print(" found before K by task", np.round(reached[:, :, :-1].any(2).mean(0), 2))
