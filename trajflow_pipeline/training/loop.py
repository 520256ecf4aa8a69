"""The training loop: a session trains the model's stages in turn, epoch by epoch (train, validate, keep the best
weights, checkpoint), then writes the final model. Read it top to bottom from `Session.run`."""

from __future__ import annotations

import datetime as dt
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import torch
from rich.progress import TextColumn
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel

from ..errors import DataError, UsageError
from ..model.batch import SceneBatch
from ..model.checkpoint import load_training_state, save_model, save_training_state
from ..model.compiled import compiled_kernels, preload_kernels
from ..model.config import StageSchedule, TrainConfig
from ..model.models import FlowModel, build_model
from ..rundir import (BEST_FILE, CONFIG_FILE, FINAL_DIR, LOWEST_VAL_LOSS_FILE, STAGE_END_FILE, STATE_FILE, is_trained,
                      read_compiled_kernels, read_run_config, write_compiled_kernels)
from ..util.atomic import atomic_write_text
from ..util.progress import make_progress, say
from .distributed import derive_seed, epoch_shard
from .policy import budget_raise, finished_state, follow_budget, refit_change
from .records import RunRecords
from .state import StageProgress, should_stop
from .steps import StageObjective, adamw, copy_weights, finite_gradients, mean_loss, on_device, part

#: Called after every completed (and checkpointed) epoch with (stage, epoch); tests use it to simulate a kill.
EpochHook = Callable[[str, int], None]
_epoch_hook: EpochHook | None = None


@dataclass
class _GradientStage:
    """A gradient stage being trained: its settings, the parameters it trains, their optimizer and its objective."""

    index: int
    name: str
    schedule: StageSchedule
    params: list[nn.Parameter]
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.ExponentialLR | None
    #: the stage loss, wrapped in DistributedDataParallel under torchrun
    objective: nn.Module
    #: with train.flow_select = "val_nll": the fixed, seeded validation problems of every check (else None)
    select_subset: Tensor | None
    #: problems per rank and batches per rank in an epoch
    per_rank: int
    n_batches: int
    #: the selection (nll, epoch, weights) before a sample-based check that only the stage's end called for
    unscheduled: tuple[float, int, dict[str, Tensor] | None] | None = None

    def done(self, progress: StageProgress) -> bool:
        """Whether the stage ends at `progress`: its epoch limit reached, or early stopping."""
        schedule = self.schedule
        return progress.epoch >= schedule.max_epochs or should_stop(progress, schedule.min_epochs, schedule.patience)


@dataclass
class Session(RunRecords):
    """One call of :func:`~.run.train`: trains the model's stages on the data into the run directory."""

    def run(self, resume: bool, start: dict[str, Any] | None = None) -> None:
        """Train every stage from the first (or from `start`, a training state to go on from; see
        `autoencoder_start`), or, with `resume`, from the run's last checkpoint."""
        torch.manual_seed(self.config.train.seed)
        self.model = build_model(self.config.model, self.data.spec, seed=self.config.train.seed).to(self.device)
        begin = self._begin(resume, start)
        if begin is None:
            return  # finished, and no stage a raised budget limits was stopped by its old one
        stage_index, progress = begin
        train_batch = on_device(self.data.train, self.device)
        val_batch = on_device(self.data.val, self.device)
        self.model.fit_data_constants(train_batch)  # a fresh run's; a resumed one restored its own
        stages = self.model.stages
        with make_progress(self.quiet or not self.writer, TextColumn("{task.fields[status]}", markup=False)) as bars:
            for index in range(stage_index, len(stages)):
                stage = stages[index]
                if stage == FlowModel.TEMPERATURE:
                    self._fit_temperature(stage, val_batch)
                elif stage in self.model.closed_form_stages:
                    self._fit_closed_form(index, stage, train_batch, val_batch)
                else:
                    self._fit_gradient(index, stage, progress, train_batch, val_batch, bars)
                progress = StageProgress()
                self._checkpoint(index + 1, progress)
        self._finish()

    # -- where training starts -------------------------------------------------------------------------------------

    def _begin(self, resume: bool, start: dict[str, Any] | None) -> tuple[int, StageProgress] | None:
        """The stage and progress training starts at (None: the resumed run is finished and stays so), with the
        run's config, run.json and state written as the start calls for."""
        state_path = self.run_dir / STATE_FILE
        if start is not None:
            stage_index, progress = self._restore(start)
            self.started = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
            if self.writer:
                self.run_dir.mkdir(parents=True, exist_ok=True)
                atomic_write_text(self.run_dir / CONFIG_FILE, self.config.to_toml())
                self._write_run_info("training")
                save_training_state(state_path, start)
            return stage_index, progress
        if resume and state_path.is_file():
            return self._resume(load_training_state(state_path, expected_model=self.model.name))
        if resume and (self.run_dir / FINAL_DIR).exists():
            saved = read_run_config(self.run_dir)
            if saved is not None and is_trained(self.run_dir) and refit_change(saved, self.config) \
                    and budget_raise(saved, self.config) == {}:
                return self._resume(finished_state(self.run_dir))  # a published model: the final flow will do
            raise UsageError(f"{self.run_dir}: {STATE_FILE} is missing, so this run cannot be continued or given a "
                             f"larger budget; train into a new directory")
        if self.writer:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.run_dir / CONFIG_FILE, self.config.to_toml())
            self._write_run_info("training")
        return 0, StageProgress()

    def _resume(self, state: dict[str, Any]) -> tuple[int, StageProgress] | None:
        """Go on from the run's checkpoint `state` (as read), following raised epoch budgets and new settings of
        the stage after the flow (:func:`~.policy.follow_budget`)."""
        state_path = self.run_dir / STATE_FILE
        resumed = follow_budget(self.run_dir, self.config, self.model, state, self._say)
        self.config = resumed.config
        if resumed.finished:
            if self.writer:
                save_training_state(state_path, resumed.state)
                atomic_write_text(self.run_dir / CONFIG_FILE, self.config.to_toml())
            return None
        stage_index, progress = self._restore(resumed.state)
        if self.writer and resumed.save:  # run.json first: an interruption now cannot look finished
            if resumed.reopened:
                self._write_run_info("training")
            save_training_state(state_path, resumed.state)
            atomic_write_text(self.run_dir / CONFIG_FILE, self.config.to_toml())
            self._write_log()  # the state's: a reopened run's is cut to where it goes on
        elif self.writer and not is_trained(self.run_dir):  # run.json names the code that continues it
            self._write_run_info("training")
        return stage_index, progress

    # -- stages ----------------------------------------------------------------------------------------------------

    def _fit_closed_form(self, index: int, stage: str, train_batch: SceneBatch, val_batch: SceneBatch) -> None:
        start = time.perf_counter()
        self.model.eval()
        with torch.no_grad():
            self.model.fit_stage(stage, train_batch)
            train_loss = mean_loss(self.model, stage, train_batch, self.config.train.eval_batch_size, self.dist,
                                   self.device)
            val_loss = mean_loss(self.model, stage, val_batch, self.config.train.eval_batch_size, self.dist,
                                 self.device)
        seconds = time.perf_counter() - start
        self.best[stage] = {"epoch": 1, "val_loss": val_loss}
        self._log_epoch(stage, 1, train_loss, val_loss, 0.0, seconds, 0, len(train_batch) / max(seconds, 1e-9))

    def _fit_temperature(self, stage: str, val_batch: SceneBatch) -> None:
        """model.flow_temperature_grid: keep the sampling temperature whose draws give the lowest evaluation NLL on
        model.flow_temperature_problems fixed validation problems. Every value draws from the same seeded noise,
        scaled, so the values differ by the temperature alone. None finite: the grid's value nearest 1, with a
        warning; the run goes on."""
        start = time.perf_counter()
        grid = self.config.model.flow_temperature_grid
        subset = validation_subset(len(val_batch), self.config.model.flow_temperature_problems,
                                   self.config.train.seed)
        curve = {}
        for temperature in grid:
            self.model.set_sampling_temperature(temperature)
            curve[temperature] = self._sample_nll(val_batch, subset, f"temperature {temperature:g}")
        finite = [t for t in grid if math.isfinite(curve[t])]
        chosen = min(finite, key=curve.__getitem__) if finite else min(grid, key=lambda t: abs(t - 1.0))
        self.model.set_sampling_temperature(chosen)
        seconds = time.perf_counter() - start
        self.best[stage] = {"epoch": 1, "temperature": chosen, "val_nll": curve[chosen], "problems": len(subset),
                            "val_nll_by_temperature": {f"{t:g}": curve[t] for t in grid}}
        self._log_epoch(stage, 1, math.nan, curve[chosen], 0.0, seconds, 0, len(subset) * len(grid) / seconds,
                        val_nll=curve[chosen])

    def _fit_gradient(self, index: int, stage: str, progress: StageProgress, train_batch: SceneBatch,
                      val_batch: SceneBatch, bars: Any) -> None:
        """Train gradient stage `stage` on from `progress`, one epoch at a time, until its epoch limit or early
        stopping ends it; every epoch is logged and checkpointed. The stage keeps its best weights."""
        fit = self._prepare(index, stage, progress, len(train_batch), len(val_batch))
        train_batch, val_batch = (self._with_fixed_targets(stage, b) for b in (train_batch, val_batch))
        epoch_task = bars.add_task(f"{stage}", total=fit.schedule.max_epochs, completed=progress.epoch, status="")
        batch_task = bars.add_task("  batches", total=fit.n_batches, status="")
        stop = fit.done(progress)
        while not stop:
            epoch = progress.epoch + 1
            start = time.perf_counter()
            lr_now = fit.optimizer.param_groups[0]["lr"]
            train_loss, skipped, train_seconds = self._train_epoch(fit, epoch, train_batch, start, bars, batch_task)
            val_loss = mean_loss(self.model, stage, val_batch, self.config.train.eval_batch_size, self.dist,
                                 self.device)
            if fit.scheduler is not None:
                fit.scheduler.step()
            improved = _count_epoch(progress, epoch, val_loss)
            stop = fit.done(progress)
            seconds = time.perf_counter() - start
            val_nll, keep = math.nan, improved
            if fit.select_subset is not None:
                val_nll, keep = self._select_by_sample_nll(fit, progress, epoch, val_loss, improved, stop, val_batch)
            if keep:
                self._keep(fit, progress, epoch, val_loss, val_nll)
            self.skipped_total += skipped
            self._log_epoch(stage, epoch, train_loss, val_loss, lr_now, seconds, skipped,
                            self.dist.world * fit.per_rank / max(train_seconds, 1e-9), val_nll)
            progress.optimizer = fit.optimizer.state_dict()
            progress.scheduler = fit.scheduler.state_dict() if fit.scheduler is not None else None
            self._checkpoint(index, progress)
            bars.update(epoch_task, completed=epoch,
                        status=f"train {train_loss:.4f}  val {val_loss:.4f}  best {progress.best_val:.4f}")
            if _epoch_hook is not None:
                _epoch_hook(stage, epoch)
        bars.remove_task(batch_task)
        self._end_stage(fit, progress)

    def _with_fixed_targets(self, stage: str, batch: SceneBatch) -> SceneBatch:
        """`batch` with what `stage` fits computed once, where it cannot change while the stage trains (TrajFlow's
        frozen-autoencoder latents in the flow stage): the same values the steps would compute, at no cost per
        step."""
        targets = self.model.fixed_targets(stage, batch)
        return batch if targets is None else replace(batch, targets=targets)

    def _prepare(self, index: int, stage: str, progress: StageProgress, n_train: int, n_val: int) -> _GradientStage:
        """The stage's settings, its parameters (the only ones left trainable), their optimizer and learning-rate
        schedule (restored from `progress`) and the objective, DDP-wrapped under torchrun."""
        cfg = self.config.train
        schedule = cfg.schedule(stage)
        select_subset = None
        if stage == "flow" and cfg.flow_select == "val_nll":  # a fixed, seeded subset of the validation problems
            select_subset = validation_subset(n_val, cfg.flow_select_problems, cfg.seed)
        params = self.model.stage_parameters(stage)
        trainable = {id(p) for p in params}
        for p in self.model.parameters():
            p.requires_grad_(id(p) in trainable)
        optimizer = adamw(params, schedule.lr, schedule.weight_decay)
        scheduler = (None if schedule.lr_decay is None
                     else torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=schedule.lr_decay))
        if progress.optimizer is not None:
            optimizer.load_state_dict(progress.optimizer)
        if scheduler is not None and progress.scheduler:
            scheduler.load_state_dict(progress.scheduler)
        per_rank = math.ceil(n_train / self.dist.world)
        n_batches = math.ceil(per_rank / schedule.batch_size)
        planned = max(0, min(schedule.min_epochs, schedule.max_epochs) - progress.epoch) * n_batches
        if stage == "flow" and cfg.compiles_flow(self.device.type, planned):
            self._compile(stage, min(schedule.batch_size, per_rank))
        objective: nn.Module = StageObjective(self.model, stage)
        if self.dist.active:
            # Buffers (flow permutations, masks) never change while training: no per-step broadcast needed.
            objective = DistributedDataParallel(objective, device_ids=[self.device] if self.device.type == "cuda"
                                                else None, broadcast_buffers=False)
        return _GradientStage(index, stage, schedule, params, optimizer, scheduler, objective, select_subset,
                              per_rank, n_batches)

    def _compile(self, stage: str, rows: int) -> None:
        """Compile the steps of `stage` for its full batches of `rows` problems, and record how it went. The
        kernels the run kept from an earlier process are loaded first, and what this compile made is kept for the
        next one (a resume, here or on another machine of the same kind), so inductor generates them once per run;
        each process still traces the graphs, and on a machine with an empty cache builds the kept C++ again."""
        self._say(f"compiling the {stage} stage's steps (train.compile_flow = {self.config.train.compile_flow}; "
                  f"a one-off cost)")
        start = time.perf_counter()
        kept, unusable = read_compiled_kernels(self.run_dir)
        if unusable is not None:
            self._say(unusable)
        if kept is not None:
            preload_kernels(kept)
        failure = self.model.compile_stage(stage, rows)
        reused = " with the kernels the run had kept" if kept is not None else ""
        self.compiled[stage] = (f"compiled in {time.perf_counter() - start:.0f} s{reused}" if failure is None
                                else f"eager: {failure}")
        self._say(f"{stage} stage: {self.compiled[stage]}")
        made = compiled_kernels() if failure is None and self.writer else None
        if made is not None and made != kept:
            write_compiled_kernels(self.run_dir, made)

    def _train_epoch(self, fit: _GradientStage, epoch: int, train_batch: SceneBatch, start: float, bars: Any,
                     batch_task: Any) -> tuple[float, int, float]:
        """One pass over this rank's shard of the epoch's seeded permutation: the mean training loss of the steps
        taken (over ranks), the steps skipped for non-finite gradients, and the seconds since `start`."""
        cfg = self.config.train
        torch.manual_seed(derive_seed(cfg.seed, fit.index, epoch, self.dist.rank))
        shard = epoch_shard(len(train_batch), cfg.seed, fit.index, epoch, self.dist)
        self.model.train()
        total, count, skipped = 0.0, 0, 0
        bars.reset(batch_task, total=fit.n_batches)
        batch_size = fit.schedule.batch_size
        for b in range(fit.n_batches):
            idx = shard[b * batch_size:(b + 1) * batch_size]
            value = self._step(fit, part(train_batch, idx, self.device))
            if value is None:
                skipped += 1
            else:
                total += value * len(idx)
                count += len(idx)
            rate = (b + 1) * batch_size / max(time.perf_counter() - start, 1e-9)
            bars.update(batch_task, advance=1, status=f"loss {total / max(count, 1):.4f}  {rate:,.0f} samples/s")
        train_seconds = time.perf_counter() - start
        # Gradients are all-reduced before the finiteness check, so every rank skipped the same steps.
        total, count = self.dist.sum([total, count], self.device)
        return (total / count if count else math.nan), skipped, train_seconds

    def _step(self, fit: _GradientStage, batch: SceneBatch) -> float | None:
        """One optimizer step on `batch`, and its loss; None, and no step, when the gradients are not finite."""
        loss = fit.objective(batch)
        fit.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if not finite_gradients(fit.params, self.config.train.grad_clip):
            fit.optimizer.zero_grad(set_to_none=True)
            return None
        fit.optimizer.step()
        return float(loss.detach())

    def _select_by_sample_nll(self, fit: _GradientStage, progress: StageProgress, epoch: int, val_loss: float,
                              improved: bool, stop: bool, val_batch: SceneBatch) -> tuple[float, bool]:
        """With train.flow_select = "val_nll": the epoch's sample-based validation NLL (NaN between checks) and
        whether its weights are kept; the weights of the lowest validation loss are saved beside them."""
        cfg = self.config.train
        val_nll, keep = math.nan, False
        if improved and self.writer:  # what "val_loss" would have kept, for comparing the two
            save_model(self.model, self.run_dir / LOWEST_VAL_LOSS_FILE.format(stage=fit.name),
                       extra={"stage": fit.name, "epoch": epoch, "val_loss": val_loss})
        if epoch % cfg.flow_select_every == 0 or stop:
            if epoch % cfg.flow_select_every:
                fit.unscheduled = (progress.selected_nll, progress.selected_epoch, progress.best_weights)
            val_nll = self._sample_nll(val_batch, fit.select_subset, f"epoch {epoch}")
            keep = math.isfinite(val_nll) and val_nll < progress.selected_nll
            if keep:
                progress.selected_nll, progress.selected_epoch = val_nll, epoch
        return val_nll, keep

    def _keep(self, fit: _GradientStage, progress: StageProgress, epoch: int, val_loss: float,
              val_nll: float) -> None:
        """Keep the epoch's weights as the stage's best (in memory, and in checkpoints/best-<stage>)."""
        progress.best_weights = copy_weights(self.model)
        if self.writer:
            save_model(self.model, self.run_dir / BEST_FILE.format(stage=fit.name),
                       extra={"stage": fit.name, "epoch": epoch, "val_loss": val_loss,
                              **({"val_nll": val_nll} if fit.select_subset is not None else {})})

    def _end_stage(self, fit: _GradientStage, progress: StageProgress) -> None:
        """Save the stage's end state, load its best weights and record which epoch they are from."""
        # The stage's last epoch, before its best weights are loaded: a larger budget continues from here, as if
        # the stage had gone on, so without the check that only the end of the stage called for.
        end = progress
        if fit.unscheduled is not None:
            end = replace(progress, selected_nll=fit.unscheduled[0], selected_epoch=fit.unscheduled[1],
                          best_weights=fit.unscheduled[2])
        self._checkpoint(fit.index, end, STAGE_END_FILE.format(stage=fit.name))
        self.model.drop_compiled()
        if progress.best_weights is not None:
            self.model.load_state_dict(progress.best_weights)
        self.best[fit.name] = _best_record(progress, by_sample_nll=fit.select_subset is not None)

    def _sample_nll(self, val_batch: SceneBatch, subset: Tensor, label: str) -> float:
        """:func:`sample_nll` of the model on the validation problems `subset`. Rank 0 computes it and every rank
        gets its value, so all ranks keep the same epoch (or temperature). Draws ROME cannot fit (non-finite, or
        all identical) give NaN, which is never kept, with a warning: the run goes on."""
        value: float | None = None
        if self.dist.rank == 0:
            try:
                value = sample_nll(self.model, val_batch, self.data.val_groups, subset, self.config.train,
                                   self.device)
            except DataError as error:
                value = math.nan
                if not self.quiet:
                    say(("warning:", "yellow"), f" {label}: no sample-based validation NLL ({error}); not kept")
        return float(self.dist.gather(value)[0])


def sample_nll(model: nn.Module, val_batch: SceneBatch, val_groups: np.ndarray, subset: Tensor, train: TrainConfig,
               device: torch.device | str = "cpu") -> float:
    """The evaluation's NLL (nats; ROME densities of `train.flow_select_samples` draws, pooled over identical
    inputs as `val_groups` says, at most `train.flow_select_max_pooled` a pool) of `model` on the validation
    problems `subset`, drawn from noise seeded by `train.seed`: the same noise at every call, so that two calls
    differ only by the model. DataError where ROME cannot fit the draws."""
    from ..metrics import compute_metrics

    generator = torch.Generator(device=device).manual_seed(train.seed)
    model.eval()
    draws = []
    with torch.no_grad():
        for chunk in subset.split(max(1, train.eval_batch_size)):
            draws.append(model.sample(part(val_batch, chunk, device), train.flow_select_samples, generator=generator)
                         .trajectories.double().cpu())
    ground_truth = val_batch.future.index_select(0, subset.to(val_batch.future.device)).double().cpu()
    table = compute_metrics(torch.cat(draws).numpy(), ground_truth.numpy(), metrics=("nll",),
                            group_id=val_groups[subset.numpy()], max_pooled=train.flow_select_max_pooled, workers=1,
                            quiet=True)
    return float(table.filter(pl.col("aggregate")).get_column("value")[0])


def _count_epoch(progress: StageProgress, epoch: int, val_loss: float) -> bool:
    """Count `epoch` into the stage's early-stopping bookkeeping; whether its validation loss is the best yet."""
    progress.epoch = epoch
    improved = math.isfinite(val_loss) and val_loss < progress.best_val
    if improved:
        progress.best_val, progress.best_epoch, progress.bad_epochs = val_loss, epoch, 0
    else:
        progress.bad_epochs += 1
    return improved


def validation_subset(n_val: int, problems: int, seed: int) -> Tensor:
    """The fixed validation problems of the sample-based checks: the first `problems` of a permutation seeded by
    the training seed, in ascending order."""
    return torch.randperm(n_val, generator=torch.Generator().manual_seed(seed))[:problems].sort().values


def _best_record(progress: StageProgress, by_sample_nll: bool) -> dict[str, Any]:
    """What run.json's "best" says of a finished gradient stage: the epoch of its kept weights and why they were
    kept (the lowest validation loss, or, by sample-based NLL, the lowest NLL checked beside the lowest loss)."""
    if by_sample_nll and progress.selected_epoch:
        return {"epoch": progress.selected_epoch, "val_nll": progress.selected_nll, "selected_by": "val_nll",
                "lowest_val_loss": progress.best_val, "lowest_val_loss_epoch": progress.best_epoch}
    if by_sample_nll:  # no check gave a finite value: the last weights stay
        return {"epoch": progress.epoch, "val_loss": progress.best_val,
                "selected_by": "last epoch (no finite sample-based validation NLL)",
                "lowest_val_loss": progress.best_val, "lowest_val_loss_epoch": progress.best_epoch}
    return {"epoch": progress.best_epoch, "val_loss": progress.best_val}

