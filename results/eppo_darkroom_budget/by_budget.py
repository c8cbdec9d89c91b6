"""Per budget of an `icrl eval --sweep` report (budgets 1..15): the share of
tasks whose goal was found in some episode, and the return and cost of the
last episode. Does a larger budget buy bolder search?

    python3 results/eppo_darkroom_budget/by_budget.py EVAL_FOLDER/eppo_*_sweep.json
"""
import json
import sys

for path in sys.argv[1:]:
    result = json.load(open(path))["result"]
    returns, costs = result["returns"], result["costs"]  # [condition][task][episode]
    print(path)
    print("  budget  found by K  return at K  cost at K")
    for c, cond in sorted(enumerate(result["conditions"]), key=lambda x: x[1]["ctg"]):
        tasks = range(len(returns[c]))
        n = len(returns[c])
        found = sum(any(r > 0 for r in returns[c][t]) for t in tasks) / n
        last_return = sum(returns[c][t][-1] for t in tasks) / n
        last_cost = sum(costs[c][t][-1] for t in tasks) / n
        print(f"  {cond['ctg']:6.1f}  {found:10.2f}  {last_return:11.2f}  {last_cost:9.1f}")
