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


def main(a_path, b_path):
    a, b = records(a_path), records(b_path)
    windows = lambda rs: {(p.get("updates"), r.get("updates")): r for p, r in zip([{}] + rs, rs)}
    wa, wb = windows(a), windows(b)
    shared = sorted((k for k in wa.keys() & wb.keys() if k[1]), key=lambda k: k[1])
    n = len(shared)
    for i, key in enumerate(shared):
        fa, fb = learning_fields(wa[key]), learning_fields(wb[key])
        differ = sorted(k for k in fa.keys() | fb.keys() if not same(fa.get(k), fb.get(k)))
        if differ:
            print(f"record {i} (update {fa.get('updates')} / {fb.get('updates')}) differs in {len(differ)} fields:")
            for k in differ[:12]:
                print(f"  {k}: {fa.get(k)!r} vs {fb.get(k)!r}")
            print(f"{i} of {n} shared windows agree before it")
            return 1
    last = learning_fields(wa[shared[-1]]) if n else {}
    print(f"all {n} shared windows agree in every learning field "
          f"({len(last)} fields; last update {last.get('updates')}, env steps {last.get('env_steps')})")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
