"""
The paper's task layer over highway-env, shared by the driving scenarios (laid out like ``highway_env.envs.common``:
:mod:`.abstract`, :mod:`.config`, :mod:`.action`, :mod:`.observation`, :mod:`.reference`, :mod:`.reward`), and the
faster simulation classes they run on (:mod:`.simulation`). Units are SI throughout.
"""

from sb3_dacerf.envs.driving.common.observation import EGO_FEATURES, VEHICLE_FEATURES, WAYPOINT_FEATURES, observe_scene
from sb3_dacerf.envs.driving.common.reward import REWARD_TERMS

__all__ = ["EGO_FEATURES", "REWARD_TERMS", "VEHICLE_FEATURES", "WAYPOINT_FEATURES", "observe_scene"]
