"""Whether two EPPO runs computed the same updates: their metrics.jsonl
compared on every learning quantity (losses, returns, costs, lambda,
entropy coefficient, Q means, environment steps), timing and CPU-share
fields left out. With collection and learning overlapped, when a round's
record is written can shift by an update or two between runs, so only the
records that close the same window of updates in both (the same update
count, after the same previous one) are compared. Prints the first that
differs, or how many agree to the last digit.

    python3 same_updates.py RUN_A/metrics.jsonl RUN_B/metrics.jsonl
"""
import json
import math
import sys

SKIP_PREFIXES = ("time/", "charts/")


def records(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def learning_fields(rec):
    return {k: v for k, v in rec.items() if not k.startswith(SKIP_PREFIXES)}


def same(x, y):
    if isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y):
        return True
    return x == y


def windows(rs):
    """Each record by the window of updates it closes: (previous update
    count, its own); records logged before the first update are left out."""
    return {(p.get("updates"), r.get("updates")): r for p, r in zip([{}] + rs, rs) if r.get("updates")}


def main(a_path, b_path):
    wa, wb = windows(records(a_path)), windows(records(b_path))
    shared = sorted(wa.keys() & wb.keys(), key=lambda k: k[1])
    n = len(shared)
    if n == 0:
        print("no window of updates is logged by both runs: nothing to compare")
        return 1
    for i, key in enumerate(shared):
        fa, fb = learning_fields(wa[key]), learning_fields(wb[key])
        differ = sorted(k for k in fa.keys() | fb.keys() if not same(fa.get(k), fb.get(k)))
        if differ:
            print(f"window {i} (to update {fa.get('updates')}) differs in {len(differ)} fields:")
            for k in differ[:12]:
                print(f"  {k}: {fa.get(k)!r} vs {fb.get(k)!r}")
            print(f"{i} of {n} shared windows agree before it")
            return 1
    last = learning_fields(wa[shared[-1]])
    print(f"all {n} shared windows agree in every learning field "
          f"({len(last)} fields; last update {last.get('updates')}, env steps {last.get('env_steps')})")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
