"""Windows of a goal-slot run's training metrics (goal_hidden_share and the hidden/shown
split, besides the pooled revisit, found and search rates).

    python3 goal_slots.py RUN/metrics.jsonl [window_updates (250)]
"""
import json,sys,math
path=sys.argv[1]; w=int(sys.argv[2]) if len(sys.argv)>2 else 250
recs=[json.loads(l) for l in open(path)]
keys=['goal_hidden_share','shown_goal_return','hidden_goal_return','hidden_goal_revisit_rate','revisit_rate','found_goal','search_new_cells','episodic_cost','losses/goal_recall']
print('upd_to  env_steps '+' '.join(k.split('/')[-1][:9].rjust(9) for k in keys))
b=0
while b < recs[-1]['updates']:
    ch=[r for r in recs if b < r['updates'] <= b+w]
    b+=w
    if not ch: continue
    def m(k):
        v=[r.get(k) for r in ch if isinstance(r.get(k),(int,float)) and not math.isnan(r.get(k))]
        return sum(v)/len(v) if v else float('nan')
    print(f"{ch[-1]['updates']:6d} {ch[-1]['env_steps']:9d} "+' '.join(f"{m(k):9.3f}" for k in keys))
