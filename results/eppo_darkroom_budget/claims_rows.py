#!/usr/bin/env python3
"""One markdown row of claims 1-4 per evaluation folder, from `results/claims.py`.

Usage: python3 results/eppo_darkroom_budget/claims_rows.py LABEL=EVAL_DIR [...]

Claim 1 and 2 are read on the figure-1 protocol (20 budgets from [1, 15]),
claim 4 on the sweep (budgets 1..15), as `claims.py` prints them. Issue 18's
cost target is added: the first-to-last-window cost drop (claims.py's
windows) over the budgets below the random policy's mean episode cost only.
"""
import json
import math
import re
import subprocess
import sys
from pathlib import Path

CLAIMS = Path(__file__).resolve().parent.parent / "claims.py"


def low_budget_cost_drop(folder):
    """Per task, first-minus-last-window cost over budgets below the random
    policy's mean episode cost; mean and s.e. over tasks."""
    # eppo_darkroom.json, or eppo_LABEL_darkroom.json for a labelled checkpoint.
    [path] = [p for p in Path(folder).glob("eppo_*darkroom.json") if "_sweep" not in p.name]
    agent = json.loads(path.read_text())["result"]
    random = json.loads(Path(folder, "random_darkroom.json").read_text())["result"]
    costs = [x for c in random["costs"] for t in c for x in t]
    bar = sum(costs) / len(costs)
    low = [i for i, c in enumerate(agent["conditions"]) if c["ctg"] < bar]
    k = len(agent["costs"][0][0])
    w = max(1, round(0.2 * k))
    drops = []
    for t in range(len(agent["tasks"])):
        per = [agent["costs"][c][t] for c in low]
        drops.append(sum(sum(e[:w]) / w - sum(e[-w:]) / w for e in per) / len(per))
    m = sum(drops) / len(drops)
    se = math.sqrt(sum((d - m) ** 2 for d in drops) / (len(drops) - 1) / len(drops))
    return m, se, bar, len(low)


def row(label, folder):
    text = subprocess.run([sys.executable, str(CLAIMS), folder], capture_output=True,
                          text=True, check=True).stdout
    eppo = text.split("darkroom Random")[0]
    # The header names the checkpoint's label when it has one: "Eppo [LABEL] sweep".
    fig1, sweep = re.split(r"Eppo (?:\[[^\]]*\] )?sweep", eppo)
    gain = re.search(r"gain (\S+) ± (\S+): (\w+)", fig1)
    drop = re.search(r"drop (\S+) ± (\S+): (\w+)", fig1)
    safe = re.search(r"last-window cost (\S+) vs mean budget (\S+): (\w+)", fig1)
    within = re.search(r"within budget at episode K (\S+)", fig1)
    follow = re.search(r"d total return / d CTG (\S+) ± (\S+); d max cost / d CTG (\S+) ± (\S+): (\w+)",
                       sweep)
    rho = re.search(r"Spearman rho of total return on the budget (\S+)", sweep)
    low = low_budget_cost_drop(folder)
    return (f"| {label} | {gain[1]} ± {gain[2]}: {gain[3]} | {drop[1]} ± {drop[2]}: {drop[3]}; below {low[2]:.1f} ({low[3]} budgets) "
            f"{low[0]:.2f} ± {low[1]:.2f} "
            f"| {safe[1]} vs {safe[2]}: {safe[3]}; within at K {within[1]} "
            f"| {follow[1]} ± {follow[2]}, max cost {follow[3]} ± {follow[4]}: {follow[5]}; rho {rho[1]} |")


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        label, folder = arg.split("=", 1)
        print(row(label, folder))
