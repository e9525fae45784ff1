"""rl_pg: REINFORCE done right inside TorchRL."""

from rl_pg import baselines, functional
from rl_pg.discretize import DiscretizeAction
from rl_pg.estimators import DiscountedReturn, RewardToGo
from rl_pg.loss import ReinforceLoss

__all__ = [
    "DiscountedReturn",
    "DiscretizeAction",
    "ReinforceLoss",
    "RewardToGo",
    "baselines",
    "functional",
]
__version__ = "0.1.0"
