"""What separates ps8's path from the weak runs of its recipe (session 63).

Windows of 500 training updates: ps8's mean of each metric, then the range
of the weak runs (ps11, pf0, pf2) in brackets; + marks ps8 above all three,
- below all three. Usage: python3 separation.py > separation.txt
"""
import json
from pathlib import Path

from rung_windows import window_mean

HERE = Path(__file__).parent
RUNS = {
    "ps8": "ps8_ps5_novelty_critic/metrics.jsonl",
    "ps11": "ps11_ps8_recipe_seed1_one_thread/metrics.jsonl",
    "pf0": "pf0_preset_gate0.7_never_opened/point__eppo__0__20261207T084207/metrics.jsonl",
    "pf2": "pf2_preset_pt6_recipe_seed0/point__eppo__0__20261207T154422/metrics.jsonl",
}
KEYS = [
    ("episodic_return", "return"),
    ("found_goal", "found"),
    ("discovery_rate", "discovery"),
    ("first_episode_return", "return k1"),
    ("losses/log_std_mean", "log_std"),
    ("charts/action_abs", "|a|"),
    ("entropy_coef", "alpha"),
    ("losses/novelty_q_mean", "Q novelty"),
    ("losses/q_mean", "Q task"),
    ("losses/grad_norm", "grad norm"),
    ("episodic_cost", "cost"),
]


runs = {name: [json.loads(l) for l in open(HERE / path)] for name, path in RUNS.items()}
print("updates " + " ".join(label.rjust(19) for _, label in KEYS))
for hi in range(500, 5001, 500):
    cells = []
    for key, _ in KEYS:
        strong = window_mean(runs["ps8"], key, hi - 500, hi)
        weak = [window_mean(runs[n], key, hi - 500, hi) for n in ("ps11", "pf0", "pf2")]
        mark = "+" if strong > max(weak) else "-" if strong < min(weak) else " "
        fmt = ".3f" if abs(strong) < 10 else ".1f"
        cells.append(f"{strong:{fmt}}{mark}[{min(weak):{fmt}},{max(weak):{fmt}}]".rjust(19))
    print(f"{hi:7d} " + " ".join(cells))
