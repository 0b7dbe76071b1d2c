"""
Layer shared by the paper's driving environments, built on highway-env: incremental action, ego-frame observation,
reference path and the paper's reward / cost terms. Laid out like highway-env's own ``highway_env.envs.common``:

- :mod:`.abstract`: :class:`PaperDrivingMixin`, the task layer (config, step loop, termination, info, rendering);
- :mod:`.config`: type and range checks of every config value, run at ``gym.make`` / ``reset(options=...)``;
- :mod:`.action`: :class:`IncrementalAction`, the action ``[Δa_x, Δδ]`` (increments of acceleration and steering);
- :mod:`.observation`: :class:`Scene` (what the ego perceives, computed once per step) and
  :class:`EgoFrameObservation`, the flat ego-frame observation;
- :mod:`.reference`: :class:`ReferencePath`, the reference path and its arc-length lookups;
- :mod:`.reward`: the paper's reward and cost terms;
- :mod:`.simulation`: faster versions of highway-env's road, lane network and IDM vehicle that give the same
  traffic (config ``fast_simulation``, on by default).

The environments subclass highway-env's own ``HighwayEnv`` and ``IntersectionEnv``; this layer replaces their action,
observation, reward, termination and info with the paper's task design (DACER-F, section "Simulation Environment" and
the reward / cost table). Units are SI throughout. Each module's docstring describes its part.
"""

from sb3_dacerf.envs.driving.common.abstract import PaperDrivingMixin
from sb3_dacerf.envs.driving.common.action import IncrementalAction
from sb3_dacerf.envs.driving.common.observation import (
    EGO_FEATURES,
    VEHICLE_FEATURES,
    WAYPOINT_FEATURES,
    EgoFrameObservation,
    Scene,
    observe_scene,
)
from sb3_dacerf.envs.driving.common.reference import ReferencePath
from sb3_dacerf.envs.driving.common.reward import REWARD_TERMS, pseudo_huber, reward_terms
from sb3_dacerf.envs.driving.density import DENSITIES

__all__ = [
    "DENSITIES",
    "EGO_FEATURES",
    "REWARD_TERMS",
    "VEHICLE_FEATURES",
    "WAYPOINT_FEATURES",
    "EgoFrameObservation",
    "IncrementalAction",
    "PaperDrivingMixin",
    "ReferencePath",
    "Scene",
    "observe_scene",
    "pseudo_huber",
    "reward_terms",
]
