"""Share of (task, budget) pairs an agent that ignores the budget ends over it,
for candidate budget ranges: each recorded episode-K cost against budgets
drawn uniformly from [lo, hi] (exact, from the empirical costs).
Usage: cost_bind.py EVAL.json [EVAL.json ...]"""
import json
import sys

costs = []
for path in sys.argv[1:]:
    r = json.load(open(path))["result"]
    # costs: [condition][task][episode]
    for condition in r["costs"]:
        for cond in condition:
            costs.append(cond[-1])
costs.sort()
n = len(costs)
print(f"{n} episode-K costs; quantiles 10/25/50/75/90%:",
      [round(costs[int(q * (n - 1))], 2) for q in (0.1, 0.25, 0.5, 0.75, 0.9)])
for lo, hi in [(2, 20), (0.5, 5), (0.5, 3), (0.25, 2), (0.5, 2), (0.1, 1.5)]:
    # P(cost > b), b ~ U[lo, hi]
    share = sum(min(max((c - lo) / (hi - lo), 0.0), 1.0) for c in costs) / n
    print(f"budgets [{lo}, {hi}]: over budget {share:.2f}")
