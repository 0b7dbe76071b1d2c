"""
The paper's two driving scenarios on highway-env (extra ``driving``: ``pip install sb3_dacerf[driving]``).

- ``DACERF-Multilane-v0``: multi-lane highway (:class:`sb3_dacerf.envs.driving.multilane.MultilaneEnv`);
- ``DACERF-Intersection-v0``: urban intersection (:class:`sb3_dacerf.envs.driving.intersection.IntersectionEnv`).

``gym.make`` kwargs: ``density="sparse" | "normal" | "dense"`` (or ``"random"``, a list or a dict of weights: each
reset draws the episode's density, see :mod:`sb3_dacerf.envs.driving.density`), ``render_mode`` (``"rgb_array"`` renders
offscreen) and ``config`` (a dict of overrides of the env's ``default_config()``; every value is checked by type
and range there). Observation, action and reward are described in :mod:`sb3_dacerf.envs.driving.common`; the
severe-event penalty is by default this package's formula for the paper's "or dynamically calculated"
(``collision_penalty="dynamic"``, see :mod:`sb3_dacerf.envs.driving.common.reward`), ``config={"collision_penalty":
200}`` selects the paper's constant.
:class:`sb3_dacerf.envs.driving.scripted.ScriptedDriver` is a scripted baseline driver.

Importing this package registers the ids (``import sb3_dacerf`` does) without importing highway-env:
registration records ids and entry points only.
"""

import gymnasium as gym

DRIVING_ENV_IDS = {
    "DACERF-Multilane-v0": "sb3_dacerf.envs.driving.multilane:MultilaneEnv",
    "DACERF-Intersection-v0": "sb3_dacerf.envs.driving.intersection:IntersectionEnv",
}

DEMONSTRATOR_NAMES = ("scripted", "junction")
"""The names of the scripted drivers in :data:`sb3_dacerf.envs.driving.scripted.DEMONSTRATORS`, importable without
highway-env (for command-line choices)."""


def register_driving_envs() -> None:
    """Register the driving environment ids with Gymnasium (idempotent, imports no simulator)."""
    for env_id, entry_point in DRIVING_ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point)


register_driving_envs()
