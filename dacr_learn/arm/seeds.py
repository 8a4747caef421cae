"""The pose bank of IK starts, :class:`~dacr_learn.ik.seeds.PoseBank` (it lives with the solver, which seeds from it
with ``IKOptions(bank=...)``)."""
from ..ik.seeds import CHUNK, POSITION_WEIGHT, PoseBank

__all__ = ["CHUNK", "POSITION_WEIGHT", "PoseBank"]
