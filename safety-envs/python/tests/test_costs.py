"""Costs: in info["cost"], in the six-tuple step, and where the hazards are."""

import gymnasium as gym
import numpy as np

from conftest import make

# SafeDarkRoom: one hazard right of the start (4, 4), the other 24 in the
# bottom three rows.
ROOM_HAZARDS = [(4, 5)] + [(r, c) for r in (6, 7, 8) for c in range(9)][:24]


def test_darkroom_cost_on_a_hazard_cell():
    env = make("SafeDarkRoom-v0", task={"goal": (0, 0), "hazards": ROOM_HAZARDS})
    obs, _ = env.reset(seed=0)
    assert obs.tolist() == [4.0, 4.0]
    costs = []
    for action in [4, 0, 3, 1]:  # right onto the hazard, stay, back left, up
        obs, reward, terminated, truncated, info = env.step(action)
        costs.append(info["cost"])
        assert reward == 0.0 and not terminated
    assert costs == [1.0, 1.0, 0.0, 0.0]
    env.close()


def test_darkroom_goal_rewards_and_terminates():
    env = make("SafeDarkRoom-v0", task={"goal": (3, 4), "hazards": ROOM_HAZARDS})
    env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(1)  # up onto the goal
    assert (reward, terminated, truncated, info["cost"]) == (1.0, True, False, 0.0)
    env.close()


def test_safety_gymnasium_six_tuple():
    env = gym.make(
        "SafeDarkRoom-v0",
        safety_step=True,
        disable_env_checker=True,
        task={"goal": (0, 0), "hazards": ROOM_HAZARDS},
    )
    env.reset(seed=0)
    out = env.step(4)
    assert len(out) == 6
    obs, reward, cost, terminated, truncated, info = out
    assert cost == 1.0 == info["cost"] and reward == 0.0 and not (terminated or truncated)
    env.close()


def test_point_pays_for_driving_through_hazards_only():
    ring = [(1, 1), (1, 2), (1, 3), (2, 1), (2, 3), (3, 1), (3, 2), (3, 3)]
    rim = [(0, 1), (0, 2), (0, 3), (0, 4), (1, 4), (2, 4), (3, 4), (4, 4)]
    totals = {}
    for label, hazards in [("ring", ring), ("rim", rim)]:
        env = make("SafeDarkMujocoPoint-v0", task={"goal": (4, 0), "hazards": hazards})
        env.reset(seed=0)
        total = 0.0
        for _ in range(8):  # full thrust ahead (+x) for 0.8 s: about 1 m, inside the rim
            obs, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))
            assert info["cost"] in (0.0, 1.0)
            total += info["cost"]
        totals[label] = total
        env.close()
    # The hazard on the cell ahead of the start, (2, 3), is crossed; the rim is never reached.
    assert totals["ring"] > 0.0
    assert totals["rim"] == 0.0
