"""The Nomad 200 mobile robot of thesis Chapter 6, simulated in MuJoCo."""

from sims.nomad.behaviours import WanderConfig, handcoded_wander, ir_veto
from sims.nomad.config import BEHAVIOURS, NomadConfig
from sims.nomad.forage import Forage, ForageConfig, NomadForage
from sims.nomad.task import NomadEnv, NomadVec

__all__ = [
    "BEHAVIOURS",
    "Forage",
    "ForageConfig",
    "NomadConfig",
    "NomadEnv",
    "NomadForage",
    "NomadVec",
    "WanderConfig",
    "handcoded_wander",
    "ir_veto",
]
