"""
The paper's task layer over highway-env, shared by the driving scenarios (laid out like ``highway_env.envs.common``):

- :mod:`.abstract`: :class:`PaperDrivingMixin`: config, step loop, termination, info and rendering;
- :mod:`.config`: type and range checks of every config value;
- :mod:`.action`: the incremental action ``[Δa_x, Δδ]``;
- :mod:`.observation`: what the ego perceives (computed once per step) and the flat ego-frame observation;
- :mod:`.reference`: the reference path and its arc-length lookups;
- :mod:`.reward`: the paper's reward and cost terms;
- :mod:`.simulation`: faster drop-in versions of highway-env's road, lane network and IDM vehicle.

Units are SI throughout.
"""

from sb3_dacerf.envs.driving.common.observation import EGO_FEATURES, VEHICLE_FEATURES, WAYPOINT_FEATURES, observe_scene
from sb3_dacerf.envs.driving.common.reward import REWARD_TERMS

__all__ = ["EGO_FEATURES", "REWARD_TERMS", "VEHICLE_FEATURES", "WAYPOINT_FEATURES", "observe_scene"]
