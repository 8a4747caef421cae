"""LightningModules for learned FK and IK, with one shared step and rank-safe metrics.

Loss: FK — mean squared error of the position divided by the total robot length plus ``rot_weight`` × the
squared Frobenius distance ‖R̂ − R‖²_F = 8 sin²(θ/2) of the rotations (smooth, ≈ 2θ² for small geodesic errors
θ). IK — mean squared error of the standardised network output (actuated Clarke features, or the joint vector
for "raw"), optionally plus the same pose loss on the analytic FK of the predicted joints (:class:`IKModule`).
Validation/test metrics are computed on all ranks' samples together (per-sample errors are all-gathered), so the
same config runs unchanged with ``--trainer.strategy ddp``.
"""
from __future__ import annotations

import lightning.pytorch as pl
import torch
from torch import Tensor

from .compositional import CompositionalFK, model_from_hparams
from .kinematics import backbone_points, forward_kinematics
from .metrics import pose_errors, summarize
from .models import IKModel
from .robot import RobotSpec


def ik_errors(model: IKModel, spec: RobotSpec, pose: Tensor, pose_target: Tensor,
              q_target: Tensor) -> dict[str, Tensor]:
    """Per-sample IK errors of ``model`` on input poses (B, 4, 4): the task error of the analytic CC
    FK of the predicted joints vs ``pose_target`` (pos_err [m], rot_err [rad]), the joint error
    ‖q̂ − q_target‖ [m] and the constraint residual ‖q̂ − dec(enc(q̂))‖ [m]."""
    q_pred = model(pose)
    task = pose_errors(forward_kinematics(spec, model.encoder(q_pred)), pose_target)
    residual = torch.linalg.vector_norm(q_pred - model.decoder(model.encoder(q_pred)), dim=-1)
    joint = torch.linalg.vector_norm(q_pred - q_target, dim=-1)
    return {**task, "joint_err": joint, "constraint_residual": residual}


def pose_loss(pred: Tensor, target: Tensor, length: float, rot_weight: float = 1.0) -> Tensor:
    """Mean over the batch of ‖p̂ − p‖²/length² + rot_weight·‖R̂ − R‖²_F for poses (..., 4, 4) → ()."""
    pos = ((pred[..., :3, 3] - target[..., :3, 3]) / length).square().sum(-1).mean()
    rot = (pred[..., :3, :3] - target[..., :3, :3]).square().sum((-1, -2)).mean()
    return pos + rot_weight * rot


def limit_excess(spec: RobotSpec, features: Tensor) -> Tensor:
    """Squared excess of feature tensors (..., m, 4) over the robot's sampling limits → (...):
    Σ_k (‖ρ_k‖/(d_k·bend_k) − 1)₊² + ((β_k, α_k) beyond their range / half the range)²
    (dimensionless, 0 inside the limits; β, α only where the segment extends / twists)."""
    total = features.new_zeros(features.shape[:-2])
    for k, seg in enumerate(spec.segments):
        f = features[..., k, :]
        total = total + (torch.linalg.vector_norm(f[..., :2], dim=-1) / (seg.radius * seg.bend) - 1).relu().square()
        for col, lim in ((2, seg.length_range), (3, seg.twist_range)):
            if lim is not None:
                half = (lim[1] - lim[0]) / 2
                total = total + (((f[..., col] - (lim[0] + lim[1]) / 2).abs() - half) / half).relu().square()
    return total


def one_cycle(opt: torch.optim.Optimizer, lr: float, total_steps: int) -> torch.optim.lr_scheduler.OneCycleLR:
    """One-cycle schedule: warm-up over 5 % of the steps (at least 2, which OneCycleLR needs to avoid a
    zero-length phase on very short runs), then cosine annealing to ~0 at ``total_steps``."""
    if total_steps < 4:
        raise ValueError(f"one-cycle schedule: expected at least 4 training steps, got {total_steps}")
    return torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=total_steps,
                                               pct_start=min(0.5, max(0.05, 2 / total_steps)))


class KinematicsModule(pl.LightningModule):
    """Shared training logic. Subclasses build ``self.model`` and define ``loss`` and ``errors``.

    Args:
        robot: robot YAML path or RobotSpec dict (stored as a dict in the checkpoint).
        features: "clarke" | "raw". width, depth, activation: MLP shape.
        lr: peak learning rate of the one-cycle schedule; weight_decay: AdamW decay.
        visual_samples: number of validation samples drawn in the Rerun 3D scene.
    """

    def __init__(self, robot: str | dict = "configs/robots/default.yaml", features: str = "clarke",
                 width: int = 256, depth: int = 3, activation: str = "silu", lr: float = 3e-3,
                 weight_decay: float = 0.0, visual_samples: int = 8):
        super().__init__()
        self.spec = RobotSpec.coerce(robot)
        self.save_hyperparameters()
        self.hparams["robot"] = self.spec.to_dict()       # the checkpoint carries the full spec
        self.model = self.build_model()
        self._outputs: list[dict[str, Tensor]] = []
        self.test_summary: dict[str, float] = {}
        self.run_config: str | None = None     # the CLI's YAML config, stored in checkpoints

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.run_config is not None:
            checkpoint["dacr_config"] = self.run_config

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self.run_config = checkpoint.get("dacr_config", self.run_config)

    task = "fk"             # the network of model_from_hparams(task, …): "fk", "ik" or "sampler"

    def build_model(self) -> torch.nn.Module:
        return model_from_hparams(self.task, self.spec, self.hparams)

    def forward(self, x: Tensor) -> Tensor:
        return self.model(x)

    def setup(self, stage: str) -> None:
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if stage == "fit" and dm is not None and hasattr(dm, "splits"):
            train = dm.splits["train"]
            self.model.fit_normalization(train["q"], train["pose"])

    def configure_optimizers(self):
        opt = torch.optim.AdamW(self.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
        sched = one_cycle(opt, self.hparams.lr, int(self.trainer.estimated_stepping_batches))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    loss_name = "loss"      # the training loss is logged as train/<loss_name>

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        loss = self.loss(batch)
        if self._trainer is None or batch_idx % max(self.trainer.log_every_n_steps, 1) == 0:
            # only on the steps the logger records: self.log costs ~15 % of a small model's step
            self.log(f"train/{self.loss_name}", loss, prog_bar=True, batch_size=batch["q"].shape[0])
        return loss

    def _eval_step(self, batch: dict[str, Tensor]) -> None:
        errors = self.errors(batch)
        errors["valid"] = batch["valid"]
        self._outputs.append({k: v.detach() for k, v in errors.items()})

    def validation_step(self, batch, batch_idx):
        self._eval_step(batch)

    test_step = validation_step

    def _gathered_summary(self) -> dict[str, float]:
        """Summary over every rank's samples (padding rows dropped)."""
        if not self._outputs:
            return {}
        local = {k: torch.cat([o[k] for o in self._outputs]) for k in self._outputs[0]}
        self._outputs.clear()
        every = {k: v.reshape(-1) for k, v in self.all_gather(local).items()}
        valid = every.pop("valid").bool()
        return summarize({k: v[valid] for k, v in every.items()}, self.spec.total_length)

    def on_validation_epoch_end(self) -> None:
        summary = self._gathered_summary()
        for k, v in summary.items():
            self.log(f"val/{k}", v, prog_bar=k in ("pos_err_mean_mm", "rot_err_mean_deg"), rank_zero_only=True)

    def on_test_epoch_end(self) -> None:
        self.test_summary = self._gathered_summary()
        for k, v in self.test_summary.items():
            self.log(f"test/{k}", v, rank_zero_only=True)

    def predicted_pose(self, q: Tensor, pose: Tensor) -> Tensor:
        raise NotImplementedError

    @torch.no_grad()
    def visual_batch(self, num_workspace: int = 2000) -> dict[str, Tensor]:
        """Scene of fixed validation samples for the Rerun callback (CPU tensors, metres; keys of
        :func:`dacr_learn.viz.scene.log_scene`): the CC backbone of the samples' features, the dataset's
        own backbone where it has one (Cosserat), the learned segment ends of a compositional model or the body of an
        FK network's shape output."""
        val = self.trainer.datamodule.splits["val"]
        k, n = min(self.hparams.visual_samples, len(val["q"])), min(num_workspace, len(val["q"]))
        q, pose = val["q"][:n].to(self.device), val["pose"][:n].to(self.device)
        pred = self.predicted_pose(q, pose)
        visual = {"backbone": backbone_points(self.spec, val["features"][:k]).cpu(),
                  "pose_true": pose[:k].cpu(), "pose_pred": pred[:k].cpu(),
                  "workspace_points": pose[:, :3, 3].cpu(), "workspace_error": pose_errors(pred, pose)["pos_err"].cpu()}
        if "backbone" in val:        # a dataset with its own backbone (Cosserat): "backbone" above is then CC's
            visual["backbone_true"] = val["backbone"][:k].cpu()
        if isinstance(getattr(self, "model", None), CompositionalFK):
            ends = self.model.segment_ends(q[:k])[..., :3, 3]
            visual["backbone_pred"] = torch.cat([torch.zeros_like(ends[..., :1, :]), ends], dim=-2).cpu()
        elif getattr(getattr(self, "model", None), "body_points", 0):       # an FK network's shape output
            visual["backbone_pred"] = self.model.body(q[:k]).points.cpu()
        return visual


class FKModule(KinematicsModule):
    """Learned forward kinematics (joint vector → tip pose).

    ``structure``: "monolithic" (one network maps all features to the tip; ``rotation`` "6d" | "quaternion") or
    "compositional" (one network per segment transform, :mod:`dacr_learn.compositional`; ``rotation`` "twist" |
    "6d", ``context`` "none" | "segment" | "distal" | "full", ``units`` "strain" | "metric"). ``segment_weight``:
    weight of the loss on the end frames of the segments before the tip when batches carry ``segment_frames``
    (compositional only). The body (docs/body.md, "Training the shape output"): ``body_points`` K > 0 and
    ``body_prior`` give a monolithic model a shape output (:class:`~dacr_learn.models.FKModel`); when batches carry
    the true body, ``body_weight`` × the mean of ‖p̂ − p‖²/L² over its points is added to the loss, and
    validation/test report ``body_err`` (per sample the largest point error).
    """

    def __init__(self, robot: str | dict = "configs/robots/default.yaml", features: str = "clarke",
                 width: int = 256, depth: int = 3, activation: str = "silu", lr: float = 3e-3,
                 weight_decay: float = 0.0, visual_samples: int = 8, rotation: str = "6d", rot_weight: float = 1.0,
                 structure: str = "monolithic", context: str = "none", segment_weight: float = 0.0,
                 units: str = "strain", body_points: int = 0, body_prior: str = "none", body_weight: float = 0.0):
        # save_hyperparameters() in the base class also records the FK-only arguments
        super().__init__(robot, features, width, depth, activation, lr, weight_decay, visual_samples)

    def pose_loss(self, pred: Tensor, target: Tensor) -> Tensor:
        """Mean of ‖Δp‖²/L² + rot_weight·‖R̂ − R‖²_F over poses (..., 4, 4)."""
        return pose_loss(pred, target, self.spec.total_length, self.hparams.rot_weight)

    def loss(self, batch: dict[str, Tensor]) -> Tensor:
        weight = self.hparams.get("segment_weight", 0.0)
        if not (weight and "segment_frames" in batch and isinstance(self.model, CompositionalFK)):
            loss = self.pose_loss(self.model(batch["q"]), batch["pose"])
        else:
            ends = self.model.segment_ends(batch["q"])
            inner = self.pose_loss(ends[..., :-1, :, :], batch["segment_frames"][..., :-1, :, :])
            loss = self.pose_loss(ends[..., -1, :, :], batch["pose"]) + weight * inner
        body_weight = self.hparams.get("body_weight", 0.0)
        if body_weight and "backbone" in batch:
            error = self.body_prediction(batch) - batch["backbone"]
            loss = loss + body_weight * (error / self.spec.total_length).square().sum(-1).mean()
        return loss

    def body_prediction(self, batch: dict[str, Tensor]) -> Tensor:
        """The model's body (B, 1 + m·K, 3) [m] at the layout of the batch's true body ``backbone``."""
        k = (batch["backbone"].shape[-2] - 1) // self.spec.num_segments
        return self.model.body(batch["q"], k).points

    def errors(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        errors = pose_errors(self.model(batch["q"]), batch["pose"])
        learned_body = self.hparams.get("body_points", 0) or getattr(self.model, "rotation", "") == "twist"
        if "backbone" in batch and learned_body:
            diff = self.body_prediction(batch) - batch["backbone"]
            errors["body_err"] = torch.linalg.vector_norm(diff, dim=-1).amax(-1)
        return errors

    def predicted_pose(self, q: Tensor, pose: Tensor) -> Tensor:
        return self.model(q)


class IKModule(KinematicsModule):
    """Learned inverse kinematics (tip pose → joint vector satisfying the constraint for "clarke").

    Loss = ``feature_weight`` × MSE of the standardised network output against the sample's joint-space target
    (actuated Clarke features, or q for "raw") + ``pose_weight`` × :func:`pose_loss` (``rot_weight``) of the
    analytic CC FK of the predicted joints against the input pose (on a redundant robot the feature term alone
    learns the mean of the solutions, no solution). ``output_scale``: :class:`~dacr_learn.models.IKModel`.

    ``limit_weight`` × the mean :func:`limit_excess` of the decoded features keeps the predictions at the training
    poses inside the sampled joint limits; ``limit_noise`` > 0 adds that penalty at the training inputs plus
    Gaussian noise of that std (standardised input units; no target, no FK), between the training poses too;
    with ``limit_noise_reference_n`` its weight falls as (reference / n_train)² (:meth:`noise_weight`).
    ``pose_noise`` > 0 augments the pose term: training inputs plus Gaussian noise of that std, mapped back to
    valid poses (:meth:`~dacr_learn.models.IKModel.input_pose`), are compared with the analytic FK of the
    network's prediction (no joint target needed), weighted by the pose weight × ``pose_noise_weight`` × the same
    (reference / n_train)² (:meth:`noise_scale`).

    ``pose_ramp`` (a fraction of the training steps): the weights move linearly from (1, 0), the pure feature
    term, to (``feature_weight``, ``pose_weight``): the network learns the smooth conditional mean first, then
    the pose term pulls it onto the nearest solution branch (docs/ablation.md, "Multi-segment IK with a pose
    loss", says why). ``pose_ramp_max_epochs`` caps that phase at so many epochs, so one config serves every size.
    Validation/test summaries add ``out_of_limits_pct``: the share of predictions with :func:`limit_excess`
    above 1e-6 (about 0.1 % relative overshoot).
    """

    def __init__(self, robot: str | dict = "configs/robots/default.yaml", features: str = "clarke",
                 width: int = 256, depth: int = 3, activation: str = "silu", lr: float = 3e-3,
                 weight_decay: float = 0.0, visual_samples: int = 8, feature_weight: float = 1.0,
                 pose_weight: float = 0.0, rot_weight: float = 1.0, pose_ramp: float = 0.0,
                 limit_weight: float = 0.0, output_scale: str = "std", pose_ramp_max_epochs: float | None = None,
                 limit_noise: float = 0.0, limit_noise_reference_n: int | None = None, pose_noise: float = 0.0,
                 pose_noise_weight: float = 1.0):
        for name, w in (("feature_weight", feature_weight), ("pose_weight", pose_weight), ("rot_weight", rot_weight),
                        ("limit_weight", limit_weight), ("pose_noise_weight", pose_noise_weight)):
            if not w >= 0:
                raise ValueError(f"{name}: expected a number >= 0, got {w!r}")
        if not 0 <= pose_ramp <= 1:
            raise ValueError(f"pose_ramp: expected a fraction of the training steps in [0, 1], got {pose_ramp!r}")
        if pose_ramp_max_epochs is not None and not pose_ramp_max_epochs > 0:
            raise ValueError("pose_ramp_max_epochs: expected a number of epochs > 0 or null, "
                             f"got {pose_ramp_max_epochs!r}")
        if limit_noise_reference_n is not None and not (isinstance(limit_noise_reference_n, int)
                                                        and limit_noise_reference_n >= 1):
            raise ValueError("limit_noise_reference_n: expected a number of training samples >= 1 or null, "
                             f"got {limit_noise_reference_n!r}")
        for name, std in (("limit_noise", limit_noise), ("pose_noise", pose_noise)):
            if not std >= 0:
                raise ValueError(f"{name}: expected a standard deviation >= 0, got {std!r}")
        if feature_weight == 0 and pose_weight == 0:
            raise ValueError("feature_weight, pose_weight: expected at least one > 0, got both 0")
        # save_hyperparameters() in the base class also records the loss weights
        super().__init__(robot, features, width, depth, activation, lr, weight_decay, visual_samples)
        self.n_train: int | None = None            # training set size, known from setup("fit")

    task = "ik"

    def setup(self, stage: str) -> None:
        super().setup(stage)
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if dm is not None and hasattr(dm, "splits") and "train" in dm.splits:
            self.n_train = len(dm.splits["train"]["q"])
        if dm is not None and getattr(dm, "source", "cc") != "cc" and self.hparams.pose_weight > 0:
            raise ValueError(
                f"model.pose_weight: the IK pose loss compares the analytic CC FK of the predicted joints with the "
                f"target pose, but this dataset's poses come from the {dm.source!r} model; got pose_weight "
                f"{self.hparams.pose_weight}, expected 0 (the joint-space loss only) for data source {dm.source!r}")

    def noise_scale(self) -> float:
        """Factor of the noisy-input terms: (``limit_noise_reference_n`` / n_train)² with a reference, else 1."""
        ref = self.hparams.get("limit_noise_reference_n")
        if ref is None:
            return 1.0
        if self.n_train is None:
            raise ValueError("limit_noise_reference_n: needs the training set size (a fit with a datamodule that "
                             "has splits['train'])")
        return (ref / self.n_train) ** 2

    def noise_weight(self) -> float:
        """Weight of the limit penalty at the noisy inputs: ``limit_weight``, × (``limit_noise_reference_n`` /
        n_train)² with a reference: needed where the training poses are sparse, and off where they are dense
        (at 100k samples a 1/n fall still cost accuracy: docs/ablation.md)."""
        weight = self.hparams.get("limit_weight", 0.0)
        return weight * self.noise_scale() if self.hparams.get("limit_noise", 0.0) else weight

    def loss_weights(self) -> tuple[float, float]:
        """(feature weight, pose weight) at the current step (see ``pose_ramp``); the final ones outside a fit."""
        h = self.hparams
        ramp = h.get("pose_ramp", 0.0)
        if not ramp or self._trainer is None or not self.training:
            return h.feature_weight, h.pose_weight
        steps = ramp * self.trainer.estimated_stepping_batches
        if h.get("pose_ramp_max_epochs") is not None:
            steps = min(steps, h.pose_ramp_max_epochs * self.trainer.num_training_batches)
        t = min(1.0, self.global_step / max(1.0, steps))
        return (1 - t) + t * h.feature_weight, t * h.pose_weight

    def loss(self, batch: dict[str, Tensor]) -> Tensor:
        x = self.model.normalized_input(batch["pose"])
        (wf, wp), z = self.loss_weights(), self.model.net(x)
        loss = z.new_zeros(())
        if wf:
            loss = loss + wf * (z - self.model.out_norm(self.model.target(batch["q"]))).square().mean()
        lw = self.hparams.get("limit_weight", 0.0)
        if wp or lw:
            features = self.model.decode_features(z)
        if wp:
            pred = forward_kinematics(self.spec, features)
            loss = loss + wp * pose_loss(pred, batch["pose"], self.spec.total_length, self.hparams.rot_weight)
        if lw:
            loss = loss + lw * limit_excess(self.spec, features).mean()
            noise = self.hparams.get("limit_noise", 0.0)
            if noise:
                noisy = self.model.decode_features(self.model.net(x + noise * torch.randn_like(x)))
                loss = loss + self.noise_weight() * limit_excess(self.spec, noisy).mean()
        pose_noise = self.hparams.get("pose_noise", 0.0)
        if wp and pose_noise:
            target = self.model.input_pose(x + pose_noise * torch.randn_like(x))
            pred = forward_kinematics(self.spec, self.model.decode_features(
                self.model.net(self.model.normalized_input(target))))
            weight = wp * self.hparams.get("pose_noise_weight", 1.0) * self.noise_scale()
            loss = loss + weight * pose_loss(pred, target, self.spec.total_length, self.hparams.rot_weight)
        return loss

    def predicted_pose(self, q: Tensor, pose: Tensor) -> Tensor:
        """Analytic CC forward kinematics of the predicted joint vector."""
        return forward_kinematics(self.spec, self.model.encoder(self.model(pose)))

    def errors(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        errors = ik_errors(self.model, self.spec, batch["pose"], batch["pose"], batch["q"])
        features = self.model.encoder(self.model(batch["pose"]))
        return {**errors, "out_of_limits": (limit_excess(self.spec, features) > 1e-6).to(features.dtype)}
