"""Environments of the paper, registered with Gymnasium on ``import sb3_dacerf``.

Registration only records ids and entry points: no simulator is imported until ``gym.make``.
"""

import sb3_dacerf.envs.dmc  # registers the DMC-<domain>-<task>-v0 ids
import sb3_dacerf.envs.driving  # noqa: F401  (registers DACERF-Multilane-v0 and DACERF-Intersection-v0)
