"""Shared helpers of the package's tests."""

import gymnasium as gym
import pytest

import safety_envs

IDS = list(safety_envs.ENV_NAMES)


@pytest.fixture(params=IDS)
def env_id(request):
    """Each environment id in turn."""
    return request.param


def make(env_id, **kwargs):
    """The raw environment (no Gymnasium wrappers), closed by the caller."""
    return gym.make(env_id, **kwargs).unwrapped
