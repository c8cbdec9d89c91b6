"""SafeDarkRoom and SafeDarkMujoco Point and Car, from safe in-context RL, as
Gymnasium environments on a Rust core.

Importing the package registers

- ``SafeDarkRoom-v0``
- ``SafeDarkMujocoPoint-v0``
- ``SafeDarkMujocoCar-v0``

with ``gymnasium.make`` and, for the vector form on Rust threads,
``gymnasium.make_vec``. See :class:`safety_envs.env.SafetyEnv` for the options
(the task, the Safety-Gymnasium six-tuple step, rendering) and
:class:`safety_envs.vector.SafetyVectorEnv` for the vector form.
"""

from functools import partial

import gymnasium as gym

from safety_envs._native import __version__
from safety_envs.env import (
    ENV_NAMES,
    SafeDarkMujocoCarEnv,
    SafeDarkMujocoPointEnv,
    SafeDarkRoomEnv,
    SafetyEnv,
    sample_task,
)
from safety_envs.vector import SafetyVectorEnv, make_vector

__all__ = [
    "__version__",
    "ENV_NAMES",
    "SafeDarkMujocoCarEnv",
    "SafeDarkMujocoPointEnv",
    "SafeDarkRoomEnv",
    "SafetyEnv",
    "SafetyVectorEnv",
    "sample_task",
]

_ENTRY_POINTS = {
    "SafeDarkRoom-v0": "safety_envs.env:SafeDarkRoomEnv",
    "SafeDarkMujocoPoint-v0": "safety_envs.env:SafeDarkMujocoPointEnv",
    "SafeDarkMujocoCar-v0": "safety_envs.env:SafeDarkMujocoCarEnv",
}

for _id, _entry in _ENTRY_POINTS.items():
    if _id not in gym.registry:
        gym.register(
            id=_id,
            entry_point=_entry,
            vector_entry_point=partial(make_vector, env_id=_id),
        )
