"""LightningModule of the learned IK sampler (:class:`~dacr_learn.sampler.ClarkeSampler`), trained by maximum
likelihood on the synthetic dataset of its robot (``train.py fit --config configs/ik_sampler_tdcr3.yaml``).

Loss: the negative log-likelihood [nats per sample, standardised flow variables] of the training joints given
their tip poses (a ``position_fraction`` of the poses with the rotation hidden). Validation/test: ``nll_mean``
(rotation given, no noise) and the tip error of one sample per target under the analytic CC model
(``pos_err_*``, ``rot_err_*``); for "raw" also ``out_of_limits_pct`` (samples whose features leave the limits
before the projection) and ``constraint_residual_*`` (their distance from the displacement constraint).
"""
from __future__ import annotations

import torch
from torch import Tensor

from .checks import F64
from .kinematics import backbone_points, forward_kinematics
from .metrics import pose_errors
from .models import actuated_to_features
from .training import KinematicsModule


class SamplerModule(KinematicsModule):
    """Learned multi-solution IK sampler: a conditional normalizing flow of the joints given the tip pose. Args beyond
    :class:`~dacr_learn.training.KinematicsModule`'s: features "clarke" | "raw" (:mod:`dacr_learn.sampler`);
    transforms, bins, width, depth, activation: the flow; noise: std of the Gaussian noise on the standardised
    training variables (> 0 for "raw"); position_fraction: share of training poses with the rotation hidden.
    """

    def __init__(self, robot: str | dict = "configs/robots/default.yaml", features: str = "clarke",
                 width: int = 128, depth: int = 2, activation: str = "relu", lr: float = 2e-3,
                 weight_decay: float = 0.0, visual_samples: int = 8, transforms: int = 4, bins: int = 8,
                 noise: float = 0.01, position_fraction: float = 0.5):
        if not noise >= 0:
            raise ValueError(f"noise: expected a standard deviation >= 0, got {noise!r}")
        if features == "raw" and noise == 0:
            raise ValueError("noise: the raw joint vectors lie on the displacement constraint (fewer dimensions than "
                             "joints), where a flow's density is unbounded; expected noise > 0 with features 'raw'")
        if not 0 <= position_fraction <= 1:
            raise ValueError(f"position_fraction: expected a fraction in [0, 1], got {position_fraction!r}")
        # save_hyperparameters() in the base class also records the sampler's arguments
        super().__init__(robot, features, width, depth, activation, lr, weight_decay, visual_samples)
        self.model.position_trained.fill_(position_fraction > 0)

    loss_name = "nll"       # train/nll and val/nll_mean share a plot; a log-likelihood may be of either sign

    task = "sampler"

    def loss(self, batch: dict[str, Tensor]) -> Tensor:
        q = batch["q"]
        hide = torch.rand(q.shape[0], device=q.device) < self.hparams.position_fraction
        return -self.model.log_prob(q, batch["pose"], hide, self.hparams.noise).mean()

    def seed_errors(self, pose: Tensor) -> dict[str, Tensor]:
        """One sample per pose (B, 4, 4): the tip errors of its analytic CC pose (pos_err [m], rot_err [rad]) and, for
        "raw", whether the sampled joints left the limits before the projection (out_of_limits, 0/1) and their
        constraint residual [m]."""
        m, space = self.model, self.model.space
        v = m.sample_variables(pose, 1)[:, 0].to(F64)
        raw = {}
        if m.features == "clarke":
            f = m.squash(v)                    # inside the limits and on the constraint by construction
        else:
            unprojected = space.features(v)
            f = space.limits.project(unprojected)
            raw = {"out_of_limits": (~space.limits.inside(unprojected)).to(F64),
                   "constraint_residual": torch.linalg.vector_norm(space.joints(unprojected) - v, dim=-1)}
        tip = forward_kinematics(self.spec, actuated_to_features(f, space.selection, space.base))
        return {**pose_errors(tip, pose.to(F64)), **raw}

    def errors(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        nll = -self.model.log_prob(batch["q"], batch["pose"])
        seeds = {k: v.to(nll.dtype) for k, v in self.seed_errors(batch["pose"]).items()}
        return {"nll": nll, **seeds}

    @torch.no_grad()
    def visual_batch(self, num_workspace: int = 2000) -> dict[str, Tensor]:
        """Rerun scene (keys of :func:`dacr_learn.viz.scene.log_scene`): ``visual_samples`` samples for the first
        validation pose (``backbone_pred``, ``pose_pred`` against ``pose_true``), the dataset's own configuration
        (``backbone``) and the validation tips coloured by the error of one sample each (``workspace_error``).
        """
        val, k, space = self.trainer.datamodule.splits["val"], self.hparams.visual_samples, self.model.space
        target = val["pose"][:1].to(self.device)
        f = self.model.sample_features(target, k)[0]
        full = actuated_to_features(f, space.selection, space.base)
        n = min(num_workspace, len(val["q"]))
        workspace = val["pose"][:n].to(self.device)
        return {"backbone": backbone_points(self.spec, val["features"][:1]).cpu(),
                "backbone_pred": backbone_points(self.spec, full).float().cpu(),
                "pose_true": target.expand(k, 4, 4).cpu(),
                "pose_pred": forward_kinematics(self.spec, full).float().cpu(),
                "workspace_points": workspace[:, :3, 3].cpu(),
                "workspace_error": self.seed_errors(workspace)["pos_err"].float().cpu()}
