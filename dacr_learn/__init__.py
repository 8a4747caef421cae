"""dacr_learn: learned kinematics of displacement-actuated continuum robots (DACR).

Raw joint lengths (tendons, bellows, rods) are mapped linearly and exactly to the DACR joint-space
abstraction — two Clarke coordinates (ρ_re, ρ_im) per segment plus the segment length β and twist α —
by differentiable Clarke layers; constant-curvature kinematics, neural FK / IK models, exported
inference modules and a resolved-rate controller build on them. Maths and conventions:
``docs/design.md`` in the repository. SI units; every tensor function takes leading batch dims.

The names a user imports first are re-exported here:

>>> import torch
>>> import dacr_learn as dl
>>> spec = dl.RobotSpec.from_dict({"name": "one-segment", "routing": "independent",
...                                "segments": [{"type": "0", "length": 0.1, "radius": 0.005, "joints": 4}]})
>>> features = dl.ClarkeEncoder(spec)(torch.tensor([0.099, 0.1, 0.101, 0.1]))   # 4 tendon lengths [m]
>>> features.shape                            # (segments, 4): rho_re, rho_im, beta, alpha
torch.Size([1, 4])
>>> dl.forward_kinematics(spec, features).shape
torch.Size([4, 4])
"""
import os
from importlib.metadata import PackageNotFoundError, version

# Idle OpenMP threads sleep instead of spinning (unless the user chose otherwise): with torch's default a batch of
# small ops on 2 threads ran 15x slower on a loaded 2-core machine (IK of 1,000 poses: 36.7 s vs 2.4 s). libgomp
# reads this once, when torch is first imported: set here, before our first torch import, it covers the CLIs.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .deploy.control import ControllerConfig, ResolvedRateController, analytic_jacobian
from .ik import IKOptions, IKResult, solve_ik
from .kinematics import analytic_inverse_kinematics, backbone_points, forward_kinematics
from .layers import ClarkeDecoder, ClarkeEncoder
from .models import FKModel, IKModel
from .robot import RobotSpec
from .runs import load_model


def __getattr__(name: str):
    # load_exported is imported on first use: importing dacr_learn stays light (no torch.export machinery)
    if name == "load_exported":
        from .deploy.export import load
        return load
    if name in ("Composite", "load_arm"):          # the arm + continuum robot model (docs/arm.md), on first use
        from . import arm
        return getattr(arm, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


try:
    __version__ = version("dacr_learn")
except PackageNotFoundError:  # a source tree that was not pip-installed
    __version__ = "0.0.0+unknown"

__all__ = [
    "ClarkeDecoder", "ClarkeEncoder", "Composite", "ControllerConfig", "FKModel", "IKModel", "IKOptions", "IKResult",
    "ResolvedRateController", "RobotSpec", "__version__", "analytic_inverse_kinematics", "analytic_jacobian",
    "backbone_points", "forward_kinematics", "load_arm", "load_exported", "load_model", "solve_ik",
]
