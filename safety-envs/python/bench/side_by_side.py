"""Side-by-side timing of our Python environments and Safety-Gymnasium (issue 53).

Run through ``side_by_side.sh`` (beside this file), which builds and installs
both sides and calls this script in two roles:

``worker``  one timed measurement, in the interpreter of the side it times
            (``target/python-venv`` for ours, ``target/safety-gymnasium-venv``
            for Safety-Gymnasium); prints one JSON line.
``table``   medians over the repetitions, the Rust bench's figures and the
            ratios, as a Markdown table.

The shape timed (the paper's): episodes of 75 agent steps with random actions
and a reset between episodes, new task every 20 episodes (ours; Safety-
Gymnasium draws a new layout at every reset anyway). One agent step is 50
MuJoCo steps on both sides: ours holds the action for 50 physics steps;
for Safety-Gymnasium (10 physics steps per ``env.step``) it is 5 ``env.step``
calls with the same action. Safety-Gymnasium runs with all lidar off (the
paper's SafeDarkMujoco observes no lidar). ``stepping`` mode times steps only,
in one long episode without resets.

Actions come from a table of 1024 uniform random actions drawn before timing
(as in the Rust bench), so the figures do not include ``action_space.sample()``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

#: Agent steps per episode, episodes per task (the paper's Point and Car).
EPISODE_STEPS = 75
EPISODES_PER_TASK = 20
#: Safety-Gymnasium ``env.step`` calls per agent step (5 x 10 physics steps = 50).
SG_STEPS_PER_AGENT_STEP = 5

OURS_IDS = {"point": "SafeDarkMujocoPoint-v0", "car": "SafeDarkMujocoCar-v0"}
SG_IDS = {"point": "SafetyPointGoal1-v0", "car": "SafetyCarGoal1-v0"}


def _allow_ndarray_dataclass_defaults() -> None:
    """Lets Safety-Gymnasium 1.0.0 import on Python >= 3.11.

    Its asset classes are dataclasses with ``np.ndarray`` defaults (e.g.
    ``color: np.ndarray = np.array(...)``), which Python 3.11 refuses
    ("mutable default ... use default_factory"). This turns each such default
    into ``field(default_factory=default.copy)`` while the class is processed:
    every instance gets its own copy of the same value. Nothing else changes.
    Not needed (and not applied) on Python 3.10, the version the pins are for.
    """
    import dataclasses

    import numpy as np

    original = dataclasses._get_field

    def _get_field(cls, a_name, a_type, *args):
        default = cls.__dict__.get(a_name, dataclasses.MISSING)
        if isinstance(default, np.ndarray):
            setattr(cls, a_name, dataclasses.field(default_factory=default.copy))
        return original(cls, a_name, a_type, *args)

    dataclasses._get_field = _get_field


def _import_safety_gymnasium():
    if sys.version_info >= (3, 11):
        _allow_ndarray_dataclass_defaults()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import safety_gymnasium
    return safety_gymnasium


def _actions(dtype):
    import numpy as np

    return np.random.default_rng(42).uniform(-1.0, 1.0, (1024, 2)).astype(dtype)


class Ours:
    """``gymnasium.make`` of our environment, the user's path."""

    def __init__(self, robot: str, stepping: bool):
        import gymnasium
        import numpy as np

        import safety_envs

        kwargs = {"time_limit": 2**40} if stepping else {}
        self.env = gymnasium.make(OURS_IDS[robot], **kwargs)
        self.actions = _actions(np.float32)
        self.obs_dim = int(self.env.observation_space.shape[0])
        self.version = f"safety-envs {safety_envs.__version__}, gymnasium {gymnasium.__version__}"
        self.j = 0
        # The stepping task: edge-oriented seed 1, as the Rust bench's.
        first_task = {"seed": 1, "orientation": "edge"} if stepping else {"seed": 0}
        self.env.reset(seed=0, options={"task": first_task})

    def reset(self, episode: int) -> None:
        # A new task every EPISODES_PER_TASK episodes, as in the Rust bench.
        if episode % EPISODES_PER_TASK == 0:
            self.env.reset(options={"task": {"seed": episode // EPISODES_PER_TASK}})
        else:
            self.env.reset()

    def agent_step(self) -> bool:
        """One agent step (50 physics steps); whether the episode ended."""
        _, _, terminated, truncated, _ = self.env.step(self.actions[self.j & 1023])
        self.j += 1
        return terminated or truncated


class SafetyGymnasium:
    """``safety_gymnasium.make`` with lidar off and 5 steps per agent step."""

    def __init__(self, robot: str, stepping: bool):
        import gymnasium
        import mujoco
        import numpy as np

        sg = _import_safety_gymnasium()
        limit = 2**40 if stepping else EPISODE_STEPS * SG_STEPS_PER_AGENT_STEP
        self.env = sg.make(SG_IDS[robot], max_episode_steps=limit)
        task = self.env.unwrapped.task
        task.num_steps = limit  # the builder's own time limit (default 1000)
        # All lidar off (goal, hazards, vases), then the observation space
        # rebuilt, as Builder.__init__ builds it.
        for obstacle in task._obstacles:
            obstacle.is_lidar_observed = False
            if hasattr(obstacle, "is_comp_observed"):
                obstacle.is_comp_observed = False
        task.build_observation_space()
        self.obs_dim = int(self.env.observation_space.shape[0])
        obs, _ = self.env.reset(seed=0)
        assert obs.shape == (self.obs_dim,), (obs.shape, self.obs_dim)
        self.actions = _actions(np.float64)
        self.version = (
            f"safety-gymnasium {getattr(sg, '__version__', '?')}, gymnasium {gymnasium.__version__}, "
            f"mujoco {mujoco.__version__}"
        )
        self.j = 0

    def reset(self, episode: int) -> None:
        self.env.reset()

    def agent_step(self) -> bool:
        action = self.actions[self.j & 1023]
        self.j += 1
        for _ in range(SG_STEPS_PER_AGENT_STEP):
            _, _, _, terminated, truncated, _ = self.env.step(action)
            if terminated or truncated:
                return True
        return False


def _episodes(side, min_episodes: int, min_seconds: float) -> dict:
    """Paper shape: episodes until both minimums are met."""
    clock, cpu = time.perf_counter, time.process_time
    steps = episodes = 0
    reset_s = step_s = 0.0
    c0 = cpu()
    while episodes < min_episodes or reset_s + step_s < min_seconds:
        t0 = clock()
        side.reset(episodes)
        t1 = clock()
        n = 0
        while n < EPISODE_STEPS:
            n += 1
            if side.agent_step():
                break
        t2 = clock()
        reset_s += t1 - t0
        step_s += t2 - t1
        steps += n
        episodes += 1
    wall = reset_s + step_s
    return {
        "agent_steps": steps,
        "episodes": episodes,
        "seconds": wall,
        "cpu_seconds": cpu() - c0,
        "reset_seconds": reset_s,
        "step_seconds": step_s,
    }


def _stepping(side, min_seconds: float) -> dict:
    """Steps only, in one long episode (a reset only if the goal is reached)."""
    clock, cpu = time.perf_counter, time.process_time
    steps = resets = 0
    c0, t0 = cpu(), clock()
    while clock() - t0 < min_seconds:
        for _ in range(100):
            if side.agent_step():
                side.reset(1)
                resets += 1
        steps += 100
    wall = clock() - t0
    return {"agent_steps": steps, "episodes": resets, "seconds": wall, "cpu_seconds": cpu() - c0}


def worker(args) -> None:
    stepping = args.mode == "stepping"
    side = (Ours if args.side == "ours" else SafetyGymnasium)(args.robot, stepping)
    # Warm-up, untimed: one episode (or a second of steps).
    if stepping:
        _stepping(side, 1.0)
    else:
        side.reset(1)
        for _ in range(EPISODE_STEPS):
            if side.agent_step():
                break
    result = _stepping(side, args.min_seconds) if stepping else _episodes(side, args.min_episodes, args.min_seconds)
    result.update(
        side=args.side,
        robot=args.robot,
        mode=args.mode,
        rep=args.rep,
        rate=result["agent_steps"] / result["seconds"],
        cpu_rate=result["agent_steps"] / result["cpu_seconds"],
        obs_dim=side.obs_dim,
        python=sys.version.split()[0],
        version=side.version,
    )
    print(json.dumps(result), flush=True)


# ---------------------------------------------------------------- the table


def _rust_rates(logs: list[str]) -> dict:
    """The Rust bench's agent steps/s per (robot, mode), one list per log set.

    ``paper`` rows: "Point: paper shape, ... | 7549 agent steps/s ...";
    ``raw`` rows: "Point: agent steps/s, env vs raw C ... | CPU time ...; wall 7359 vs 7479 ...".
    """
    import re

    rates: dict = {}
    for path in logs:
        with open(path) as f:
            for line in f:
                m = re.match(r"\| (point|car): paper shape.*?\| (\d+) agent steps/s", line, re.I)
                if m:
                    rates.setdefault((m[1].lower(), "paper"), []).append(float(m[2]))
                m = re.match(r"\| (point|car): agent steps/s, env vs raw C.*?wall (\d+) vs", line, re.I)
                if m:
                    rates.setdefault((m[1].lower(), "stepping"), []).append(float(m[2]))
    return rates


def _fmt(x: float) -> str:
    return f"{x:,.0f}".replace(",", " ") if x >= 100 else f"{x:.1f}"


def table(args) -> None:
    rows = []
    with open(args.results) as f:
        for line in f:
            line = line.strip()
            if line.startswith("{"):
                rows.append(json.loads(line))
    rust = _rust_rates(args.rust_log)

    def pick(side, robot, mode):
        return [r for r in rows if r["side"] == side and r["robot"] == robot and r["mode"] == mode]

    def med(rs, key="rate"):
        return statistics.median(r[key] for r in rs) if rs else float("nan")

    out = []
    out.append(
        "| robot | shape | Rust bench | ours, Python | Safety-Gymnasium, Python "
        "| **ours / SG** (wall) | ours / SG (CPU time) | **Rust / Python** |"
    )
    out.append("|---|---|---|---|---|---|---|---|")
    notes = []
    for robot in ("point", "car"):
        for mode, label in (("paper", "paper shape (75-step episodes, resets)"), ("stepping", "stepping only")):
            ours, sg = pick("ours", robot, mode), pick("sg", robot, mode)
            r_ours, r_sg = med(ours), med(sg)
            c_ours, c_sg = med(ours, "cpu_rate"), med(sg, "cpu_rate")
            r_rust = statistics.median(rust[(robot, mode)]) if rust.get((robot, mode)) else float("nan")
            out.append(
                f"| {robot.capitalize()} | {label} | {_fmt(r_rust)} | {_fmt(r_ours)} | {_fmt(r_sg)} "
                f"| **{r_ours / r_sg:.1f}x** | {c_ours / c_sg:.1f}x | **{r_rust / r_ours:.2f}x** |"
            )
            if mode == "paper" and ours and sg:
                per_reset = lambda rs: statistics.median(r["reset_seconds"] / r["episodes"] for r in rs)  # noqa: E731
                share = lambda rs: statistics.median(r["reset_seconds"] / r["seconds"] for r in rs)  # noqa: E731
                notes.append(
                    f"- {robot.capitalize()}, paper shape: a reset costs {per_reset(ours) * 1e6:.0f} us in ours "
                    f"({share(ours):.1%} of the time) and {per_reset(sg) * 1e3:.1f} ms in Safety-Gymnasium "
                    f"({share(sg):.1%} of its time); episodes timed per repetition: ours "
                    f"{min(r['episodes'] for r in ours)}, Safety-Gymnasium {min(r['episodes'] for r in sg)}."
                )
    reps = sorted({r["rep"] for r in rows})
    info = {}
    for r in rows:
        info.setdefault(r["side"], set()).add((r["python"], r["version"]))
    dims = {(r["side"], r["robot"]): r["obs_dim"] for r in rows}
    notes.append(
        f"- Median of {len(reps)} repetitions (interleaved: ours and Safety-Gymnasium, Point and Car, in turn); "
        f"the Rust column is the median over the same rounds of the bench's best-of-3 (paper shape) or "
        f"best-of-15 (stepping) figure."
    )
    notes.append(
        "- Observation sizes: ours Point "
        f"{dims.get(('ours', 'point'))}, Car {dims.get(('ours', 'car'))}; Safety-Gymnasium with lidar off Point "
        f"{dims.get(('sg', 'point'))}, Car {dims.get(('sg', 'car'))}."
    )
    for side, label in (("ours", "ours"), ("sg", "Safety-Gymnasium")):
        for py, version in sorted(info.get(side, ())):
            notes.append(f"- {label}: Python {py}, {version}.")
    text = "\n".join(out + [""] + notes) + "\n"
    if args.header:
        text = args.header.rstrip() + "\n\n" + text
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    w = sub.add_parser("worker", help="one timed measurement (prints a JSON line)")
    w.add_argument("--side", choices=("ours", "sg"), required=True)
    w.add_argument("--robot", choices=("point", "car"), required=True)
    w.add_argument("--mode", choices=("paper", "stepping"), required=True)
    w.add_argument("--rep", type=int, default=0)
    w.add_argument("--min-episodes", type=int, default=20)
    w.add_argument("--min-seconds", type=float, default=3.0)
    sub.add_parser("check", help="import Safety-Gymnasium and make both tasks with lidar off")
    t = sub.add_parser("table", help="the Markdown table from the workers' JSON lines and the Rust logs")
    t.add_argument("--results", required=True)
    t.add_argument("--rust-log", action="append", default=[])
    t.add_argument("--header", default="")
    t.add_argument("--out")
    args = p.parse_args()
    if args.command == "worker":
        worker(args)
    elif args.command == "check":
        for robot in ("point", "car"):
            side = SafetyGymnasium(robot, stepping=False)
            print(f"{SG_IDS[robot]}: lidar off, {side.obs_dim} observations ({side.version})")
    else:
        table(args)


if __name__ == "__main__":
    main()
