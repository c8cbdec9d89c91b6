"""The claims row of one `icrl eval` JSON, as `icrl sweep --gather` computes it
(icrl/src/cli/sweep.rs, `Score::of`), for checkpoints that gather does not
read: the intermediate ones of the time-to-target curve.

    python3 score.py LABEL=EVAL_DIR/eppo_X_darkroom.json ...

Prints a Markdown table: return first/last window, gain in standard errors,
within budget at K, cost first/last window, found by K, revisit pooled over
the episodes after the first, and Spearman's rho between budget and total
return (ranks with ties averaged, `claims.spearman`).
"""
import json
import sys
from pathlib import Path

# Spearman's rho as the claims table computes it (results/claims.py).
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from claims import spearman  # noqa: E402


def score(summary):
    trend = summary["trend"]
    per_episode = summary["per_episode"]
    last = per_episode[-1]
    hits = count = 0.0
    for e in per_episode[1:]:
        n = e["revisit"]["n"]
        if n:
            hits += e["revisit"]["mean"] * n
            count += n
    conditions = summary.get("per_condition", [])
    return {
        "return, first": trend["first_return"]["mean"],
        "return, last": trend["last_return"]["mean"],
        "gain (s.e.)": trend["return_gain"]["mean"] / trend["return_gain"]["se"],
        "within at K": 1.0 - last["violation"]["mean"],
        "cost, first": trend["first_cost"]["mean"],
        "cost, last": trend["last_cost"]["mean"],
        "found by K": last["found_by"]["mean"],
        "revisit": hits / count if count else float("nan"),
        "rho": spearman(
            [c["condition"]["ctg"] for c in conditions],
            [c["total_return"]["mean"] for c in conditions],
        ),
    }


rows = []
for arg in sys.argv[1:]:
    label, path = arg.split("=", 1)
    rows.append((label, score(json.load(open(path))["summary"])))
columns = list(rows[0][1])
print("| checkpoint | " + " | ".join(columns) + " |")
print("|---" * (len(columns) + 1) + "|")
for label, row in rows:
    print(f"| {label} | " + " | ".join(f"{row[c]:.2f}" for c in columns) + " |")
