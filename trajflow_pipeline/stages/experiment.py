"""`trajflow experiment CONFIG -o EXP`: from raw files to the report: build the data stages, train + eval every
(model, fold, seed) of a dataset protocol, resumably, and write ``EXP/report``.

The config file: :mod:`trajflow_pipeline.stages.experiment_config`; its data stages (an ingest, augmentations),
each built only when its options or inputs changed: :mod:`trajflow_pipeline.stages.data_stages`. A run trained on
data that a stage has changed since is moved to ``EXP/superseded/`` and trained again.

Runs land in ``EXP/runs/<model>-<fold>-s<seed>/``. Re-running the same command skips finished runs and resumes an
interrupted training from its last checkpoint, so an interrupted experiment never repeats finished work. The
config may change between calls only by raising epoch budgets (``train.ae_max_epochs`` / ``train.flow_max_epochs`` /
``train.ae_patience`` / ``train.flow_patience`` in ``[train] set`` or ``[models.*] set``; comments, name and
description are free): runs that the larger budget would not have stopped where the old one did then continue from
their last epoch (see `trajflow train` in docs/usage.md) and are evaluated again; and by the settings of the stage
after the flow (``model.flow_temperature_grid`` / ``model.flow_temperature_problems``): finished runs fit that stage
again on their final flow and are evaluated again.
``EXP/metrics.parquet`` concatenates every run's metrics; ``EXP/experiment.json`` lists the runs.

Runs are worked on model by model, the models fitted in closed form (the constant-velocity baseline) first: they
take minutes where a trained model takes hours, so a report of an unfinished experiment has its reference rows.

Several processes can work on one experiment directory: ``--jobs N`` runs N runs at once in worker processes,
``--ray ADDRESS`` makes each run a task on a Ray cluster (:mod:`trajflow_pipeline.util.scheduler` holds both
backends), and the same command may also be started again (another terminal, another node on a shared file
system). Each run is claimed by one process (an OS file lock in ``EXP/runs/.<run>.lock``, released when its holder
exits, however it exits); a run claimed elsewhere is left to its holder. On a CPU each of N workers gets 1/N of
torch's threads: small models gain more from parallel runs than from threads. A Ray task asks for
``--cpus-per-run`` CPUs (torch threads and evaluation workers) and, with ``--device cuda`` or ``auto`` on a cluster
that has GPUs, one GPU; EXP must be on a file system every node shares. A Ray task whose worker died (killed, node
lost) is run again and resumes the run from its last checkpoint; a run that fails with a data or usage error is
not retried: it is reported, with its one-line error, when the other runs are done. ``--only PATTERN`` limits a
process to the runs whose names match (shell patterns: ``flomo-zara2-s0``, ``'*-eth-*'``; ``trajflow-*`` also
matches trajflow-no-ae's runs): to have one run trained now, beside a process that works through the plan, or to
split an experiment between machines. The index
still covers every finished run of the plan.

``--autoencoder-from DIR`` (another experiment directory, or a folder that ``docs/results/publish.py`` wrote) makes
each new run whose twin ``DIR/runs/<run>`` or ``DIR/models/<run>`` is finished take that twin's autoencoder and
train only its flow (`trajflow train --autoencoder-from`): for ablations of flow and context settings, without
the autoencoder stage, and with both sides on one autoencoder whatever machine trained it. Runs without a twin
train their own.
"""

from __future__ import annotations

import fnmatch
import json
import os
import shutil
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future, as_completed
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import polars as pl

from ..data import list_folds
from ..errors import TrajflowError, UsageError
from ..metrics.parallel import resolve_workers
from ..model.config import RunConfig, load_config, toml_value
from ..model.models import MODEL_CLASSES
from ..rundir import (CONFIG_FILE, EVAL_DIR, METRICS_FILE, final_model_identity, is_evaluated, is_trained,
                      read_run_config, read_run_info)
from ..schemas import data_mismatch, open_dataset
from ..training import (BUDGET_KEYS, REFIT_MODEL_KEYS, budget_raise, budget_size, describe_refit, first_difference,
                        raise_blocker, refit_change, refit_matters)
from ..util import input_files
from ..util.atomic import atomic_file, atomic_write_text
from ..util.claim import claim, claims_supported
from ..util.progress import say
from ..util.scheduler import LocalPool, RayPool, Resources, cluster_resources, one_line
from .evaluate import EvalOptions, evaluate
from .data_stages import build_data
from .experiment_config import (SAVED_CONFIG, ExperimentConfig, load_experiment, load_saved_experiment,
                                save_experiment_config, saved_overrides)
from .report import report as make_report

#: the experiment's index: the runs planned and finished, the data and the config
INDEX_FILE = "experiment.json"
#: times Ray runs a run again whose worker died (each time it resumes from the run's last checkpoint)
RAY_RETRIES = 3
#: in the experiment directory: the report written when the experiment ends, and runs trained on data since changed
REPORT_DIR, SUPERSEDED_DIR = "report", "superseded"


def _folds(config: ExperimentConfig, data: Path) -> list[str | None]:
    available = list_folds(data)
    if not available:
        if config.folds not in (None, "all"):
            raise UsageError(f"dataset {data} has no folds, but the experiment lists folds {config.folds}")
        return [None]
    if config.folds in (None, "all"):
        return list(available)
    unknown = [f for f in config.folds if f not in available]
    if unknown:
        raise UsageError(f"unknown fold(s) {', '.join(unknown)}; the dataset has {', '.join(available)}")
    return list(config.folds)


def run_name(model: str, fold: str | None, seed: int) -> str:
    """Directory name of one run of an experiment."""
    return f"{model}-{fold or 'all'}-s{seed}"


def experiment_complete(out: str | Path) -> bool:
    """Whether every planned run of the experiment in `out` is finished (its index, experiment.json, says so)."""
    index = json.loads(input_files.read_text(Path(out) / INDEX_FILE))
    return isinstance(index, dict) and index.get("runs") == index.get("planned")


def run_experiment(config_path: str | Path, out: str | Path, *, device: str = "auto", quiet: bool = False,
                   jobs: int = 1, only: Sequence[str] = (), ray: str | None = None, cpus_per_run: int = 1,
                   overrides: Sequence[str] = (), report: bool = False,
                   autoencoder_from: str | Path | None = None) -> Path:
    """Build the data stages that are not current, then train and evaluate every run of the experiment into `out`
    (resuming what an earlier call left), with `jobs` worker processes, or as tasks of `cpus_per_run` CPUs on the
    Ray cluster at `ray`; with `only` (run-name patterns), just the runs that match; then, with `report` (as the
    command does unless --no-report), write the report into ``out/report``. `overrides` (``KEY=VALUE``) apply on
    top of the config file. With `autoencoder_from`, new runs take their twin's autoencoder there. Runs that
    another process is working on are left to it (see the module docstring)."""
    if jobs < 1:
        raise UsageError(f"--jobs must be at least 1, got {jobs}")
    if jobs > 1 and not claims_supported():
        raise UsageError("--jobs needs POSIX file locks (fcntl), which this platform lacks: use --jobs 1")
    if ray is not None and jobs > 1:
        raise UsageError("--jobs and --ray exclude each other: on Ray, as many runs run at once as the cluster has "
                         "room for (--cpus-per-run sets a run's share)")
    if cpus_per_run < 1:
        raise UsageError(f"--cpus-per-run must be at least 1, got {cpus_per_run}")
    twins = Path(autoencoder_from) if autoencoder_from is not None else None
    if twins is not None and not twins.is_dir():
        raise UsageError(f"--autoencoder-from {twins}: no such directory")
    overrides = list(overrides)
    config = load_experiment(config_path, overrides, check_inputs=True)
    out = Path(out)
    text = input_files.read_text(config_path)
    changed = (out / SAVED_CONFIG).exists() and (input_files.read_text(out / SAVED_CONFIG) != text
                                                 or saved_overrides(out) != overrides)
    if changed:
        _check_budgets_only(out, config, quiet)
    build_data(config, quiet=quiet)
    data = config.data_path
    plan = _plan(config, data)
    if changed:  # every run must be able to follow the raised budgets before anything changes
        blockers = [b for model, fold, seed in plan
                    if not trained_on_other_data(run_dir := out / "runs" / run_name(model, fold, seed), data)
                    and (b := raise_blocker(run_dir, run_overrides(config, model, run_dir)))]
        if blockers:
            raise UsageError("cannot raise the budgets of this experiment: " + "; ".join(blockers)
                             + ". Use a new -o for the larger budget")
    selected = select_runs(plan, only)
    left = sum(not run_done(out / "runs" / name, run_overrides(config, model, out / "runs" / name), data)
               for model, fold, seed in plan if (name := run_name(model, fold, seed)) in selected)
    # Workers beyond the runs left to do would only idle while holding their share of the threads.
    jobs = max(1, min(jobs, left))
    pool = _ray_pool(ray, device, cpus_per_run) if ray is not None and left else None
    out.mkdir(parents=True, exist_ok=True)
    save_experiment_config(out, text, overrides)
    # The index before any work, so that an experiment killed before its first run finishes can still be published
    # (docs/results/publish.py reads it) with the resume states of the runs it was training.
    _write_index(out, config, data, plan)
    if pool is not None:
        if not quiet:
            say(f"Ray cluster {ray}: each run a task of {cpus_per_run} CPU(s)"
                + (" and a GPU" if pool.resources.gpus else "") + f", up to {pool.capacity} at once")
        _work_in_pool(config, data, out, pool, device=device, quiet=quiet, selected=selected, threads=cpus_per_run,
                      eval_options=replace(config.eval_options, workers=cpus_per_run), twins=twins)
    elif jobs == 1:
        _work(config, data, out, device=device, quiet=quiet, selected=selected, twins=twins)
    else:
        _work_in_processes(config, data, out, device=device, quiet=quiet, jobs=jobs, selected=selected, twins=twins)
    _write_index(out, config, data, plan)
    unfinished = [run_name(*key) for key in plan if not run_done(
        run_dir := out / "runs" / run_name(*key), run_overrides(config, key[0], run_dir), data)]
    elsewhere = [name for name in unfinished if name in selected]
    if elsewhere and not quiet:
        say((f"{len(elsewhere)} run(s) are still in progress in another process", "yellow"),
            f" ({', '.join(elsewhere)}); the index includes them once they finish")
    if len(elsewhere) < len(unfinished) and not quiet:
        say(f"{len(unfinished) - len(elsewhere)} unfinished run(s) were not selected by --only")
    if report and len(unfinished) < len(plan):
        make_report([out], out / REPORT_DIR, quiet=quiet)
    return out


def select_runs(plan: list[tuple[str, str | None, int]], only: Sequence[str]) -> frozenset[str]:
    """Names of the planned runs that match any of the shell patterns `only` (all of them when it is empty). A
    pattern that matches no planned run is an error, so that a typo does not silently do nothing. Matching is
    case-sensitive on every platform, as run directories are."""
    names = [run_name(*key) for key in plan]
    if isinstance(only, str):
        only = (only,)
    if not only:
        return frozenset(names)
    unmatched = [pattern for pattern in only if not any(fnmatch.fnmatchcase(name, pattern) for name in names)]
    if unmatched:
        raise UsageError(f"--only {', '.join(map(repr, unmatched))} matches no run of this experiment; its runs are "
                         f"{', '.join(names)}")
    return frozenset(name for name in names if any(fnmatch.fnmatchcase(name, pattern) for pattern in only))


def _check_budgets_only(out: Path, config: ExperimentConfig, quiet: bool) -> None:
    """Accept a config that differs from the one the experiment in `out` was made with only by raised epoch
    budgets, the settings of the stage after the flow (finished runs fit it again), its data stages (their changes
    rebuild what they change, and the runs trained on other data are trained again) and comments, name or
    description; anything else would mix settings in one directory."""
    def different(what: str) -> UsageError:
        return UsageError(f"{out}: this experiment directory was made with a different config "
                          f"({out / SAVED_CONFIG}; {what}); resuming would mix settings (only epoch budgets, the "
                          f"settings of the stage after the flow and the data stages may change). Use a new -o, or "
                          f"delete it")

    try:
        saved = load_saved_experiment(out)
    except UsageError as error:
        raise different(str(error)) from None
    protocol = {"name": "", "train_overrides": (), "model_overrides": {}, "source": {}, "file": Path(),
                "data_path": Path(), "ingest": None, "ingest_options": {}, "augment": ()}
    before, after = vars(replace(saved, **protocol)), vars(replace(config, **protocol))
    for key in before:
        if before[key] != after[key]:
            raise different(f"{key}: {before[key]!r} vs {after[key]!r}")
    raised: dict[str, tuple[int, int]] = {}
    refits: dict[str, tuple[Any, Any]] = {}
    for model in config.models:
        before, after = _run_config(saved, model), _run_config(config, model)
        change = budget_raise(before, after)
        if change is None:
            raise different(f"{model}: {first_difference(before, after)}")
        raised.update(change)
        if refit_matters(before, after):
            refits.update(refit_change(before, after))
    if raised and not quiet:
        say("epoch budgets raised (" + ", ".join(f"train.{key} {old} -> {new}" for key, (old, new) in raised.items())
            + "): runs the larger budget would not have stopped where the old one did continue from their last "
              "epoch and are evaluated again")
    if refits and not quiet:
        say(f"the stage after the flow changed ({describe_refit(refits)}): finished runs fit it again on their final "
            "flow and are evaluated again")


def run_overrides(config: ExperimentConfig, model: str, run_dir: Path | None = None) -> list[str]:
    """The `--set` overrides the experiment gives `model`'s runs (the one in `run_dir`, when given), ending with
    the settings of the stage after the flow (REFIT_MODEL_KEYS: the experiment's, so that one it no longer sets
    goes back to the default) and every epoch budget spelled out: the experiment's, or the run's own where that is
    higher.

    A run resumes from its saved config with these applied, so a budget the experiment config no longer sets (an
    override deleted, back to the default) must be named too, or the run would keep its old, lower one. A budget
    raised beyond the experiment's for one run (`trajflow train --resume --set ...`) stays: an experiment never
    lowers a budget, it would only refuse to resume such a run. (A change of the built-in default budget counts as
    a change of the experiment's: its runs would continue to the new default.)"""
    given = [*config.train_overrides, *config.model_overrides.get(model, ())]
    requested = load_config(overrides=[*given, f"model.name={model}"])
    budgets = requested.train
    saved = None if run_dir is None else read_run_config(run_dir)
    own = saved.train if saved is not None else budgets
    larger = {key: max(getattr(budgets, key), getattr(own, key), key=partial(budget_size, key))
              for key in BUDGET_KEYS}  # (a patience of 0, no early stopping, is the largest)
    return [*given, *(f"model.{key}={toml_value(getattr(requested.model, key))}" for key in REFIT_MODEL_KEYS),
            *(f"train.{key}={value}" for key, value in larger.items())]


def _run_config(config: ExperimentConfig, model: str) -> RunConfig:
    """The training config the experiment gives `model`'s runs (the seed aside)."""
    return load_config(overrides=[*run_overrides(config, model), f"model.name={model}"])


def _plan(config: ExperimentConfig, data: Path) -> list[tuple[str, str | None, int]]:
    """(model, fold, seed) of every run, in the order they are worked on (see `plan_order`)."""
    return plan_order(config.models, _folds(config, data), config.seeds)


def fitted_in_closed_form(model: str) -> bool:
    """Whether every training stage of `model` is a closed-form fit (no gradient descent: minutes, not hours)."""
    family = MODEL_CLASSES[model]
    return set(family.stages) <= set(family.closed_form_stages)


def plan_order(models: list[str], folds: list[str | None], seeds: list[int]) -> list[tuple[str, str | None, int]]:
    """(model, fold, seed) of every run, model by model: those fitted in closed form first, so that their rows (the
    baselines every table compares against) exist long before the trained models are done; otherwise the config's
    order."""
    ordered = sorted(models, key=lambda m: not fitted_in_closed_form(m))  # stable: the config's order otherwise
    return [(m, f, s) for m in ordered for f in folds for s in seeds]


def run_done(run_dir: Path, overrides: list[str], data: Path | None = None) -> bool:
    """Finished (see `rundir.is_evaluated`) with the config the experiment now gives it (its budgets were not raised,
    its stage after the flow not changed where it has one) and, when `data` is given, on that dataset as it is
    now."""
    if not is_evaluated(run_dir) or (data is not None and trained_on_other_data(run_dir, data)):
        return False
    saved = read_run_config(run_dir)
    if saved is None:
        return True
    requested = load_config(overrides=overrides, base=saved)
    return requested == saved or (budget_raise(saved, requested) == {} and not refit_matters(saved, requested))


def trained_on_other_data(run_dir: Path, data: Path) -> str | None:
    """How the data the run in `run_dir` was trained on differs from the dataset `data` as it is now (None: the
    same, or nothing trained there yet): after a data stage changed, its runs are trained again."""
    recorded = (read_run_info(run_dir) or {}).get("fingerprint")
    if not isinstance(recorded, dict) or not recorded:
        return None
    return data_mismatch(recorded, open_dataset(data).fingerprint())


def _set_aside(run_dir: Path, out: Path, quiet: bool) -> None:
    """Move a run trained on other data to ``out/superseded/<run>`` (replacing an older one there), so that it is
    trained again from scratch and its results stay readable until then."""
    target = out / SUPERSEDED_DIR / run_dir.name
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.exists():
        shutil.rmtree(target)
    os.replace(run_dir, target)
    if not quiet:
        say((f"{run_dir.name}: trained on data that a data stage has changed since, moved to {target}; training it "
             "again", "yellow"))


@dataclass(frozen=True)
class RunJob:
    """One planned run as a worker gets it: what to train and evaluate, where, and with how many torch threads
    (None: as the worker has them)."""

    config: ExperimentConfig
    data: Path
    out: Path
    model: str
    fold: str | None
    seed: int
    device: str
    eval_options: EvalOptions
    threads: int | None = None
    #: --autoencoder-from: the directory whose runs (or published models) of the same name lend their autoencoder
    twins: Path | None = None

    @property
    def name(self) -> str:
        return run_name(self.model, self.fold, self.seed)

    def autoencoder_source(self, run_dir: Path) -> Path | None:
        """The finished twin whose autoencoder `run_dir` takes: for a new run of a model with an autoencoder stage,
        the first of ``twins/runs/<run>`` and ``twins/models/<run>`` that is finished; for a run already started,
        the twin it started from (None if it trained its own)."""
        if self.twins is None or "autoencoder" not in MODEL_CLASSES[self.model].stages:
            return None
        candidates = [self.twins / folder / self.name for folder in ("runs", "models")]
        if (run_dir / CONFIG_FILE).is_file():
            recorded = ((read_run_info(run_dir) or {}).get("autoencoder_from") or {}).get("run")
            return next((c for c in candidates if str(c.resolve()) == recorded), None)
        return next((c for c in candidates if is_trained(c)), None)


@dataclass(frozen=True)
class RunOutcome:
    """How a run handed to a worker ended: "done", "elsewhere" (another process holds it) or "failed" (`error`)."""

    status: str
    error: str = ""


def _do_run(job: RunJob, *, quiet: bool, starting: Callable[[], None] = lambda: None) -> bool:
    """Claim the run, then train it (resuming what is there) and evaluate it unless it is finished; `starting` is
    called once the run is ours and not finished. False, having done nothing, when another process holds it."""
    from ..training import train

    run_dir = job.out / "runs" / job.name
    with claim(job.out / "runs" / f".{job.name}.lock") as mine:
        if not mine:
            return False
        if trained_on_other_data(run_dir, job.data):
            _set_aside(run_dir, job.out, quiet)
        overrides = run_overrides(job.config, job.model, run_dir)  # as the run is now that it is ours
        if run_done(run_dir, overrides):  # finished by another process between the check and the claim
            return True
        starting()
        # Returns at once for a trained run; continues a run whose budget was raised (when that budget
        # stopped it: otherwise its model, and so its evaluation, stay as they are), or one a killed worker left.
        model_before = final_model_identity(run_dir)
        train(job.data, run_dir, fold=job.fold, model=job.model, config_path=None, overrides=overrides,
              seed=job.seed, device=job.device, resume=(run_dir / CONFIG_FILE).is_file(), quiet=quiet,
              autoencoder_from=job.autoencoder_source(run_dir))
        if not is_evaluated(run_dir) or final_model_identity(run_dir) != model_before:
            evaluate(run_dir, data=job.data, options=job.eval_options, device=job.device, quiet=quiet)
    return True


def _work(config: ExperimentConfig, data: Path, out: Path, *, device: str, quiet: bool,
          selected: frozenset[str] | None = None, twins: Path | None = None) -> None:
    """Go through the plan in this process and do each run (of the `selected` names, if given) that is neither
    finished nor claimed by another process; the first error ends the experiment."""
    plan = _plan(config, data)

    def note(message: str, style: str = "") -> None:
        if not quiet:
            say((message, style))

    for index, (model, fold, seed) in enumerate(plan, start=1):
        name = run_name(model, fold, seed)
        if selected is not None and name not in selected:
            continue
        if run_done(out / "runs" / name, run_overrides(config, model, out / "runs" / name), data):
            note(f"{index}/{len(plan)} {name}: done earlier, skipped", "dim")
            continue
        job = RunJob(config, data, out, model, fold, seed, device, config.eval_options, twins=twins)
        if not _do_run(job, quiet=quiet, starting=lambda: note(f"{index}/{len(plan)} {name}", "bold")):
            note(f"{index}/{len(plan)} {name}: in progress in another process, left to it", "dim")
            continue
        note(f"{index}/{len(plan)} {name}: done", "green")
        _write_index(out, config, data, plan)


def _run_task(job: RunJob) -> RunOutcome:
    """A run in a worker process or a Ray task. A data or usage error is the run's outcome, returned rather than
    raised, so that Ray does not retry it (it would fail again); anything else (an interruption, a bug) is raised."""
    if job.threads is not None:
        import torch

        torch.set_num_threads(job.threads)
    try:
        return RunOutcome("done" if _do_run(job, quiet=True) else "elsewhere")
    except TrajflowError as error:
        return RunOutcome("failed", one_line(error))


def _work_in_pool(config: ExperimentConfig, data: Path, out: Path, pool: Executor, *, device: str, quiet: bool,
                  selected: frozenset[str], eval_options: EvalOptions, threads: int | None,
                  twins: Path | None = None) -> None:
    """Hand each selected run that is not finished to `pool` (in plan order), write the index as runs finish, and
    raise, once every run has ended, a TrajflowError naming each run that failed with its error."""
    plan = _plan(config, data)
    failed: list[str] = []
    with pool:
        jobs: dict[Future, tuple[int, str]] = {}
        for index, (model, fold, seed) in enumerate(plan, start=1):
            name = run_name(model, fold, seed)
            if name not in selected:
                continue
            if run_done(out / "runs" / name, run_overrides(config, model, out / "runs" / name), data):
                if not quiet:
                    say((f"{index}/{len(plan)} {name}: done earlier, skipped", "dim"))
                continue
            job = RunJob(config, data, out, model, fold, seed, device, eval_options, threads, twins)
            jobs[pool.submit(_run_task, job)] = (index, name)
        for future in as_completed(jobs):
            index, name = jobs[future]
            try:
                outcome = future.result()
            except Exception as error:  # the worker died (on Ray: beyond its retries), or a bug
                outcome = RunOutcome("failed", one_line(error))
            if outcome.status == "failed":
                failed.append(f"{name}: {outcome.error}")
                if not quiet:
                    say((f"{index}/{len(plan)} {name}: failed", "red"), f" ({outcome.error})")
            elif outcome.status == "elsewhere":
                if not quiet:
                    say((f"{index}/{len(plan)} {name}: in progress in another process, left to it", "dim"))
            else:
                if not quiet:
                    say((f"{index}/{len(plan)} {name}: done", "green"))
                _write_index(out, config, data, plan)
    if failed:
        _write_index(out, config, data, plan)
        raise TrajflowError(f"{len(failed)} of {len(jobs)} run(s) failed: {'; '.join(failed)}. Finished runs are "
                            "kept; running the same command again resumes the rest")


def _work_in_processes(config: ExperimentConfig, data: Path, out: Path, *, device: str, quiet: bool,
                       jobs: int, selected: frozenset[str], twins: Path | None = None) -> None:
    """The runs in `jobs` worker processes on this machine; torch threads and evaluation workers are shared out."""
    import torch

    threads = max(1, torch.get_num_threads() // jobs)
    options = config.eval_options
    if options.workers is None:
        options = replace(options, workers=max(1, resolve_workers(None) // jobs))
    if not quiet:
        say(f"{jobs} worker processes, {threads} torch thread(s) and {options.workers} evaluation worker(s) each")
    _work_in_pool(config, data, out, LocalPool(jobs), device=device, quiet=quiet, selected=selected,
                  eval_options=options, threads=threads, twins=twins)


def _ray_pool(address: str, device: str, cpus: int) -> RayPool:
    """The Ray cluster at `address` as a pool of run tasks of `cpus` CPUs and, for `device` cuda (or auto on a
    cluster with GPUs), one GPU; a usage error for a request the cluster can never meet (a task would wait
    forever)."""
    if device.startswith("cuda:"):
        raise UsageError(f"--device {device} with --ray: use --device cuda (Ray gives each run its GPU)")
    total = cluster_resources(address)
    gpus = 1.0 if device == "cuda" or (device == "auto" and total.gpus >= 1) else 0.0
    if gpus > total.gpus:
        raise UsageError(f"--device {device}: the Ray cluster at {address} has no GPU")
    if cpus > total.cpus:
        raise UsageError(f"--cpus-per-run {cpus}: the Ray cluster at {address} has {total.cpus:g} CPU(s)")
    return RayPool(address, Resources(cpus=cpus, gpus=gpus), retries=RAY_RETRIES)


def _write_index(out: Path, config: ExperimentConfig, data: Path, plan: list[tuple[str, str | None, int]]) -> None:
    """experiment.json and the concatenated metrics of the runs finished so far (with the config the experiment
    now gives them); one process at a time, so that both files always describe the same runs. experiment.json's
    `plan` gives every planned run's model, fold and seed, so that a report of unfinished work knows what is
    missing."""
    runs = [f"runs/{run_name(*key)}" for key in plan]
    with claim(out / ".index.lock", wait=True):
        finished = [r for r, key in zip(runs, plan) if run_done(out / r, run_overrides(config, key[0], out / r), data)]
        if finished:
            metrics = pl.concat([input_files.read_parquet(out / r / EVAL_DIR / METRICS_FILE) for r in finished],
                                how="vertical_relaxed")
            with atomic_file(out / "metrics.parquet") as tmp:
                metrics.write_parquet(tmp)
        plan_rows = [{"run": r, "model": model, "fold": fold, "seed": seed}
                     for r, (model, fold, seed) in zip(runs, plan)]
        atomic_write_text(out / INDEX_FILE, json.dumps(
            {"name": config.name, "data": str(data.resolve()), "runs": finished, "planned": runs, "plan": plan_rows,
             "config": config.source}, indent=2, default=str) + "\n")
