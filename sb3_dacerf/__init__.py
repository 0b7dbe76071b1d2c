import sb3_dacerf.envs  # noqa: F401  (registers the environment ids, imports no simulator)
from sb3_dacerf.dacer import DACER
from sb3_dacerf.dacerf import DACERF
from sb3_dacerf.dsac import DSAC
from sb3_dacerf.version import __version__

__all__ = ["DACER", "DACERF", "DSAC", "__version__"]
