"""What a training session keeps and writes: the training log, the resumable state, run.json and the final
model, all by rank 0 and atomically."""

from __future__ import annotations

import datetime as dt
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import polars as pl
import torch

from .. import __version__
from ..model.checkpoint import MODEL_FILE, model_digest, save_model, save_training_state
from ..model.config import RunConfig
from ..model.models import TrajectoryModel
from ..rundir import FINAL_DIR, LOG_FILE, MODEL_INFO_FILE, STATE_FILE, write_run_info
from ..util.atomic import atomic_directory, atomic_write_bytes
from ..util.progress import say
from ..util.provenance import machines_after, revisions_after
from .data import TrainingData
from .distributed import DistContext
from .state import LOG_SCHEMA, StageProgress, progress_from
from .steps import copy_weights


@dataclass
class RunRecords:
    """A session's model, data and run directory, and what it records there (the loop is :class:`~.loop.Session`)."""

    run_dir: Path
    config: RunConfig
    data: TrainingData
    device: torch.device
    dist: DistContext
    quiet: bool
    fold: str | None
    log: list[dict[str, Any]] = field(default_factory=list)
    best: dict[str, dict[str, float]] = field(default_factory=dict)
    skipped_total: int = 0
    started: str = field(default_factory=lambda: dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"))
    #: the code revisions and the machines that trained this run, oldest first (see util.provenance)
    code_revisions: list[str] = field(default_factory=list)
    machines: list[str] = field(default_factory=list)
    #: per stage whose steps were to run compiled (train.compile_flow): "compiled in N s" or why it trains eager
    compiled: dict[str, str] = field(default_factory=dict)
    #: the run whose trained autoencoder this one started from (run.json "autoencoder_from"), if any
    autoencoder_from: dict[str, Any] | None = None
    #: the model being trained (built when the session runs)
    model: TrajectoryModel = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.code_revisions = self.code_revisions or revisions_after([])
        self.machines = self.machines or machines_after([], str(self.device))

    @property
    def writer(self) -> bool:
        return self.dist.rank == 0

    def _restore(self, state: dict[str, Any]) -> tuple[int, StageProgress]:
        """Load a training state (already reconciled with the config by `follow_budget`)."""
        self.model.load_state_dict(state["weights"])
        self.log = list(state["log"])
        self.best = dict(state["best"])
        self.skipped_total = int(state["skipped_total"])
        self.started = str(state["started"])
        self.code_revisions = revisions_after(state.get("code_revisions"))
        self.machines = machines_after(state.get("machines"), str(self.device))
        progress = progress_from(state)
        if self.writer and not self.quiet:
            say((f"resuming {self.run_dir}: stage {int(state['stage_index']) + 1}, after epoch {progress.epoch}",
                 "dim"))
        return int(state["stage_index"]), progress

    def _log_epoch(self, stage: str, epoch: int, train_loss: float, val_loss: float, lr: float, seconds: float,
                   skipped: int, rate: float, val_nll: float = math.nan) -> None:
        self.log.append({"epoch": epoch, "stage": stage, "train_loss": float(train_loss), "val_loss": float(val_loss),
                         "lr": float(lr), "seconds": float(seconds), "skipped_steps": int(skipped),
                         "samples_per_s": float(rate), "val_nll": None if math.isnan(val_nll) else float(val_nll)})
        self._write_log()

    def _write_log(self) -> None:
        """Write the training log as it stands (train_log.parquet)."""
        if self.writer:
            frame = pl.DataFrame(self.log, schema=LOG_SCHEMA)
            buffer = io.BytesIO()
            frame.write_parquet(buffer)
            atomic_write_bytes(self.run_dir / LOG_FILE, buffer.getvalue())

    def _checkpoint(self, stage_index: int, progress: StageProgress, path: str = STATE_FILE) -> None:
        """Write the resumable training state (stage `stage_index` at `progress`) to `path` in the run."""
        if not self.writer:
            return
        save_training_state(self.run_dir / path, {
            "model": self.model.name,
            "config": self.config.to_json(),
            "stage_index": stage_index,
            "epoch": progress.epoch,
            "best_val": progress.best_val,
            "best_epoch": progress.best_epoch,
            "bad_epochs": progress.bad_epochs,
            "weights": copy_weights(self.model),
            "best_weights": progress.best_weights,
            "selected_nll": progress.selected_nll,
            "selected_epoch": progress.selected_epoch,
            "optimizer": progress.optimizer,
            "scheduler": progress.scheduler,
            "log": self.log,
            "best": self.best,
            "skipped_total": self.skipped_total,
            "started": self.started,
            "code_revisions": self.code_revisions,
            "machines": self.machines,
        })

    def _say(self, message: str) -> None:
        if self.writer and not self.quiet:
            say((f"{self.run_dir}: {message}", "dim"))

    def _finish(self) -> None:
        digest = model_digest(self.model)
        digests = self.dist.gather(digest)
        if self.writer:
            info_extra = {"rank_weight_digests": digests, "ranks_consistent": len(set(digests)) == 1}
            with atomic_directory(self.run_dir / FINAL_DIR) as tmp:
                save_model(self.model, tmp / MODEL_FILE,
                           extra={"dataset": self.data.spec.dataset, "fold": self.fold,
                                  "seed": self.config.train.seed, "fingerprint": self.data.fingerprint})
                (tmp / MODEL_INFO_FILE).write_text(json.dumps(
                    {"model": self.model.name, "log_lik_space": self.model.log_lik_space,
                     "config": self.config.to_dict(), "spec": self.data.spec.to_dict(),
                     "trajflow_version": __version__}, indent=2) + "\n")
            self._write_run_info("finished", info_extra)
            if not self.quiet:
                best = ", ".join(f"{stage} {_kept_by(b)} (epoch {b['epoch']})" for stage, b in self.best.items())
                say(("trained", "green"), f" {self.model.name} -> {self.run_dir / FINAL_DIR}: {best}"
                    + (f"; skipped {self.skipped_total} non-finite steps" if self.skipped_total else ""))
        self.dist.barrier()

    def _write_run_info(self, status: str, extra: dict[str, Any] | None = None) -> None:
        spec = self.data.spec
        info = {
            "model": self.config.model.name, "dataset": spec.dataset, "fold": self.fold,
            "seed": self.config.train.seed, "status": status, "trajflow_version": __version__,
            "data_dir": str(self.data.dataset_dir.resolve()), "fingerprint": self.data.fingerprint,
            "n_past": spec.n_past, "n_future": spec.n_future, "has_map": spec.has_map, "dt": spec.dt,
            "n_train": len(self.data.train), "n_val": len(self.data.val), "validation": self.data.validation,
            "log_lik_space": self.model.log_lik_space, "world_size": self.dist.world, "device": str(self.device),
            "cpu_threads": torch.get_num_threads(), "best": self.best, "skipped_steps": self.skipped_total,
            "started": self.started, "code_revisions": self.code_revisions, "machines": self.machines,
            "final": f"{FINAL_DIR}/{MODEL_FILE}" if status == "finished" else None,
        }
        if self.compiled:
            info["compiled"] = self.compiled
        if self.autoencoder_from is not None:
            info["autoencoder_from"] = self.autoencoder_from
        if status == "finished":
            # to the microsecond: with the weights' digest it tells one training of the final model from the next
            # (a raised budget can end in the second the run first finished, keeping the same weights)
            info["finished"] = dt.datetime.now(dt.timezone.utc).isoformat()
        info.update(extra or {})
        write_run_info(self.run_dir, info)


def _kept_by(best: dict[str, Any]) -> str:
    """What a stage's kept weights were chosen by, for the summary line: "val 0.1234", "val_nll -41.2000" or, for
    the stage "temperature", "T = 1.2, val_nll -24.5800"."""
    if "temperature" in best:
        return f"T = {best['temperature']:g}, val_nll {best['val_nll']:.4f}"
    return f"val_nll {best['val_nll']:.4f}" if "val_nll" in best else f"val {best['val_loss']:.4f}"
