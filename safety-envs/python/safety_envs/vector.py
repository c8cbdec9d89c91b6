"""The vector form: ``gymnasium.vector.VectorEnv`` over the Rust ``VecEnv``.

All environments step in one call into Rust, on its own threads, with the GIL
released while the physics runs. Episodes that end are reset within the same
step (Gymnasium's ``AutoresetMode.SAME_STEP``): ``info["final_obs"]`` holds the
last observation of those environments and ``info["final_info"]`` their last
info, each with its ``_``-mask.
"""

from __future__ import annotations

import os

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from safety_envs import _native
from safety_envs.env import ENV_CLASSES, ENV_NAMES, _resolve_task, _space, _task_dict


class SafetyVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` copies of environment ``env_id`` (``"SafeDarkRoom-v0"``,
    ``"SafeDarkMujocoPoint-v0"``, ``"SafeDarkMujocoCar-v0"``).

    Args:
        num_threads: threads stepping the batch (default: the CPU count, at
            most ``num_envs``); SafeDarkRoom's steps are too cheap to hand to
            a thread and stay on the calling one.
        task: the first task of every environment (see ``safety_envs.env``);
            ``reset(options={"task": t})`` sets ``t`` for all, or a list of
            ``num_envs`` tasks one each.
        safety_step, time_limit, physics_steps_per_action: as for the
            single environment.

    The costs are in ``info["cost"]`` (a ``(num_envs,)`` array).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        *,
        num_threads: int | None = None,
        task: dict | list | None = None,
        safety_step: bool = False,
        time_limit: int | None = None,
        physics_steps_per_action: int | None = None,
    ):
        if env_id not in ENV_NAMES:
            raise ValueError(f"unknown environment id {env_id!r}; valid: {sorted(ENV_NAMES)}")
        self._name = ENV_NAMES[env_id]
        threads = num_threads if num_threads is not None else (os.cpu_count() or 1)
        self._vec = _native.VecEnv(self._name, num_envs, threads, time_limit, physics_steps_per_action)
        self.num_envs = num_envs
        self.render_mode = None
        self.spec = gym.spec(env_id) if env_id in gym.registry else None
        native_single = _native.Env(self._name, time_limit, physics_steps_per_action)
        self.single_observation_space = _space(native_single.observation_space)
        self.single_action_space = _space(native_single.action_space)
        native_single.close()
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._discrete = isinstance(self.single_action_space, gym.spaces.Discrete)
        self._safety_step = bool(safety_step)
        self._env_class = ENV_CLASSES[env_id]
        if task is not None:
            self.set_task(task)

    def tasks(self) -> list[dict]:
        """Each environment's current task."""
        return [_task_dict(self._vec.task(i)) for i in range(self.num_envs)]

    def set_task(self, task: dict | list) -> None:
        """Sets one task for every environment, or a list of one per
        environment; kept across resets."""
        tasks = task if isinstance(task, list) else [task] * self.num_envs
        if len(tasks) != self.num_envs:
            raise ValueError(f"{len(tasks)} tasks for {self.num_envs} environments")
        for i, t in enumerate(tasks):
            goal, hazards = _resolve_task(self._name, t)
            self._vec.set_task(i, goal, hazards)

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        """Resets every environment: ``seed`` an int gives environment ``i``
        the seed ``seed + i``, a list one each; later episodes (auto-reset)
        draw their seeds from these."""
        if isinstance(seed, int):
            super().reset(seed=seed)
            seeds = [seed + i for i in range(self.num_envs)]
        elif seed is not None:
            super().reset(seed=None)
            seeds = [int(s) for s in seed]
        else:
            super().reset(seed=None)
            seeds = [int(s) for s in self.np_random.integers(2**63, size=self.num_envs)]
        if options and "task" in options:
            self.set_task(options["task"])
        return self._vec.reset(seeds), {}

    def step(self, actions):
        if self._discrete:
            actions = np.asarray(actions, dtype=np.int64)
        else:
            actions = np.asarray(actions, dtype=np.float32)
        obs, reward, cost, terminated, truncated, final_obs = self._vec.step(actions)
        info = {"cost": cost, "_cost": np.ones(self.num_envs, dtype=bool)}
        done = terminated | truncated
        if done.any():
            last = np.empty(self.num_envs, dtype=object)
            for i in np.flatnonzero(done):
                last[i] = final_obs[i]
            info["final_obs"] = last
            info["_final_obs"] = done
            info["final_info"] = {"cost": np.where(done, cost, 0.0).astype(np.float32), "_cost": done}
            info["_final_info"] = done
        if self._safety_step:
            return obs, reward, cost, terminated, truncated, info
        return obs, reward, terminated, truncated, info

    def close_extras(self, **kwargs):
        self._vec.close()


def make_vector(num_envs: int = 1, *, env_id: str, **kwargs) -> SafetyVectorEnv:
    """The vector entry point ``gymnasium.make_vec`` calls."""
    return SafetyVectorEnv(env_id, num_envs, **kwargs)
