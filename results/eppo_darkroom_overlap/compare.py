"""Synchronous against overlapped, one evaluation folder: return by episode
k, the mean over k, the largest gap over k in standard errors
(|a - b| / sqrt(se_a^2 + se_b^2)), found by the last episode K, revisit over
k = 2..K and the share over budget at K. Any environment: the files are
eppo_{label}_{env}.json.

    python3 compare.py eval_seedS [LABEL_A LABEL_B]   (default: sync overlap)
"""
import glob
import json
import math
import sys


def load(folder, label):
    (path,) = glob.glob(f"{folder}/eppo_{label}_*.json")
    with open(path) as f:
        return json.load(f)["summary"]["per_episode"]


def main(folder, a="sync", b="overlap"):
    ea, eb = load(folder, a), load(folder, b)
    last = len(ea)
    ks = sorted({1, 2, 4, last // 2, 3 * last // 4, last})
    print("k: " + " ".join(str(k) for k in ks))
    for name, e in ((a, ea), (b, eb)):
        rets = {x["k"]: x["ret"]["mean"] for x in e}
        print(f"{name}: " + " ".join(f"{rets[k]:.2f}" for k in ks), end="")
        mean = sum(x["ret"]["mean"] for x in e) / len(e)
        rev = [x["revisit"]["mean"] for x in e if x["k"] > 1 and x["revisit"]["mean"] is not None]
        print(f"  mean over k {mean:.3f}  found by {last} {e[-1]['found_by']['mean']:.2f}"
              f"  revisit {sum(rev) / len(rev):.2f}  over budget at {last} {e[-1]['violation']['mean']:.2f}")
    print(f"largest gap over k: {largest_gap(ea, eb):.2f} s.e.")


def largest_gap(ea, eb):
    """The largest |a - b| / sqrt(se_a^2 + se_b^2) of the return over k."""
    return max(abs(x["ret"]["mean"] - y["ret"]["mean"])
               / math.sqrt(x["ret"]["se"] ** 2 + y["ret"]["se"] ** 2 or 1e-12)
               for x, y in zip(ea, eb))


if __name__ == "__main__":
    main(*sys.argv[1:])
