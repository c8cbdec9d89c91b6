"""The in-context task API: set from a seed or by hand, kept across resets."""

import gymnasium as gym
import numpy as np
import pytest

import safety_envs
from conftest import make


def test_task_from_options_is_kept_across_resets(env_id):
    env = make(env_id)
    task = safety_envs.sample_task(env_id, 11, "edge")
    env.reset(seed=0, options={"task": {"seed": 11, "orientation": "edge"}})
    assert env.task == task
    for _ in range(3):
        env.reset()
        assert env.task == task
    env.close()


def test_set_task_by_hand_and_through_wrappers():
    env = gym.make("SafeDarkRoom-v0")
    hazards = [(r, c) for r in (6, 7, 8) for c in range(9)][:25]
    env.unwrapped.set_task({"goal": (0, 0), "hazards": hazards})
    env.reset(seed=1)
    assert env.unwrapped.task == {"grid_size": 9, "goal": (0, 0), "hazards": hazards}
    # The task dict round-trips.
    env.reset(options={"task": env.unwrapped.task})
    assert env.unwrapped.task["goal"] == (0, 0)
    env.close()


def test_a_task_per_seed_and_orientation():
    centre = [safety_envs.sample_task("darkroom", s, "centre") for s in range(40)]
    edge = [safety_envs.sample_task("darkroom", s, "edge") for s in range(40)]
    assert centre[0] == safety_envs.sample_task("SafeDarkRoom-v0", 0)  # centre is the default
    assert len({str(t) for t in centre}) > 30, "seeds give different tasks"

    def mean_goal_distance(tasks):
        return np.mean([np.hypot(t["goal"][0] - 4, t["goal"][1] - 4) for t in tasks])

    # Edge-oriented goals lie further from the start than centre-oriented ones.
    assert mean_goal_distance(edge) > mean_goal_distance(centre) + 0.5


def test_a_bad_task_is_refused_with_the_rust_message():
    env = make("SafeDarkMujocoPoint-v0")
    hazards = safety_envs.sample_task("point", 0)["hazards"]
    with pytest.raises(ValueError, match="off the centre"):
        env.set_task({"goal": (2, 2), "hazards": hazards})
    with pytest.raises(ValueError, match="the environment expects 8"):
        env.set_task({"goal": (0, 0), "hazards": hazards[:3]})
    with pytest.raises(ValueError, match="unknown orientation"):
        env.reset(options={"task": {"seed": 1, "orientation": "middle"}})
    env.close()
