"""`train()`: the run's config (new, resumed or with raised budgets), its data and fold, then one session of the
loop, under ``torchrun`` as one rank of several."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from ..errors import UsageError
from ..model.config import MODEL_NAMES, RunConfig, load_config, with_values
from ..model.runtime import resolve_device, tune_cpu_allocator
from ..rundir import CONFIG_FILE, is_trained, read_run_config
from ..util.atomic import recover
from ..util.progress import say
from ..util.provenance import code_revision
from .data import load_data
from .distributed import DistContext
from .loop import Session
from .policy import (CHANGEABLE, autoencoder_start, budget_raise, check_same_data, first_difference, resume_fold,
                     source_record, started_from)


def train(dataset_dir: str | Path, run_dir: str | Path, *, fold: str | None = None, model: str | None = None,
          config_path: str | Path | None = None, overrides: Sequence[str] = (), seed: int | None = None,
          device: str | None = None, resume: bool = False, quiet: bool = False,
          autoencoder_from: str | Path | None = None) -> Path:
    """Train `model` on the train split of `dataset_dir` (validating on its val split) into `run_dir`.

    `model`, `seed` and `device` override the config (``model.name``, ``train.seed``, ``train.device``); the
    config is the defaults, then `config_path` (TOML), then `overrides` (``section.key=value``). With `resume`, an
    interrupted run continues from its last checkpoint (its saved config is used; options that would change it are
    refused, except raised epoch budgets: see docs/usage.md) and a finished run is returned as is; a directory
    that holds no run (no config.toml) is a UsageError, not a fresh start. With `autoencoder_from`, a new run
    starts from that run's trained autoencoder and trains the flow only (see docs/usage.md). Returns `run_dir`.
    """
    tune_cpu_allocator()
    code_revision()  # read now: a commit or checkout during training must not be credited with it
    run_dir = Path(run_dir)
    dist = DistContext.from_env()
    config, previous = _resolve_config(run_dir, config_path, overrides, model, seed, device, resume)
    fold = resume_fold(run_dir, fold) if resume else fold
    source = Path(autoencoder_from) if autoencoder_from is not None else None
    #: the run to take the autoencoder from now (None: no source, or this run already took it and resumes)
    start_from = source if source is not None and not started_from(run_dir, resume, source) else None
    if resume and previous is None and is_trained(run_dir):
        if dist.rank == 0 and not quiet:
            say((f"{run_dir}: already trained, nothing to resume", "dim"))
        return run_dir
    torch_device = resolve_device(config.train.device, dist.local_rank)
    dist.start(torch_device)
    try:
        data = load_data(dataset_dir, fold, config)
        check_same_data(run_dir, data, resume)
        start = autoencoder_start(start_from, config, data, fold) if start_from is not None else None
        session = Session(run_dir=run_dir, config=config, data=data, device=torch_device, dist=dist, quiet=quiet,
                          fold=fold, autoencoder_from=source_record(run_dir, source, start))
        session.run(resume, start)
    finally:
        dist.stop()
    return run_dir


def _resolve_config(run_dir: Path, config_path: str | Path | None, overrides: Sequence[str], model: str | None,
                    seed: int | None, device: str | None, resume: bool) -> tuple[RunConfig, RunConfig | None]:
    """The run's config and, when a resume changes it (raised epoch budgets, new settings of the stage after the
    flow), the config it was trained with so far (else None). On resume the saved config is used; changes other
    than raised budgets, the settings of the stage after the flow (`policy.REFIT_MODEL_KEYS`) and the device are
    refused."""
    if model is not None and model not in MODEL_NAMES:
        raise UsageError(f"unknown model {model!r}; choose one of {', '.join(MODEL_NAMES)}")
    if resume and not run_dir.is_dir():
        raise UsageError(f"{run_dir}: no such run directory to resume; train without --resume to start a run there")
    saved = read_run_config(run_dir) if resume else None
    if resume and saved is None:
        raise UsageError(f"{run_dir} holds no run to resume ({CONFIG_FILE} is missing); train without --resume to "
                         "start one" + (" in a new directory" if any(run_dir.iterdir()) else ""))
    if saved is not None:
        requested = _with_options(load_config(config_path, overrides, base=saved), model, seed, None)
        if requested == saved:
            return _with_options(saved, None, None, device), None
        raised = budget_raise(saved, requested)
        if raised is None:
            key = first_difference(saved, requested)
            raise UsageError(f"{run_dir} was started with a different configuration ({key}); resume it without "
                             f"changing options (only {CHANGEABLE}), or train into a new directory")
        return _with_options(requested, None, None, device), saved
    recover(run_dir / CONFIG_FILE)  # what a run killed at its start left (a temporary config.toml) is no run
    if not resume and run_dir.exists() and any(run_dir.iterdir()):
        raise UsageError(f"{run_dir} already holds a run; pass --resume to continue it or choose a new directory")
    return _with_options(load_config(config_path, overrides), model, seed, device).validate(), None


def _with_options(config: RunConfig, model: str | None, seed: int | None, device: str | None) -> RunConfig:
    """`config` with the options that override it (--model, --seed, --device), each checked as a setting is."""
    for option, key, value in (("--model", "model.name", model), ("--seed", "train.seed", seed),
                               ("--device", "train.device", device)):
        if value is not None:
            config = with_values(config, {key: value}, source=option)
    return config.validate()
