from sb3_dacerf.dacerf.dacerf import DACERF, PAPER_HYPERPARAMETERS
from sb3_dacerf.dacerf.policies import CnnPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["DACERF", "PAPER_HYPERPARAMETERS", "CnnPolicy", "MlpPolicy", "MultiInputPolicy"]
