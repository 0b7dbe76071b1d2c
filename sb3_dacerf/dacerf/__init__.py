from sb3_dacerf.dacerf.dacerf import DACERF
from sb3_dacerf.dacerf.policies import CnnPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["DACERF", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
