"""
What DACER-F and DACER share: the generative actor base and twin-critic policy (:mod:`.policies`), the twin-critic
algorithm base (:mod:`.twin_critic`), and the two pieces of DACER-F's actor update, side by side:
:func:`langevin_targets` (Algorithm 1: targets ``a*`` from replay actions) and :func:`flow_matching_loss` (the
imitation term of ``J_F`` towards them). :class:`DemonstrationReplayBuffer` keeps demonstrations apart from the
agent's transitions and draws a fixed share of every batch from them.
"""

from sb3_dacerf.common.buffers import DemonstrationReplayBuffer
from sb3_dacerf.common.flow_matching import actor_loss_weights, flow_matching_loss
from sb3_dacerf.common.langevin import langevin_targets

__all__ = ["DemonstrationReplayBuffer", "actor_loss_weights", "flow_matching_loss", "langevin_targets"]
