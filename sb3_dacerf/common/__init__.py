"""
What DACER-F and DACER share: the generative actor base and twin-critic policy (:mod:`.policies`), the twin-critic
algorithm base (:mod:`.twin_critic`), and the two pieces of DACER-F's actor update, side by side:
:func:`langevin_targets` (Algorithm 1: targets ``a*`` from replay actions) and :func:`flow_matching_loss` (the
imitation term of ``J_F`` towards them).
"""

from sb3_dacerf.common.flow_matching import actor_loss_weights, flow_matching_loss
from sb3_dacerf.common.langevin import langevin_targets

__all__ = ["actor_loss_weights", "flow_matching_loss", "langevin_targets"]
