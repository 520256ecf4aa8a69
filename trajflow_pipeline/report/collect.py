"""Turn the report's inputs (run and experiment directories) into validated :class:`Run` records and polars frames.

A *run* is a directory written by `trajflow train` + `trajflow eval`; the report reads only its ``eval/``
folder (``eval.json``, ``metrics.parquet``, ``predictions.parquet``, ``ground_truth.parquet``) and, when present,
``train_log.csv`` / ``train_log.parquet``. An *experiment* directory holds ``experiment.json`` whose ``runs``
lists its finished runs relative to it. Every problem becomes one line naming the path at fault.

A run whose draws are gone (an evaluated copy that kept only eval.json and the metric rows a report reads, see
:func:`report_rows`: docs/results/publish.py) reports the same tables; only the figures drawn from draws leave it
out (:func:`has_draws`).
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import polars as pl

from ..errors import DataError, TrajflowError
from ..rundir import (EVAL_DIR, EVAL_FILE, GROUND_TRUTH_FILE, LOG_FILES, METRICS_FILE, PREDICTIONS_FILE,
                      looks_like_run)
from ..util import input_files
from .paper import UNBOUNDED_PREFIX, model_label, model_order

EXPERIMENT_FILE = "experiment.json"

#: Column kinds the report checks; the dtype each is cast to.
_KINDS: dict[str, pl.DataType] = {"int": pl.Int64, "float": pl.Float64, "str": pl.String, "bool": pl.Boolean}

METRICS_COLUMNS = {"metric": "str", "value": "float", "aggregate": "bool"}
PREDICTION_COLUMNS = {"sample_id": "int", "draw": "int", "step": "int", "x": "float", "y": "float",
                      "log_lik": "float"}
GROUND_TRUTH_COLUMNS = {"sample_id": "int", "group_id": "int", "joint_id": "int", "step": "int", "x": "float",
                        "y": "float"}
TRAIN_LOG_COLUMNS = {"epoch": "int", "stage": "str", "train_loss": "float"}
TRAIN_LOG_OPTIONAL = {"val_loss": "float", "lr": "float", "seconds": "float"}
#: CSV logs are typed explicitly: an all-empty val_loss column would otherwise be read as text.
_CSV_LOG_TYPES: dict[str, pl.DataType] = {"stage": pl.String, "train_loss": pl.Float64, "val_loss": pl.Float64,
                                          "lr": pl.Float64, "seconds": pl.Float64}


@dataclass(frozen=True)
class Run:
    """One evaluated run: where it is, what it is (from eval.json), and which experiment listed it."""

    path: Path
    name: str
    model: str
    dataset: str
    fold: str | None
    seed: int
    info: dict[str, Any] = field(repr=False)
    experiment: str | None = None

    @property
    def eval_dir(self) -> Path:
        return self.path / EVAL_DIR

    @property
    def draws(self) -> int | None:
        """Draws per problem (eval.json `samples`)."""
        value = self.info.get("samples")
        return int(value) if isinstance(value, int) else None

    @property
    def k(self) -> int | None:
        """The K of minADE_K / minFDE_K (eval.json `k`)."""
        value = self.info.get("k")
        return int(value) if isinstance(value, int) else None

    @property
    def label(self) -> str:
        """Short label for legends: fold and seed."""
        return f"fold {self.fold}, seed {self.seed}" if self.fold is not None else f"seed {self.seed}"


class PlannedRun(NamedTuple):
    """One run an experiment plans (experiment.json `plan`), finished or not."""

    experiment_dir: Path
    run: str             # its directory, relative to the experiment's
    model: str
    fold: str | None
    seed: int

    @property
    def path(self) -> Path:
        """The run's directory."""
        return self.experiment_dir / self.run


@dataclass(frozen=True)
class Inputs:
    """The resolved inputs: run directories in order (each with the experiment that listed it), notes, and the
    runs the experiments plan, finished or not."""

    runs: tuple[tuple[Path, str | None], ...]
    experiments: tuple[str, ...]
    notes: tuple[str, ...]
    planned: tuple[PlannedRun, ...] = ()


def _check_run_dir(path: Path) -> None:
    """Raise the right one-line error for a directory that is not a usable evaluated run."""
    if (path / EVAL_DIR / METRICS_FILE).is_file():
        return
    if looks_like_run(path):
        raise TrajflowError(f"{path}: no {EVAL_DIR}/{METRICS_FILE}; run `trajflow eval {path}` first")
    raise TrajflowError(f"{path}: neither an evaluated run (no {EVAL_DIR}/{METRICS_FILE}) nor an experiment "
                        f"(no {EXPERIMENT_FILE})")


def read_json(path: Path) -> dict[str, Any]:
    """A JSON object from `path`, or a DataError naming the file."""
    try:
        value = json.loads(input_files.read_text(path))
    except (OSError, json.JSONDecodeError) as error:
        raise DataError(f"not valid JSON ({error})", path) from None
    if not isinstance(value, dict):
        raise DataError("expected a JSON object", path)
    return value


def _plan(manifest: dict[str, Any], experiment_dir: Path, manifest_path: Path) -> list[PlannedRun]:
    """The runs an experiment plans, from its manifest's `plan` (empty for manifests written before it existed)."""
    plan = manifest.get("plan")
    if plan is None:
        return []
    if not isinstance(plan, list) or not all(
            isinstance(row, dict) and isinstance(row.get("run"), str) and isinstance(row.get("model"), str)
            and type(row.get("seed")) is int and (row.get("fold") is None or isinstance(row.get("fold"), str))
            for row in plan):
        raise DataError("`plan` must be a list of {run, model, fold, seed} objects (fold a string or null, seed an "
                        "integer)", manifest_path)
    return [PlannedRun(experiment_dir, row["run"], row["model"], row.get("fold"), row["seed"]) for row in plan]


def _unfinished(plan: list[PlannedRun], finished: list[str]) -> str:
    """` (not yet: FloMo, 5 runs; ...)`: the planned runs missing from `finished`, per model (empty without a
    plan)."""
    done = set(finished)
    missing = Counter(p.model for p in plan if p.run not in done)
    if not missing:
        return ""
    parts = [f"{model_label(m)}, {n} run{'s' if n > 1 else ''}" for m in model_order(list(missing))
             for n in [missing[m]]]
    return f" (not yet: {'; '.join(parts)})"


def _experiment_runs(path: Path) -> tuple[list[Path], str, str | None, list[PlannedRun]]:
    """The run directories an experiment lists, its name, a note on planned runs that are not finished, and its
    plan."""
    manifest_path = path / EXPERIMENT_FILE
    manifest = read_json(manifest_path)
    runs = manifest.get("runs")
    if not isinstance(runs, list) or not all(isinstance(r, str) for r in runs):
        raise DataError("`runs` must be a list of run paths relative to the experiment", manifest_path)
    name = str(manifest.get("name", path.name))
    plan = _plan(manifest, path, manifest_path)
    planned = [p.run for p in plan] or manifest.get("planned")
    note = None
    if isinstance(planned, list) and len(planned) > len(runs):
        note = (f"experiment {name}: {len(runs)} of {len(planned)} planned runs are finished; the report shows "
                f"the finished ones{_unfinished(plan, runs)}")
    if not runs:
        raise TrajflowError(f"{path}: the experiment lists no finished runs yet; run `trajflow experiment` first")
    return [path / r for r in runs], name, note, plan


def resolve_inputs(inputs: Iterable[str | Path]) -> Inputs:
    """Expand experiments into their runs, check every run has been evaluated, and drop duplicates."""
    runs: list[tuple[Path, str | None]] = []
    experiments: list[str] = []
    notes: list[str] = []
    planned: list[PlannedRun] = []
    seen: set[Path] = set()
    for raw in inputs:
        path = Path(raw)
        if not path.exists():
            raise TrajflowError(f"{path}: not found")
        if not path.is_dir():
            raise TrajflowError(f"{path}: not a directory (expected a run or an experiment directory)")
        if (path / EXPERIMENT_FILE).is_file():
            members, name, note, plan = _experiment_runs(path)
            experiments.append(name)
            notes.extend([note] if note else [])
            planned.extend(plan)
        else:
            members, name = [path], None
        for member in members:
            _check_run_dir(member)
            key = member.resolve()
            if key not in seen:
                seen.add(key)
                runs.append((member, name))
    if not runs:
        raise TrajflowError("no runs given: pass run or experiment directories")
    return Inputs(tuple(runs), tuple(experiments), tuple(notes), tuple(planned))


def load_run(path: Path, experiment: str | None = None) -> Run:
    """A :class:`Run` from its eval.json (model, dataset and seed are required; fold may be null)."""
    info_path = path / EVAL_DIR / EVAL_FILE
    info = read_json(info_path)
    missing = [key for key in ("model", "dataset", "seed") if key not in info]
    if missing:
        raise DataError(f"missing key(s) {', '.join(missing)}", info_path)
    try:
        seed = int(info["seed"])
    except (TypeError, ValueError):
        raise DataError(f"seed must be an integer, got {info['seed']!r}", info_path) from None
    fold = info.get("fold")
    return Run(path=path, name=str(info.get("run") or path.name), model=str(info["model"]),
               dataset=str(info["dataset"]), fold=None if fold is None else str(fold), seed=seed, info=info,
               experiment=experiment)


def _conform(frame: pl.LazyFrame, path: Path, columns: dict[str, str], optional: dict[str, str] | None = None,
             what: str = "table") -> pl.LazyFrame:
    """Check `frame`'s schema against `columns` (name -> kind) and cast to the canonical dtypes."""
    try:
        schema = frame.collect_schema()
    except (pl.exceptions.PolarsError, OSError) as error:
        raise DataError(f"unreadable {what} ({error})", path) from None
    missing = [name for name in columns if name not in schema]
    if missing:
        raise DataError(f"not a trajflow {what}: missing column(s) {', '.join(missing)}", path)
    wanted = {**columns, **{k: v for k, v in (optional or {}).items() if k in schema}}
    for name, kind in wanted.items():
        dtype = schema[name]
        ok = {"int": dtype.is_integer(), "float": dtype.is_numeric(), "str": dtype in (pl.String, pl.Categorical),
              "bool": dtype == pl.Boolean, }[kind]
        if not ok and dtype != pl.Null:
            raise DataError(f"column {name!r} has type {dtype}, expected {kind}", path)
    return frame.with_columns(*(pl.col(name).cast(_KINDS[kind]) for name, kind in wanted.items()))


def scan_table(path: Path, columns: dict[str, str], optional: dict[str, str] | None = None,
               what: str = "table") -> pl.LazyFrame:
    """A lazily scanned, schema-checked Parquet file (DataError naming the file when missing or corrupt)."""
    if not path.is_file():
        raise DataError(f"{what} not found; run `trajflow eval` again", path)
    try:
        frame = input_files.scan_parquet(path)
    except (pl.exceptions.PolarsError, OSError) as error:
        raise DataError(f"unreadable {what} ({error})", path) from None
    return _conform(frame, path, columns, optional, what)


def collect(frame: pl.LazyFrame, path: Path, what: str = "Parquet file") -> pl.DataFrame:
    """Collect a scan, turning read errors of a corrupt file into a DataError naming it."""
    try:
        return frame.collect()
    except (pl.exceptions.PolarsError, OSError) as error:
        raise DataError(f"unreadable {what} ({error})", path) from None


def run_metrics(run: Run) -> pl.DataFrame:
    """The run's aggregate rows (metric, value); identity columns come from eval.json, not the table."""
    path = run.eval_dir / METRICS_FILE
    table = collect(scan_table(path, METRICS_COLUMNS, what="metrics table")
                    .filter(pl.col("aggregate")).select("metric", "value"), path, "metrics table")
    duplicated = table.filter(pl.col("metric").is_duplicated()).get_column("metric").unique().sort().to_list()
    if duplicated:
        raise DataError(f"more than one aggregate row for metric(s) {', '.join(duplicated)}", path)
    return table


def report_rows() -> pl.Expr:
    """The rows of a run's metrics table that a report reads: the aggregates (the tables) and the per-agent
    (joint: per-group) rows of the unbounded metrics (their medians). A copy of the table that keeps only these
    reports the same; the other per-agent rows are for people and scripts."""
    return pl.col("aggregate") | pl.col("metric").str.starts_with(UNBOUNDED_PREFIX)


def has_draws(run: Run) -> bool:
    """Whether the run still has its draws (eval/predictions.parquet), which the example, density and minADE(K)
    figures read; an evaluated copy may have left them behind (with the ground truth they are drawn over). Draws
    without their ground truth stay an error, where a figure reads them."""
    return (run.eval_dir / PREDICTIONS_FILE).exists()


def run_medians(run: Run) -> pl.DataFrame:
    """The median of the run's per-agent (joint: per-group) rows of each unbounded metric (NLL and its variants
    that have such rows; `*_ext_long` has only its aggregate), as (metric, value): the typical problem, which a few
    far-off ground truths cannot move as they move the mean. NaN where any row is NaN (as the mean would be),
    rather than a median of the other rows."""
    path = run.eval_dir / METRICS_FILE
    value = pl.col("value")
    scan = (scan_table(path, METRICS_COLUMNS, what="metrics table")
            .filter(~pl.col("aggregate") & pl.col("metric").str.starts_with(UNBOUNDED_PREFIX))
            .group_by("metric")
            .agg(pl.when(value.is_nan().any()).then(pl.lit(float("nan"))).otherwise(value.median()).alias("value"))
            .sort("metric"))
    return collect(scan, path, "metrics table")


def metrics_frame(runs: list[Run], read: Callable[[Run], pl.DataFrame] = run_metrics) -> pl.DataFrame:
    """One row per (run, metric) value with the run's identity: the input of every table. `read` gives a run's
    (metric, value) rows: its aggregates (default) or e.g. :func:`run_medians`."""
    schema = {"run_index": pl.Int64, "run": pl.String, "model": pl.String, "dataset": pl.String,
              "fold": pl.String, "seed": pl.Int64, "metric": pl.String, "value": pl.Float64}
    frames = [read(run).with_columns(
        run_index=pl.lit(index, pl.Int64), run=pl.lit(run.name), model=pl.lit(run.model),
        dataset=pl.lit(run.dataset), fold=pl.lit(run.fold, pl.String), seed=pl.lit(run.seed, pl.Int64),
    ).select(list(schema)) for index, run in enumerate(runs)]
    return pl.concat(frames) if frames else pl.DataFrame(schema=schema)


def scan_predictions(run: Run) -> pl.LazyFrame:
    """The run's draws, lazily (they can be large: filter before collecting)."""
    return scan_table(run.eval_dir / PREDICTIONS_FILE, PREDICTION_COLUMNS, what="predictions table")


def scan_ground_truth(run: Run) -> pl.LazyFrame:
    """The run's observed pasts and ground-truth futures, lazily."""
    return scan_table(run.eval_dir / GROUND_TRUTH_FILE, GROUND_TRUTH_COLUMNS, what="ground-truth table")


def _scan_train_log(run: Run) -> tuple[pl.LazyFrame, Path] | None:
    """The run's training log, checked against the log columns, and its path (None when the run has none)."""
    for name in LOG_FILES:
        path = run.path / name
        if not path.is_file():
            continue
        try:
            frame = (input_files.scan_csv(path, schema_overrides=_CSV_LOG_TYPES) if path.suffix == ".csv"
                     else input_files.scan_parquet(path))
        except (pl.exceptions.PolarsError, OSError) as error:
            raise DataError(f"unreadable training log ({error})", path) from None
        return _conform(frame, path, TRAIN_LOG_COLUMNS, TRAIN_LOG_OPTIONAL, what="training log"), path
    return None


def load_train_log(run: Run) -> pl.DataFrame | None:
    """The run's training log (epoch, stage, train_loss, val_loss), or None when the run has none (e.g. cv)."""
    scanned = _scan_train_log(run)
    if scanned is None:
        return None
    frame, path = scanned
    if "val_loss" not in frame.collect_schema():
        frame = frame.with_columns(val_loss=pl.lit(None, pl.Float64))
    return collect(frame.select("epoch", "stage", "train_loss", "val_loss"), path, "training log")


def training_seconds(run: Run) -> float | None:
    """The sum of the epoch times in the run's training log (None: no log, or a log without times)."""
    scanned = _scan_train_log(run)
    if scanned is None or "seconds" not in scanned[0].collect_schema():
        return None
    frame, path = scanned
    return float(collect(frame.select(pl.col("seconds").sum()), path, "training log").item())
