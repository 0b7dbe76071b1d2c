from sb3_dacerf.dsac.dsac import DSAC
from sb3_dacerf.dsac.policies import CnnPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["DSAC", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
