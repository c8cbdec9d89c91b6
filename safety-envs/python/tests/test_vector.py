"""The vector form on the Rust VecEnv: same results as single environments, GIL released."""

import sys
import threading

import gymnasium as gym
import numpy as np
import pytest

import safety_envs
from conftest import make


@pytest.mark.parametrize("env_id", ["SafeDarkRoom-v0", "SafeDarkMujocoPoint-v0"])
def test_vector_equals_single_environments(env_id):
    n, steps = 3, 40
    tasks = [safety_envs.sample_task(env_id, s, "centre") for s in range(n)]
    vec = gym.make_vec(env_id, num_envs=n, num_threads=2, time_limit=10)
    assert isinstance(vec, safety_envs.SafetyVectorEnv)
    obs, _ = vec.reset(seed=5, options={"task": tasks})
    assert vec.tasks() == tasks
    singles = [make(env_id, time_limit=10, task=t) for t in tasks]
    single_obs = np.stack([e.reset(seed=5 + i)[0] for i, e in enumerate(singles)])
    np.testing.assert_array_equal(obs, single_obs)
    vec.action_space.seed(0)
    ended = 0
    for t in range(steps):
        actions = vec.action_space.sample()
        obs, reward, terminated, truncated, info = vec.step(actions)
        assert obs.shape == (n,) + vec.single_observation_space.shape
        for i, e in enumerate(singles):
            o, r, te, tr, inf = e.step(actions[i])
            assert (reward[i], info["cost"][i], terminated[i], truncated[i]) == (r, inf["cost"], te, tr), (t, i)
            if te or tr:
                ended += 1
                # Same-step auto-reset: the last observation is in info.
                assert info["_final_obs"][i]
                np.testing.assert_array_equal(info["final_obs"][i], o)
                o, _ = e.reset()
            np.testing.assert_array_equal(obs[i], o)
    assert ended > 0
    vec.close()
    for e in singles:
        e.close()


def test_vector_errors_carry_the_rust_message():
    vec = safety_envs.SafetyVectorEnv("SafeDarkMujocoCar-v0", 2, num_threads=2)
    vec.reset(seed=0)
    with pytest.raises(ValueError, match="environment 1: invalid action"):
        vec.step(np.array([[0.0, 0.0], [np.inf, 0.0]], np.float32))
    with pytest.raises(ValueError, match=r"actions of shape \[3, 2\] for 2 environments"):
        vec.step(np.zeros((3, 2), np.float32))
    vec.close()
    with pytest.raises(RuntimeError, match="closed"):
        vec.step(np.zeros((2, 2), np.float32))


def test_physics_runs_without_the_gil():
    """A Python thread keeps counting while the robots step."""
    # 2000 physics steps per action: tens of milliseconds a step.
    vec = safety_envs.SafetyVectorEnv("SafeDarkMujocoCar-v0", 2, num_threads=2, physics_steps_per_action=2000)
    vec.reset(seed=0)
    single = make("SafeDarkMujocoCar-v0", physics_steps_per_action=2000)
    single.reset(seed=0)
    counter = [0]
    stop = threading.Event()

    def count():
        while not stop.is_set():
            counter[0] += 1

    old = sys.getswitchinterval()
    # Long forced switches: a thread holding the GIL in Rust would keep the
    # counter still for the whole call; only a released GIL lets it run.
    sys.setswitchinterval(0.5)
    thread = threading.Thread(target=count)
    thread.start()
    try:
        for step in (
            lambda: vec.step(np.zeros((2, 2), np.float32)),
            lambda: single.step(np.zeros(2, np.float32)),
        ):
            before = counter[0]
            step()
            assert counter[0] > before, "the counting thread did not run during the step"
    finally:
        stop.set()
        sys.setswitchinterval(old)
        thread.join()
    vec.close()
    single.close()
