"""
What the package's algorithms share: the base class (:mod:`.twin_critic`), the actor base, ensemble critics and
twin-critic policy (:mod:`.policies`), their checks (:mod:`.validation`) and saving (:mod:`.persistence`).
:class:`DemonstrationReplayBuffer` keeps demonstrations apart from the agent's transitions and draws a fixed share of
every batch from them.
"""

from sb3_dacerf.common.buffers import DemonstrationReplayBuffer

__all__ = ["DemonstrationReplayBuffer"]
