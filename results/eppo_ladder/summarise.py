#!/usr/bin/env python3
"""Prints an EPPO metrics.jsonl in 8 windows: return (all, first and last
episode of a trajectory), cost, discovery and revisit rates, found fraction,
lambda, epsilon, entropy and updates/s. Standard library only."""
import json,sys,math
for path in sys.argv[1:]:
    recs=[json.loads(l) for l in open(path)]
    n=len(recs); w=max(1,n//8)
    print(path, n, "rounds")
    for i in range(0,n,w):
        ch=recs[i:i+w]
        def m(k):
            v=[r.get(k) for r in ch if r.get(k) is not None and not (isinstance(r.get(k),float) and math.isnan(r.get(k)))]
            return sum(v)/len(v) if v else float('nan')
        print(f"upd {ch[-1]['updates']:6d} steps {ch[-1]['env_steps']:8d} ret {m('episodic_return'):.2f} first {m('first_episode_return'):.2f} last {m('last_episode_return'):.2f} cost {m('episodic_cost'):.2f} lastc {m('last_episode_cost'):.2f} disc {m('discovery_rate'):.2f} rev {m('revisit_rate'):.2f} found {m('found_goal'):.2f} lam {m('lambda'):.3f} eps {m('charts/epsilon'):.2f} ent {m('losses/entropy'):.2f} ups {ch[-1]['charts/updates_per_s']:.2f}")
