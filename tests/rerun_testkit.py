"""Shared pieces of the Rerun tests (not collected: no ``test_`` prefix): reading recordings back and a tiny
Lightning module to log from.

Every recording is read back with ``rerun.chunk.RrdReader`` (rerun-sdk 0.41) and checked with ``rerun rrd verify``:
data chunks per entity, one column of them, and a blueprint store's views (class, name, origin, contents query,
visible time ranges, the entities a view hides) and time panel.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from rerun.chunk import RrdReader
from torch.utils.data import DataLoader, TensorDataset

FOLLOWING = 3     # rerun.blueprint.components.PlayState.Following
WHOLE_RANGE = {"start": None, "end": None}
K, P, N = 3, 9, 40


def rerun_cli() -> str:
    local = Path(sys.executable).parent / "rerun"
    cli = str(local) if local.exists() else shutil.which("rerun")
    if cli is None:
        pytest.skip("rerun CLI not installed")
    return cli


def rrd_verify(path: Path) -> None:
    proc = subprocess.run(
        [rerun_cli(), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


def rrd_chunks(path: Path) -> dict[str, list]:
    """Entity path -> list of pyarrow RecordBatches of the recording in ``path``."""
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def rrd_column(batches: list, name: str) -> list:
    return [v for rb in batches if name in rb.schema.names for v in rb.column(name).to_pylist()]


def rrd_data_chunks(path: Path) -> int:
    return sum(1 for _ in RrdReader(path).stream())


def rrd_blueprint(path: Path):
    (store,) = RrdReader(path).blueprints()
    return store


def rrd_views(path: Path, store=None) -> dict[str, dict]:
    """View entity (``/view/<id>``) -> {"class", "name", "origin", "query", "ranges", "hidden"} of one blueprint
    store of the recording (by default its only one); "hidden": the entities the view overrides with
    EntityBehavior(visible=False)."""
    fields = {"ViewBlueprint:class_identifier": "class", "ViewBlueprint:display_name": "name",
              "ViewBlueprint:space_origin": "origin", "ViewContents:query": "query",
              "VisibleTimeRanges:ranges": "ranges"}
    views: dict[str, dict] = {}
    for chunk in RrdReader(path).stream(store=rrd_blueprint(path) if store is None else store):
        if not chunk.entity_path.startswith("/view/"):
            continue
        rb = chunk.to_record_batch()
        view = views.setdefault("/".join(chunk.entity_path.split("/")[:3]), {"hidden": set()})
        for column, key in fields.items():
            if column in rb.schema.names:
                row = rb.column(column).to_pylist()[-1]
                view[key] = row if key in ("query", "ranges") else row[0]
        if "EntityBehavior:visible" in rb.schema.names and rb.column("EntityBehavior:visible").to_pylist() == [[False]]:
            view["hidden"].add(chunk.entity_path.split("/overrides/")[1].removesuffix("/visualizers"))
    return views


def rrd_time_panel(path: Path, store=None) -> dict[str, list]:
    """The time panel's ``TimePanel…`` components of one blueprint store (by default the recording's only one)."""
    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream(store=rrd_blueprint(path) if store is None else store):
        if chunk.entity_path == "/time_panel":
            rb = chunk.to_record_batch()
            out.update({n: rb.column(n).to_pylist()[-1] for n in rb.schema.names if n.startswith("TimePanel")})
    return out


def rrd_data(path: Path) -> dict[str, dict[str, list]]:
    """Entity -> component column (``Archetype:field``) -> its rows of the recording's data."""
    out: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).stream():
        rb = chunk.to_record_batch()
        for name in (n for n in rb.schema.names if ":" in n):
            out.setdefault(chunk.entity_path, {}).setdefault(name, []).extend(rb.column(name).to_pylist())
    return out


def random_visual() -> dict[str, torch.Tensor]:
    pose_true = torch.eye(4).repeat(K, 1, 1)
    pose_true[:, :3, 3] = torch.rand(K, 3) * 0.1
    pose_pred = pose_true.clone()
    pose_pred[:, :3, 3] += 0.002 * torch.randn(K, 3)
    return {
        "backbone": torch.rand(K, P, 3) * 0.1,
        "pose_true": pose_true,
        "pose_pred": pose_pred,
        "workspace_points": torch.rand(N, 3) * 0.1,
        "workspace_error": torch.rand(N) * 0.003,
    }


class TinyModule(pl.LightningModule):
    def __init__(self, lr: float = 0.01) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.net = torch.nn.Linear(3, 3)

    def training_step(self, batch, batch_idx):
        x, y = batch
        loss = torch.nn.functional.mse_loss(self.net(x), y)
        self.log("train_loss", loss)
        return loss

    def validation_step(self, batch, batch_idx):
        x, y = batch
        err = (self.net(x) - y).norm(dim=-1)
        self.log("val_loss", err.pow(2).mean())
        self.log("val/pos_err", err.mean())

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=self.hparams.lr)

    def train_dataloader(self):
        g = torch.Generator().manual_seed(0)
        data = TensorDataset(torch.randn(32, 3, generator=g), torch.randn(32, 3, generator=g))
        return DataLoader(data, batch_size=8)

    def val_dataloader(self):
        return DataLoader(TensorDataset(torch.randn(16, 3), torch.randn(16, 3)), batch_size=8)


class VisualModule(TinyModule):
    def visual_batch(self) -> dict[str, torch.Tensor]:
        return random_visual()


def fit_module(module: pl.LightningModule, logger, callbacks, epochs: int = 2) -> pl.Trainer:
    trainer = pl.Trainer(
        max_epochs=epochs,
        logger=logger,
        callbacks=callbacks,
        accelerator="cpu",
        devices=1,
        log_every_n_steps=1,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", ".*does not have many workers.*")
        trainer.fit(module)
    return trainer
