"""Draw the K episodes of an evaluation's --render recording: the robot's path, hazards
(purple), goal (green), the arrivals that paid a cost (red x).
Usage: paths.py EVAL.json OUT.png  (needs matplotlib)"""
import json,sys,glob
import matplotlib; matplotlib.use('Agg')
import matplotlib.pyplot as plt
path,out=sys.argv[1],sys.argv[2]
d=json.load(open(path)); r=d['result']; rec=r['recording']
task=r['tasks'][rec['task']]
sp,ext=0.75,1.5
cxy=lambda c:(-ext+c[1]*sp, ext-c[0]*sp)
K=len(rec['episodes'])
fig,axes=plt.subplots(2,(K+1)//2,figsize=(3*((K+1)//2),6))
for k,(ax,ep) in enumerate(zip(axes.flat,rec['episodes'])):
    for o in task['obstacles']:
        ax.add_patch(plt.Circle(cxy(o),0.2,color='purple',alpha=0.4))
    ax.add_patch(plt.Circle(cxy(task['goal']),0.3,color='green',alpha=0.4))
    xs=[o[0] for o in ep['observations']]; ys=[o[1] for o in ep['observations']]
    ax.plot(xs,ys,'-',lw=1); ax.plot(xs[0],ys[0],'ko',ms=3)
    cx=[xs[i+1] for i,c in enumerate(ep['costs']) if c>0]; cy=[ys[i+1] for i,c in enumerate(ep['costs']) if c>0]
    ax.plot(cx,cy,'rx',ms=4)
    ax.set_xlim(-2,2); ax.set_ylim(-2,2); ax.set_aspect('equal'); ax.set_xticks([]); ax.set_yticks([])
    ax.set_title(f"k={k+1} R={sum(ep['rewards']):.0f} C={sum(ep['costs']):.0f}",fontsize=8)
plt.tight_layout(); plt.savefig(out,dpi=70)
