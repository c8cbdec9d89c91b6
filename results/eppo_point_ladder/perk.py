"""Per-episode summary of an `icrl eval` JSON: return, cost, the cost paid again
(repeat_cost; "-" in older files), over-budget rate, revisit, discovery and found-by
for each episode index k (means over tasks x budgets).

    python3 perk.py EVAL_DIR/eppo_LABEL_point.json
"""
import json
import sys

summary = json.load(open(sys.argv[1]))["summary"]["per_episode"]
keys = ["ret", "cost", "repeat_cost", "violation", "revisit", "discovery", "found_by", "search_new_cells"]
print("k  " + "  ".join(f"{k[:9]:>9}" for k in keys))
for k, row in enumerate(summary, start=1):
    cells = []
    for key in keys:
        v = row.get(key)
        mean = v.get("mean") if isinstance(v, dict) else v
        cells.append(f"{mean:9.3f}" if isinstance(mean, (int, float)) and mean == mean else f"{'-':>9}")
    print(f"{k:<2} " + "  ".join(cells))
