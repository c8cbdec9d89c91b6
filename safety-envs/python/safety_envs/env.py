"""The three environments as ``gymnasium.Env`` subclasses over the Rust core.

A *task* is where the goal and the hazards are, on the environment's task grid
(SafeDarkRoom 9x9 with 25 hazards; Point and Car 5x5 with 8), the agent always
starting at the centre cell. It is kept across resets, so one task can be played
for K episodes, as in-context RL does. Give it as any of

- ``{"seed": 3, "orientation": "edge"}``: drawn from the paper's centre- (the
  default, pretraining) or edge-oriented (evaluation) distribution;
- ``{"goal": (row, col), "hazards": [(row, col), ...]}``: placed by hand;
- what :attr:`SafetyEnv.task` returns,

through ``reset(options={"task": task})`` or :meth:`SafetyEnv.set_task`.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from safety_envs import _native

#: Environment ids and the Rust names behind them.
ENV_NAMES = {
    "SafeDarkRoom-v0": "darkroom",
    "SafeDarkMujocoPoint-v0": "point",
    "SafeDarkMujocoCar-v0": "car",
}


def sample_task(env: str, seed: int, orientation: str = "centre") -> dict:
    """The task of ``env`` (an id such as ``"SafeDarkRoom-v0"`` or a name:
    ``darkroom``, ``point``, ``car``) drawn from ``seed``, ``orientation``
    ``"centre"`` or ``"edge"``, as ``{"grid_size", "goal", "hazards"}``."""
    return _task_dict(_native.sample_task(ENV_NAMES.get(env, env), orientation, seed))


def _task_dict(native: tuple) -> dict:
    grid_size, goal, hazards = native
    return {"grid_size": grid_size, "goal": tuple(goal), "hazards": [tuple(h) for h in hazards]}


def _resolve_task(name: str, task: Any) -> tuple[tuple[int, int], list[tuple[int, int]]]:
    """``task`` (see the module documentation) as ``(goal, hazards)``."""
    if not isinstance(task, dict):
        raise TypeError(
            f"a task is a dict, {{'seed': N, 'orientation': 'centre'|'edge'}} or "
            f"{{'goal': (row, col), 'hazards': [(row, col), ...]}}; got {task!r}"
        )
    if "seed" in task:
        unknown = set(task) - {"seed", "orientation"}
        if unknown:
            raise ValueError(f"a task drawn from a seed takes 'seed' and 'orientation' only, not {sorted(unknown)}")
        task = sample_task(name, int(task["seed"]), task.get("orientation", "centre"))
    if "goal" not in task or "hazards" not in task:
        raise ValueError(f"a task needs 'seed', or 'goal' and 'hazards'; got keys {sorted(task)}")
    goal = tuple(int(v) for v in task["goal"])
    hazards = [tuple(int(v) for v in h) for h in task["hazards"]]
    return goal, hazards


def _space(native: tuple) -> spaces.Space:
    kind, n, low, high = native
    if kind == "discrete":
        return spaces.Discrete(n)
    return spaces.Box(np.asarray(low, dtype=np.float32), np.asarray(high, dtype=np.float32), dtype=np.float32)


class SafetyEnv(gym.Env):
    """One of the environments (see the subclasses).

    Args:
        render_mode: ``None`` or ``"rgb_array"`` (a top-down picture,
            ``(height, width, 3)`` uint8, drawn headless).
        task: the first task (see the module documentation); default the
            centre-oriented task of seed 0.
        safety_step: ``True`` makes :meth:`step` return Safety-Gymnasium's
            six-tuple ``(obs, reward, cost, terminated, truncated, info)``
            instead of Gymnasium's five-tuple. Through ``gymnasium.make`` add
            ``disable_env_checker=True``: Gymnasium's checker wants five.
        time_limit: the time limit in agent steps (default 30 for
            SafeDarkRoom, 75 for Point and Car), after which the environment
            truncates the episode itself. (``gymnasium.make``'s own
            ``max_episode_steps`` adds Gymnasium's ``TimeLimit`` wrapper on
            top, which cannot lengthen an episode.)
        physics_steps_per_action: Point and Car, MuJoCo physics steps per
            agent action (default 50, the paper's macro action).
        width, height: the size of rendered pictures.

    The cost of every step is in ``info["cost"]`` (1.0 for a step that ends
    in, or for the robots passes through, a hazard).
    """

    #: The Rust environment's name, set by each subclass.
    _name: str = ""
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        render_mode: str | None = None,
        *,
        task: dict | None = None,
        safety_step: bool = False,
        time_limit: int | None = None,
        physics_steps_per_action: int | None = None,
        width: int = 256,
        height: int = 256,
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r} is not one of {self.metadata['render_modes']} or None")
        self.render_mode = render_mode
        self._env = _native.Env(self._name, time_limit, physics_steps_per_action)
        self.observation_space = _space(self._env.observation_space)
        self.action_space = _space(self._env.action_space)
        self._discrete = isinstance(self.action_space, spaces.Discrete)
        self._safety_step = bool(safety_step)
        self._size = (int(width), int(height))
        if task is not None:
            self.set_task(task)

    @property
    def task(self) -> dict:
        """The current task, ``{"grid_size", "goal", "hazards"}``."""
        return _task_dict(self._env.task())

    def set_task(self, task: dict) -> None:
        """Places the goal and hazards for the following episodes (kept across
        resets); call :meth:`reset` next, since the agent stays where it is."""
        goal, hazards = _resolve_task(self._name, task)
        self._env.set_task(goal, hazards)

    @property
    def max_episode_steps(self) -> int:
        """The time limit in agent steps."""
        return self._env.max_episode_steps

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Starts an episode in the current task; ``options={"task": ...}``
        sets a new task first (kept for the following resets)."""
        super().reset(seed=seed)
        if options and "task" in options:
            self.set_task(options["task"])
        # The episode's seed: the one given, else the next from the
        # environment's generator (seeded once by the first seeded reset).
        episode_seed = seed if seed is not None else int(self.np_random.integers(2**63))
        obs = self._env.reset(episode_seed)
        return obs, {}

    def step(self, action):
        if not self._discrete:
            # No copy when the action already is float32; NaN, infinity and a
            # wrong shape are refused by the Rust side with its message.
            action = np.asarray(action, dtype=np.float32)
        obs, reward, cost, terminated, truncated = self._env.step(action)
        info = {"cost": cost}
        if self._safety_step:
            return obs, reward, cost, terminated, truncated, info
        return obs, reward, terminated, truncated, info

    def render(self):
        """With ``render_mode="rgb_array"``: the current state seen from
        above, ``(height, width, 3)`` uint8 (robot red, goal green, hazards
        blue); else ``None``."""
        if self.render_mode != "rgb_array":
            gym.logger.warn("render() called without render_mode='rgb_array'; nothing drawn")
            return None
        width, height = self._size
        return self._env.render(width, height)

    def close(self):
        """Frees the simulation; later calls raise ``RuntimeError``."""
        self._env.close()


class SafeDarkRoomEnv(SafetyEnv):
    """SafeDarkRoom: a dark 9x9 grid, 5 actions (stay, up, down, left, right),
    the observation the agent's own cell ``(row, col)``; reward 1 and the end
    of the episode at the goal, cost 1 per step ending on a hazard, 30 steps."""

    _name = "darkroom"


class SafeDarkMujocoPointEnv(SafetyEnv):
    """SafeDarkMujoco Point: Safety-Gymnasium's Point robot, all lidar off
    (23 observations of its own state), actions in [-1, 1]^2, each held for
    50 physics steps; reward 1 and the end of the episode at the goal, cost 1
    per step through a hazard, 75 agent steps."""

    _name = "point"


class SafeDarkMujocoCarEnv(SafetyEnv):
    """SafeDarkMujoco Car: Safety-Gymnasium's Car robot, all lidar off (35
    observations), wheel torques in [-1, 1]^2, otherwise as Point."""

    _name = "car"


ENV_CLASSES = {
    "SafeDarkRoom-v0": SafeDarkRoomEnv,
    "SafeDarkMujocoPoint-v0": SafeDarkMujocoPointEnv,
    "SafeDarkMujocoCar-v0": SafeDarkMujocoCarEnv,
}
