"""One row of issue 18's table from an `icrl eval --sweep` folder of one EPPO checkpoint:
return and cost at k = 1 and 16 (figure-1 protocol, 20 budgets from [1, 15]),
within budget at k = 16, mean revisit over k = 2..16, found by 16, and Spearman's
rho of the total return on the budget over the sweep 1..15 (claims.py's rank rule).

    python3 results/eppo_darkroom_budget/row.py EVAL_FOLDER
"""
import csv, glob, json, os, sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from claims import spearman  # noqa: E402


def rows(path):
    with open(path) as f:
        return list(csv.DictReader(l for l in f if not l.startswith("#")))


def main(folder):
    [episodes] = [p for p in glob.glob(f"{folder}/eppo_*_episodes.csv") if "_sweep_" not in p]
    e = rows(episodes)
    first, last = e[0], e[-1]
    gain = float(last["return_mean"]) - float(first["return_mean"])
    rev = [float(r["revisit_mean"]) for r in e[1:] if r["revisit_mean"] not in ("", "nan")]
    [sweep] = glob.glob(f"{folder}/eppo_*_sweep_conditions.csv")
    pts = [(float(r["ctg"]), float(r["total_return_mean"])) for r in rows(sweep)]
    rho = spearman([p[0] for p in pts], [p[1] for p in pts])
    print(
        f"return {float(first['return_mean']):.2f} -> {float(last['return_mean']):.2f} (gain {gain:.2f}) | "
        f"cost {float(first['cost_mean']):.1f} -> {float(last['cost_mean']):.1f} | "
        f"within budget at k=16 {1 - float(last['violation_mean']):.2f} | "
        f"revisit k=2..16 {sum(rev) / len(rev):.2f} | found by 16 {float(last['found_by_mean']):.2f} | rho {rho:.2f}"
    )


main(sys.argv[1])
