"""
Fixtures and helpers shared by the test modules.

Behaviours the algorithms share are tested once, parametrised over ``MODEL_LIST`` through the ``model_class``
fixture (as sb3-contrib's tests are). A module about one algorithm overrides ``model_class`` with a fixture that
returns that algorithm (pytest's fixture overriding), and gets the same ``fast`` settings.
"""

import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from sb3_dacerf import DACER, DACERF, DSAC

# The benchmark scripts some tests load by path import benchmarks/_checkout.py (the repository's package first)
sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))

# The suite's networks and batches are tiny: one thread avoids oversubscribing CI's two cores
th.set_num_threads(1)

MODEL_LIST = [DACER, DACERF, DSAC]


def fast_settings(model_class: type) -> dict[str, Any]:
    """
    Small and fast settings of ``model_class`` (the behaviours under test do not depend on the network size or the
    number of steps): a new dict at every call, so that a test can change it without affecting another.
    """
    settings: dict[str, Any] = dict(learning_starts=50, batch_size=32, buffer_size=2_000, policy_kwargs=dict(net_arch=[32, 32]))
    if model_class is DACER:
        settings["policy_kwargs"]["n_diffusion_steps"] = 5
    return settings


@pytest.fixture(params=MODEL_LIST, ids=lambda model_class: model_class.__name__)
def model_class(request: pytest.FixtureRequest) -> type:
    """Each algorithm of the package in turn."""
    return request.param


@pytest.fixture
def fast(model_class: type) -> dict[str, Any]:
    """:func:`fast_settings` of ``model_class``."""
    return fast_settings(model_class)


def autograd_action_gradient(q_function):
    """∇_a Q(a) of a differentiable ``q_function`` by autograd: the reference the written-out gradient is checked against."""

    def gradient(actions: th.Tensor) -> th.Tensor:
        with th.enable_grad():
            actions = actions.detach().requires_grad_(True)
            (grad,) = th.autograd.grad(q_function(actions).sum(), actions)
        return grad

    return gradient


#: MaskedVecNormalize's ``rows`` of TableEnv: two leading entries, then 3 rows of [x, y, mask]
TABLE_ROWS = (2, 3, 3)


class TableEnv(gym.Env):
    """Observations of 2 entries and 3 rows [x, y, mask], the first ``min_rows`` to 3 of them present (drawn)."""

    observation_space = spaces.Box(-np.inf, np.inf, shape=(11,), dtype=np.float32)
    action_space = spaces.Box(-1, 1, shape=(2,), dtype=np.float32)

    def __init__(self, min_rows: int = 1):
        self.min_rows = min_rows

    def observe(self) -> np.ndarray:
        obs = np.zeros(11, dtype=np.float32)
        obs[:2] = self.np_random.normal([5.0, -1.0], [2.0, 0.5])
        for row in range(int(self.np_random.integers(self.min_rows, 4))):
            obs[2 + 3 * row : 5 + 3 * row] = [*self.np_random.normal([40.0 + 10 * row, 3.0], [8.0, 1.0]), 1.0]
        return obs

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observe(), {}

    def step(self, action):
        return self.observe(), 0.0, False, False, {}
