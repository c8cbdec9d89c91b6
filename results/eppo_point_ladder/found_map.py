"""Which held-out tasks an agent solves, and in which episodes: one row per
task (its goal cell), one string per budget, '1' where episode k reached the
goal. Reads where the search goes: a policy that searches one fixed route
solves the same tasks under every budget and never the others.

    python3 found_map.py EVAL_DIR [EVAL_DIR ...]
"""
import glob
import json
import sys

for folder in sys.argv[1:]:
    report = next(p for p in glob.glob(f"{folder}/*.json") if "random_" not in p.rsplit("/", 1)[-1])
    result = json.load(open(report))["result"]
    reached = result["reached_goal"]  # [budget][task][episode]
    print(folder)
    solved = []
    for t, task in enumerate(result["tasks"]):
        rows = [reached[c][t] for c in range(len(reached))]
        print(f"{t:3d} goal {task['goal']}  " + " ".join("".join("1" if r else "." for r in row) for row in rows))
        if any(any(row) for row in rows):
            solved.append(tuple(task["goal"]))
    print(f"    goal cells ever reached: {sorted(set(solved))}")
