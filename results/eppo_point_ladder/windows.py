import json,sys
from rung_windows import window_mean
# Means of a run's training metrics over windows of updates.
# usage: python3 windows.py metrics.jsonl [window_updates (200)] [goal_slots|hazard_slots]
# goal_slots: a goal-slot run's keys (the hidden share, the hidden/shown split) instead;
# hazard_slots: a hazard-map run's (the hidden share, the cost and return of each kind).
path=sys.argv[1]; w=int(sys.argv[2]) if len(sys.argv)>2 else 200
recs=[json.loads(l) for l in open(path)]
keys=['revisit_rate','search_new_cells','episodic_return','last_episode_return','episodic_cost','losses/q_mean','charts/action_saturated','losses/entropy','entropy_coef','lambda','losses/novelty_q_mean']
if len(sys.argv)>3 and sys.argv[3]=='goal_slots':
    keys=['goal_hidden_share','shown_goal_return','hidden_goal_return','hidden_goal_revisit_rate','revisit_rate','found_goal','search_new_cells','episodic_cost','losses/goal_recall']
if len(sys.argv)>3 and sys.argv[3]=='hazard_slots':
    keys=['goal_hidden_share','shown_slots_cost','hidden_slots_cost','shown_goal_return','hidden_goal_return','revisit_rate','found_goal','search_new_cells','lambda']
print('upd_to  env_steps '+' '.join(k.split('/')[-1][:9].rjust(9) for k in keys))
b=0
while b < recs[-1]['updates']:
    ch=[r for r in recs if b < r['updates'] <= b+w]
    b+=w
    if not ch: continue
    print(f"{ch[-1]['updates']:6d} {ch[-1]['env_steps']:9d} "+' '.join(f"{window_mean(ch,k,b-w,b):9.3f}" for k in keys))
