"""
The paper's two driving scenarios on highway-env (extra ``driving``: ``pip install sb3_dacerf[driving]``):
``DACERF-Multilane-v0`` (:mod:`.multilane`) and ``DACERF-Intersection-v0`` (:mod:`.intersection`).

``gym.make`` kwargs: ``density`` (``"sparse" | "normal" | "dense"``, or a distribution drawn from at each reset, see
:mod:`.density`), ``render_mode`` (``"rgb_array"`` renders offscreen) and ``config`` (overrides of the env's
``default_config()``, each checked by type and range). The task layer (observation, action, reward) is
:mod:`.common`; :class:`.scripted.ScriptedDriver` is a scripted baseline. Importing this package registers the ids
without importing highway-env.
"""

import gymnasium as gym

DRIVING_ENV_IDS = {
    "DACERF-Multilane-v0": "sb3_dacerf.envs.driving.multilane:MultilaneEnv",
    "DACERF-Intersection-v0": "sb3_dacerf.envs.driving.intersection:IntersectionEnv",
}

SCRIPTED_DRIVER_NAMES = ("scripted", "junction")
"""The names of :data:`.scripted.SCRIPTED_DRIVERS`, importable without highway-env (for command-line choices)."""

for _env_id, _entry_point in DRIVING_ENV_IDS.items():
    if _env_id not in gym.registry:
        gym.register(id=_env_id, entry_point=_entry_point)
