"""Bad calls are Python exceptions carrying the Rust messages; none ends the interpreter."""

import numpy as np
import pytest

import safety_envs
from conftest import make


def test_robot_action_errors():
    env = make("SafeDarkMujocoCar-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"invalid action: action \[NaN, 0.0\] contains a non-finite value"):
        env.step(np.array([np.nan, 0.0], np.float32))
    with pytest.raises(ValueError, match="invalid action: car takes 2 action values, got 3"):
        env.step(np.zeros(3, np.float32))
    with pytest.raises(ValueError, match=r"invalid action: car takes an action of shape \(2,\), got shape \[2, 1\]"):
        env.step(np.zeros((2, 1), np.float32))
    # A list is taken as an array; the environment still steps after the errors.
    obs, reward, terminated, truncated, info = env.step([0.5, -0.5])
    assert obs.shape == (35,)
    env.close()


def test_darkroom_action_errors():
    env = make("SafeDarkRoom-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="invalid action: SafeDarkRoom action 7 is out of range 0..5"):
        env.step(7)
    with pytest.raises(ValueError, match="out of range 0..5"):
        env.step(-1)
    with pytest.raises(TypeError, match="integer action"):
        env.step("up")
    env.close()


def test_state_errors():
    env = make("SafeDarkRoom-v0", time_limit=1)
    with pytest.raises(RuntimeError, match="step called after the episode ended"):
        env.step(0)  # before the first reset
    env.reset(seed=0)
    env.step(0)
    with pytest.raises(RuntimeError, match="step called after the episode ended"):
        env.step(0)
    env.close()
    env.close()  # twice is fine
    for call in (lambda: env.step(0), lambda: env.reset(seed=0), lambda: env.task):
        with pytest.raises(RuntimeError, match="the environment is closed"):
            call()


def test_bad_settings():
    with pytest.raises(ValueError, match="darkroom has no physics"):
        make("SafeDarkRoom-v0", physics_steps_per_action=5)
    with pytest.raises(ValueError, match="render_mode"):
        safety_envs.SafeDarkRoomEnv(render_mode="human")
