"""What the algorithms share: base class (:mod:`.twin_critic`), policies' parts (:mod:`.policies`), checks
(:mod:`.validation`), saving (:mod:`.persistence`), and a replay buffer that keeps demonstrations apart."""

from sb3_dacerf.common.buffers import DemonstrationReplayBuffer

__all__ = ["DemonstrationReplayBuffer"]
