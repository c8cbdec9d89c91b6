"""The Python loop against the Rust environment alone, step for step."""

import numpy as np

import safety_envs
from safety_envs import _native
from conftest import make


def random_actions(env, steps, seed):
    rng = np.random.default_rng(seed)
    if env.action_space.shape == ():
        return rng.integers(0, 5, size=(steps, 1)).astype(np.float32)
    return rng.uniform(-1, 1, size=(steps, 2)).astype(np.float32)


def python_rollout(env, task, seed, actions, discrete):
    obs0, _ = env.reset(seed=seed, options={"task": task})
    rows = []
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(int(a[0]) if discrete else a)
        rows.append((obs, reward, info["cost"], terminated, truncated))
        if terminated or truncated:
            env.reset(seed=seed)
    return obs0, rows


def test_same_as_rust_step_for_step(env_id):
    name = safety_envs.ENV_NAMES[env_id]
    # Short episodes so that several ends (and resets) are crossed.
    env = make(env_id, time_limit=12)
    discrete = env.action_space.shape == ()
    for task_seed, orientation in [(1, "centre"), (2, "edge")]:
        task = safety_envs.sample_task(env_id, task_seed, orientation)
        actions = random_actions(env, 60, task_seed)
        obs0, rows = python_rollout(env, task, 7, actions, discrete)
        ref = _native.rust_rollout(name, task["goal"], task["hazards"], 7, actions, 12)
        first, ref_obs, ref_reward, ref_cost, ref_term, ref_trunc = ref
        np.testing.assert_array_equal(obs0, first)
        assert len(rows) == len(ref_obs) == 60
        for t, (obs, reward, cost, terminated, truncated) in enumerate(rows):
            np.testing.assert_array_equal(obs, np.asarray(ref_obs[t], dtype=np.float32), err_msg=f"step {t}")
            assert (reward, cost, terminated, truncated) == (
                ref_reward[t],
                ref_cost[t],
                ref_term[t],
                ref_trunc[t],
            ), f"step {t}"
        assert any(r[3] or r[4] for r in rows), "no episode ended: the resets went untested"
    env.close()


def test_seeded_runs_repeat_bitwise(env_id):
    def run():
        env = make(env_id)
        env.reset(seed=3, options={"task": {"seed": 5, "orientation": "edge"}})
        env.action_space.seed(3)
        out = []
        for _ in range(40):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            out.append((obs.tobytes(), reward, info["cost"], terminated, truncated))
            if terminated or truncated:
                env.reset()
        env.close()
        return out

    assert run() == run()
