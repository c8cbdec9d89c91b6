"""Gymnasium's own checker, registration, spaces and the version."""

import re
from importlib import metadata
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium.utils.env_checker import check_env

import safety_envs
from conftest import make


def test_check_env_passes(env_id):
    # With render_mode set, check_env also checks render().
    env = make(env_id, render_mode="rgb_array")
    check_env(env)
    env.close()


def test_registered_on_import_with_their_spaces():
    shapes = {"SafeDarkRoom-v0": (2,), "SafeDarkMujocoPoint-v0": (23,), "SafeDarkMujocoCar-v0": (35,)}
    for env_id, shape in shapes.items():
        env = gym.make(env_id)
        assert env.observation_space.shape == shape
        assert env.observation_space.dtype == np.float32
        if env_id == "SafeDarkRoom-v0":
            assert env.action_space == gym.spaces.Discrete(5)
        else:
            assert env.action_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        obs, info = env.reset(seed=0)
        assert obs.shape == shape and obs.dtype == np.float32
        assert env.observation_space.contains(obs)
        env.close()


def test_version_is_the_workspace_version():
    cargo = (Path(__file__).resolve().parents[3] / "Cargo.toml").read_text()
    workspace = re.search(r'\[workspace\.package\][^\[]*?version = "([^"]+)"', cargo).group(1)
    assert safety_envs.__version__ == workspace
    assert metadata.version("safety-envs") == workspace
