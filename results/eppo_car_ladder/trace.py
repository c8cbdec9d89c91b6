"""Read the trajectory an `icrl eval --render` recorded (robots), episode by
episode: return, cost, steps, the longest run of consecutive costly steps and
how far the robot's centre moved during it (a run of many costly steps over a
few centimetres is a robot turning on the spot inside a hazard), and the
closest it came to the goal.

    python3 trace.py EVAL_DIR/eppo_LABEL_car.json [--steps K]

--steps K also prints every third step of episode K (1-based): position,
distances to the goal and to the nearest hazard, action, cost.
"""
import json
import sys

import numpy as np

path = sys.argv[1]
show = int(sys.argv[sys.argv.index("--steps") + 1]) if "--steps" in sys.argv else None
result = json.load(open(path))["result"]
rec = result["recording"]
task = result["tasks"][rec["task"]]
budget = result["conditions"][rec["condition"]]["ctg"]
# Cell (row, column) to metres, as safety-envs/src/nav.rs lays out the 5x5 arena.
SPACING, EXTENT = 0.75, 1.5
cell_xy = lambda c: np.array((-EXTENT + c[1] * SPACING, EXTENT - c[0] * SPACING))
goal = cell_xy(task["goal"])
hazards = np.array([cell_xy(o) for o in task["obstacles"]])
print(f"task {rec['task']} (goal cell {task['goal']}), budget {budget:.2f}")
for k, ep in enumerate(rec["episodes"]):
    xy = np.array(ep["observations"])[:, :2]
    costs = np.array(ep["costs"])
    run, best, best_end = 0, 0, 0
    for t, c in enumerate(costs):
        run = run + 1 if c > 0 else 0
        if run > best:
            best, best_end = run, t + 1
    moved = np.linalg.norm(np.diff(xy[best_end - best : best_end + 1], axis=0), axis=1).sum() if best else 0.0
    print(
        f"k={k + 1:2d}  return {sum(ep['rewards']):.0f}  cost {costs.sum():3.0f}  steps {len(costs):2d}"
        f"  longest costly run {best:2d} steps over {moved:.2f} m"
        f"  closest to goal {np.linalg.norm(xy - goal, axis=1).min():.2f} m"
    )
    if show == k + 1:
        d_goal = np.linalg.norm(xy - goal, axis=1)
        d_hazard = np.min(np.linalg.norm(xy[:, None] - hazards[None], axis=2), axis=1)
        for t in range(0, len(xy), 3):
            a = ep["actions"][min(t, len(ep["actions"]) - 1)]
            c = costs[t - 1] if t else 0
            print(
                f"   t{t:2d} ({xy[t, 0]:+.2f}, {xy[t, 1]:+.2f})  goal {d_goal[t]:.2f}  hazard {d_hazard[t]:.2f}"
                f"  action ({a[0]:+.2f}, {a[1]:+.2f})  cost {c:.0f}"
            )
