import json,sys,math
for path in sys.argv[1:]:
    recs=[json.loads(l) for l in open(path)]
    n=len(recs); w=max(1,n//10)
    ks=['episodic_return','episodic_cost','losses/value_loss','losses/policy_loss','losses/q_mean','losses/target_mean','losses/log_std_mean','losses/entropy','charts/action_abs','charts/action_saturated','losses/grad_norm']
    print(path,n,'rounds'); print('upd    '+' '.join(k.split('/')[-1][:9].rjust(9) for k in ks))
    for i in range(0,n,w):
        ch=recs[i:i+w]
        def m(k):
            v=[r.get(k) for r in ch if r.get(k) is not None and not (isinstance(r.get(k),float) and math.isnan(r.get(k)))]
            return sum(v)/len(v) if v else float('nan')
        print(f"{ch[-1]['updates']:6d} "+' '.join(f"{m(k):9.3f}" for k in ks))
