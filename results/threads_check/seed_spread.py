"""The recipe's own spread, the yardstick for compare.py's gaps: the largest
gap over k (|a - b| / sqrt(se_a^2 + se_b^2), return per episode) between runs
of one thread count at different training seeds, on the same tasks.

    python3 results/threads_check/seed_spread.py
"""
import itertools
import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "eppo_darkroom_overlap"))
from compare import largest_gap  # noqa: E402


def per_episode(path):
    with open(path) as f:
        return json.load(f)["summary"]["per_episode"]


FINAL = "results/final/darkroom/gather"
for seed in (97, 101):
    runs = {n: per_episode(f"{FINAL}/seed{n}/eval_seed{seed}/eppo_seed{n}_darkroom.json") for n in (0, 1, 2)}
    for a, b in itertools.combinations(runs, 2):
        print(f"evaluation seed {seed}: two threads, training seed {a} vs {b}: {largest_gap(runs[a], runs[b]):.2f} s.e.")
HERE = "results/threads_check/darkroom"
for seed in (139, 149):
    for label in ("two-threads", "one-thread"):
        a, b = (per_episode(f"{HERE}/seed{n}/eval_seed{seed}/eppo_{label}_darkroom.json") for n in (0, 1))
        print(f"evaluation seed {seed}: {label}, training seed 0 vs 1: {largest_gap(a, b):.2f} s.e.")
# Car: the main job's two final runs (two threads, training seeds 0 and 1) on the same 16 tasks x 8 budgets.
CAR = "results/final/car"
for where in ("eval_tuning_seed11_8budgets", "eval_tuning_seed13_8budgets", "eval_seed73", "eval_seed79"):
    a, b = (per_episode(f"{CAR}/seed{n}/{where}/eppo_seed{n}_car.json") for n in (0, 1))
    print(f"car {where}: two threads, training seed 0 vs 1: {largest_gap(a, b):.2f} s.e.")
