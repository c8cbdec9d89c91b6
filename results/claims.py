#!/usr/bin/env python3
"""Checks the paper's claims (SPEC section 5) against `icrl eval` reports.

Usage: python3 results/claims.py results/eval_darkroom [more folders...]

Reads the JSON reports (`{method}_{env}[_sweep].json`) and prints one line per
claim with the numbers and a verdict. Criteria (fixed before looking at data):
- in-context improvement: per task, mean return of the last 20% of the K
  episodes minus the first 20% (averaged over budgets); PASS if the mean over
  tasks exceeds 2 standard errors;
- cost decrease: the same for first-minus-last cost; PASS above 2 s.e.;
- safe at the end: mean episode cost over the last 20% of episodes at or
  below the mean budget (CTG);
- faster adaptation (EPPO vs AD): mean return over episodes 1..m, m = the
  smaller K, per task; PASS if EPPO - AD exceeds 2 s.e. (independent samples);
- robustness (reported, not a verdict): per-task least-squares slope of the
  episode return and cost against k over all K episodes;
- budget following: per-task least-squares slope of total return on the CTG
  in the sweep; PASS if above 2 s.e. (EPPO); for AD the paper reports no
  trend, so PASS (paper reproduced) if |slope| is within 2 s.e. of zero.
Standard library only.
"""
import json
import math
import sys
from pathlib import Path


def mean_se(xs):
    n = len(xs)
    m = sum(xs) / n
    if n < 2:
        return m, 0.0
    var = sum((x - m) ** 2 for x in xs) / (n - 1)
    return m, math.sqrt(var / n)


def load(folders):
    reports = {}
    for folder in folders:
        for f in sorted(Path(folder).glob("*.json")):
            r = json.loads(f.read_text())
            if not all(k in r for k in ("env", "method", "protocol", "summary")):
                continue
            # Several checkpoints of one method are told apart by their --label.
            reports[(r["env"], r["method"], r.get("label", ""), r["protocol"])] = (f, r)
    return reports


def early_returns(r, m):
    """Per task: mean return over episodes 1..m, averaged over conditions."""
    res = r["result"]
    out = []
    for t in range(len(res["tasks"])):
        vals = [sum(res["returns"][c][t][:m]) / m for c in range(len(res["conditions"]))]
        out.append(sum(vals) / len(vals))
    return out


def slope(xs, ys):
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx


def per_episode_slopes(r, key):
    """Per task: least-squares slope of the episode value (averaged over
    conditions) against k = 1..K; mean and s.e. over tasks."""
    res = r["result"]
    k_n, n_c = r["episodes"], len(res["conditions"])
    out = []
    for t in range(len(res["tasks"])):
        ys = [sum(res[key][c][t][k] for c in range(n_c)) / n_c for k in range(k_n)]
        out.append(slope(list(range(1, k_n + 1)), ys))
    return mean_se(out)


def spearman(xs, ys):
    """Spearman's rank correlation (average ranks for ties)."""
    def ranks(v):
        order = sorted(range(len(v)), key=lambda i: v[i])
        r = [0.0] * len(v)
        i = 0
        while i < len(order):
            j = i
            while j + 1 < len(order) and v[order[j + 1]] == v[order[i]]:
                j += 1
            for m in range(i, j + 1):
                r[order[m]] = (i + j) / 2 + 1
            i = j + 1
        return r
    rx, ry = ranks(xs), ranks(ys)
    mx, my = sum(rx) / len(rx), sum(ry) / len(ry)
    sxy = sum((a - mx) * (b - my) for a, b in zip(rx, ry))
    sxx = sum((a - mx) ** 2 for a in rx)
    syy = sum((b - my) ** 2 for b in ry)
    return sxy / math.sqrt(sxx * syy) if sxx > 0 and syy > 0 else float("nan")


def pooled_rate(r, found_before):
    """P(goal at k | goal reached / not reached in episodes 1..k-1), pooled
    over every (condition, task, k >= 2)."""
    hits = n = 0
    for per_task in r["result"]["reached_goal"]:
        for eps in per_task:
            for k in range(1, len(eps)):
                if any(eps[:k]) == found_before:
                    n += 1
                    hits += eps[k]
    return hits / n if n else float("nan")


def fmt(ms):
    return f"{ms['mean']:.3f} ± {ms['se']:.3f}"


def main(folders):
    reports = load(folders)
    if not reports:
        sys.exit(f"no eval reports in {folders}")
    for (env, method, label, protocol), (f, r) in sorted(reports.items()):
        s = r["summary"]
        t = s["trend"]
        k = r["episodes"]
        name = f"{method} [{label}]" if label else method
        head = f"{env} {name} {protocol} (K={k}, {len(r['result']['conditions'])} conditions, {r['tasks']} tasks; {f.name})"
        print(head)
        gain, drop = t["return_gain"], t["cost_drop"]
        print(f"  return first {t['window']} eps {fmt(t['first_return'])} -> last {fmt(t['last_return'])}; "
              f"gain {fmt(gain)}: {'PASS' if gain['mean'] > 2 * gain['se'] else 'FAIL'}")
        print(f"  cost first {fmt(t['first_cost'])} -> last {fmt(t['last_cost'])}; "
              f"drop {fmt(drop)}: {'PASS' if drop['mean'] > 2 * drop['se'] else 'FAIL'}")
        if k > 1:
            (rs, rse), (cs, cse) = per_episode_slopes(r, "returns"), per_episode_slopes(r, "costs")
            print(f"  robustness: slope over all K episodes, return {rs:+.4f} ± {rse:.4f} per episode, "
                  f"cost {cs:+.4f} ± {cse:.4f} per episode")
        safe = t["last_cost"]["mean"] <= s["mean_budget"]
        last = s["per_episode"][-1]
        print(f"  last-window cost {t['last_cost']['mean']:.3f} vs mean budget {s['mean_budget']:.2f}: "
              f"{'PASS' if safe else 'FAIL'}; over-budget rate in episode K {fmt(last['violation'])}; "
              f"goal reached in episode K {fmt(last['success'])}")
        if method == "Eppo" and protocol == "figure1" and k > 1:
            # Issue 9's targets for the in-context learner.
            rs, rse = per_episode_slopes(r, "returns")
            within = 1 - last["violation"]["mean"]
            rev = pooled_rate(r, True)
            print(f"  issue 9: last-episode return {last['ret']['mean']:.3f} (>= 0.6: {'PASS' if last['ret']['mean'] >= 0.6 else 'FAIL'}); "
                  f"return slope {rs:+.4f} ± {rse:.4f} (> 3 s.e.: {'PASS' if rs > 3 * rse else 'FAIL'}); "
                  f"revisit {rev:.3f} (>= 0.9: {'PASS' if rev >= 0.9 else 'FAIL'}); discovery {pooled_rate(r, False):.3f}; "
                  f"within budget at episode K {within:.3f} (>= 0.9: {'PASS' if within >= 0.9 else 'FAIL'})")
        if method == "Ad" and protocol == "figure1" and k > 1:
            # Issue 11's targets for the supervised learner.
            rs, rse = per_episode_slopes(r, "returns")
            cs, cse = per_episode_slopes(r, "costs")
            rnd = reports.get((env, "Random", "", "figure1"))
            rnd_cost = rnd[1]["summary"]["trend"]["last_cost"]["mean"] if rnd else float("nan")
            print(f"  issue 11: return slope {rs:+.4f} ± {rse:.4f} (> 3 s.e.: {'PASS' if rs > 3 * rse else 'FAIL'}); "
                  f"cost slope {cs:+.4f} ± {cse:.4f} (< 0: {'PASS' if cs < 0 else 'FAIL'}); last-window cost "
                  f"{t['last_cost']['mean']:.3f} vs random {rnd_cost:.3f} ({'PASS' if t['last_cost']['mean'] < rnd_cost else 'FAIL'}); "
                  f"discovery {pooled_rate(r, False):.3f}, revisit {pooled_rate(r, True):.3f}")
        slope = s.get("total_return_slope")
        if protocol == "sweep" and slope:
            within = abs(slope["mean"]) <= 2 * slope["se"]
            if method == "Eppo":
                verdict = "PASS" if slope["mean"] > 2 * slope["se"] else "FAIL"
            elif method == "Ad":
                verdict = "PASS (no trend, as the paper)" if within else "FAIL (follows the budget, unlike the paper)"
            else:
                verdict = "baseline"
            print(f"  d total return / d CTG {fmt(slope)}; d max cost / d CTG {fmt(s['max_cost_slope'])}: {verdict}")
            if method == "Eppo":
                pts = [(c["condition"]["ctg"], c["total_return"]["mean"]) for c in s["per_condition"]]
                rho = spearman([p[0] for p in pts], [p[1] for p in pts])
                print(f"  issue 9: Spearman rho of total return on the budget {rho:.3f} over {len(pts)} budgets "
                      f"(>= 0.8: {'PASS' if rho >= 0.8 else 'FAIL'})")
        if r.get("parameters_checksum"):
            a, b = r["parameters_checksum"]
            print(f"  parameters frozen: {'yes' if a == b else 'NO'} (checksum {a:#x})")
    for (env, method, label, protocol), a in sorted(reports.items()):
        e = reports.get((env, "Eppo", "", "figure1"))
        if method == "Ad" and protocol == "figure1" and e:
            m = min(e[1]["episodes"], a[1]["episodes"])
            me, se_e = mean_se(early_returns(e[1], m))
            ma, se_a = mean_se(early_returns(a[1], m))
            diff, se = me - ma, math.sqrt(se_e ** 2 + se_a ** 2)
            print(f"{env}: mean return over episodes 1..{m}: EPPO {me:.3f} ± {se_e:.3f}, AD{' [' + label + ']' if label else ''} {ma:.3f} ± {se_a:.3f}; "
                  f"EPPO - AD {diff:.3f} ± {se:.3f}: {'PASS' if diff > 2 * se else 'FAIL'}")


if __name__ == "__main__":
    main(sys.argv[1:] or ["results/eval_darkroom"])
