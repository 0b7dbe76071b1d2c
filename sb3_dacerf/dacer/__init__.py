from sb3_dacerf.dacer.dacer import DACER
from sb3_dacerf.dacer.policies import CnnPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["DACER", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
