"""HyDrA, the binocular active head of thesis Chapter 7, simulated in MuJoCo."""

from sims.hydra.task import AXES, REGIMES, HydraConfig, HydraEnv, HydraVec

__all__ = ["AXES", "REGIMES", "HydraConfig", "HydraEnv", "HydraVec"]
