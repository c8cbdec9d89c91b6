"""A plain tabular Q-learning agent on SafeDarkRoom with a fixed task reaches the goal."""

import gymnasium as gym
import numpy as np

import safety_envs


def test_q_learning_reaches_the_goal():
    task = safety_envs.sample_task("SafeDarkRoom-v0", 4, "edge")
    env = gym.make("SafeDarkRoom-v0", task=task)
    rng = np.random.default_rng(0)
    # Optimistic values (the largest return is 1): untried actions look best,
    # so the agent explores systematically rather than by chance alone.
    q = np.ones((9, 9, 5))
    alpha, gamma, epsilon = 0.5, 0.95, 0.2
    env.reset(seed=0)
    for _ in range(400):
        obs, _ = env.reset()
        done = False
        while not done:
            s = tuple(obs.astype(int))
            best = np.flatnonzero(q[s] == q[s].max())
            a = int(rng.integers(5)) if rng.random() < epsilon else int(rng.choice(best))
            obs, reward, terminated, truncated, info = env.step(a)
            target = reward + (0.0 if terminated else gamma * np.max(q[tuple(obs.astype(int))]))
            q[s + (a,)] += alpha * (target - q[s + (a,)])
            done = terminated or truncated
    # The greedy policy, frozen.
    obs, _ = env.reset()
    ret, steps, done = 0.0, 0, False
    while not done:
        obs, reward, terminated, truncated, info = env.step(int(np.argmax(q[tuple(obs.astype(int))])))
        ret, steps, done = ret + reward, steps + 1, terminated or truncated
    assert tuple(obs.astype(int)) == task["goal"] and ret == 1.0
    # Shortest path: the goal's Manhattan distance from the start (4, 4).
    assert steps == abs(task["goal"][0] - 4) + abs(task["goal"][1] - 4)
    env.close()
