"""Training metrics of several Point runs side by side, windows of 500 updates.

Usage: python3 rung_windows.py NAME=metrics.jsonl [NAME=metrics.jsonl ...]
Columns per run: return, goal found, discovery in episodes 2-10, first-episode
return, novelty Q / task Q. Session 63's novelty rung reads discovery against
the first episode's success: a path has learned to search in context when the
first rises above the second.
"""
import json
import math
import sys

KEYS = [
    ("episodic_return", "ret"),
    ("found_goal", "found"),
    ("discovery_rate", "disc"),
    ("first_episode_return", "k1"),
    ("losses/novelty_q_mean", "Qnov"),
    ("losses/q_mean", "Q"),
]


def window_mean(records, key, lo, hi):
    values = [
        r[key]
        for r in records
        if lo < r["updates"] <= hi
        and isinstance(r.get(key), (int, float))
        and not math.isnan(r[key])
    ]
    return sum(values) / len(values) if values else float("nan")


def main():
    runs = []
    for arg in sys.argv[1:]:
        name, path = arg.split("=", 1)
        runs.append((name, [json.loads(l) for l in open(path)]))
    last = max(r["updates"] for _, recs in runs for r in recs)
    print("updates run    " + " ".join(label.rjust(6) for _, label in KEYS))
    for hi in range(500, last + 1, 500):
        for name, recs in runs:
            cells = [window_mean(recs, key, hi - 500, hi) for key, _ in KEYS]
            print(f"{hi:7d} {name:6s} " + " ".join(f"{c:6.3f}" if abs(c) < 10 else f"{c:6.2f}" for c in cells))
        print()


if __name__ == "__main__":
    main()
