"""Environments of the paper, registered with Gymnasium on ``import sb3_dacerf``.

Registration only records ids and entry points: no simulator is imported until ``gym.make``.
"""
