"""render_mode="rgb_array": a picture of the right shape that shows the task."""

import numpy as np

from conftest import make

GREEN = np.array([26, 204, 51])  # the goal, in the grid and in the arena


def test_rgb_array_of_the_right_shape_and_not_blank(env_id):
    env = make(env_id, render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    colours = np.unique(frame.reshape(-1, 3), axis=0)
    assert len(colours) >= 4, f"only {len(colours)} colours: blank"
    # Something green (the goal) is drawn: lit by MuJoCo, so near, not equal.
    greenish = (frame[..., 1].astype(int) - np.maximum(frame[..., 0], frame[..., 2]) > 60).sum()
    assert greenish > 20
    env.close()


def test_the_picture_follows_the_agent(env_id):
    env = make(env_id, render_mode="rgb_array", width=96, height=96)
    env.reset(seed=0)
    before = env.render()
    for _ in range(5):
        env.step(4 if env_id == "SafeDarkRoom-v0" else np.array([1.0, 0.0], np.float32))
    assert not np.array_equal(before, env.render())
    env.close()


def test_no_render_mode_draws_nothing():
    env = make("SafeDarkRoom-v0")
    env.reset(seed=0)
    assert env.render() is None
    env.close()
