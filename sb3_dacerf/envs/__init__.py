"""Environments of the paper, registered with Gymnasium on ``import sb3_dacerf``.

Registration only records ids and entry points: no simulator is imported until ``gym.make``.
"""

from sb3_dacerf.envs.driving import register_driving_envs; register_driving_envs()  # noqa: E402, E702
