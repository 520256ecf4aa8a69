"""The `trajflow` command line: parses arguments and calls one stage per command."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from .. import __version__
from ..util.progress import say, stdout
from .common import Overwrite, Quiet, set_debug, user_errors
from .forking_cmd import augment_forking_command, augment_scale_rotate_command, ingest_forking_paths_command
from .nuscenes_cmd import ingest_nuscenes_command
from .report_cmd import report_command
from .round_cmd import ingest_round_command
from .status_cmd import status_command
from .train_cmd import train_command

app = typer.Typer(
    name="trajflow",
    help="TrajFlow pipeline: raw trajectory datasets -> unified Parquet scenes -> models -> metrics and reports.",
    no_args_is_help=True,
    rich_markup_mode="rich",
    pretty_exceptions_show_locals=False,
)
ingest_app = typer.Typer(help="Turn raw datasets into the unified Parquet scene dataset.", no_args_is_help=True)
app.add_typer(ingest_app, name="ingest")
augment_app = typer.Typer(help="Scaling / rotation augmentation into a new dataset.", no_args_is_help=True)
app.add_typer(augment_app, name="augment")


OutDir = Annotated[Path, typer.Option("--out", "-o", help="Dataset directory to write (created atomically).")]


def _version(value: bool) -> None:
    if value:
        stdout.print(f"trajflow {__version__}")
        raise typer.Exit()


#: commands that run models, whose torch thread count matters
MODEL_COMMANDS = frozenset({"train", "eval", "experiment", "demo"})
#: set by the console script: choose torch's thread count from the idle CPUs (off where the app is embedded)
AUTO_THREADS = {"enabled": False}


def _set_threads(command: str | None, threads: int | None) -> None:
    """--threads N as given; otherwise, for model commands run from the console script, as many threads as the
    machine has idle CPUs, so that a second trajflow beside a busy one does not slow both down many times over."""
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    elif AUTO_THREADS["enabled"] and command in MODEL_COMMANDS:
        from ..model.runtime import fit_threads_to_idle_cpus

        lowered = fit_threads_to_idle_cpus()
        if lowered is not None:
            say(("note:", "yellow"), f" other processes keep CPUs busy: {lowered[1]} torch thread(s) instead of "
                f"{lowered[0]} (set them with trajflow --threads N)")


@app.callback()
def _root(
    ctx: typer.Context,
    debug: Annotated[bool, typer.Option("--debug", help="Show full tracebacks for errors.")] = False,
    threads: Annotated[Optional[int], typer.Option(
        "--threads", min=1, help="torch CPU threads for model commands (default: one per CPU that other processes "
                                 "leave idle; OMP_NUM_THREADS is respected).")] = None,
    version: Annotated[Optional[bool], typer.Option("--version", callback=_version, is_eager=True,
                                                    help="Print the version and exit.")] = None,
) -> None:
    """TrajFlow: from raw trajectory datasets to trained normalizing-flow predictors and paper-grade metrics."""
    set_debug(debug)
    _set_threads(ctx.invoked_subcommand, threads)


@ingest_app.command("eth-ucy")
def ingest_eth_ucy_command(
    raw: Annotated[Path, typer.Argument(help="The Trajectron++ layout (<location>/{train,val,test}/*.txt) or a "
                                             "folder of the eight full sequences (e.g. all_data/).")],
    out: OutDir,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """ETH/UCY pedestrians: leave-one-location-out folds, 8 past + 12 future steps at 0.4 s."""
    from ..ingest.registry import get_ingest

    with user_errors():
        adapter = get_ingest("eth-ucy")
        adapter.report(adapter.run(raw, out, overwrite=overwrite, quiet=quiet), quiet)


@ingest_app.command("synthetic-bimodal")
def ingest_synthetic_command(
    out: OutDir,
    samples: Annotated[int, typer.Option(help="Number of futures (half per mode).")] = 3000,
    seed: Annotated[int, typer.Option(help="Random seed; the same seed gives byte-identical files.")] = 0,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """The paper's synthetic bimodal set: one past of 10 steps, two future modes of 14 steps at 0.25 s."""
    from ..ingest.registry import get_ingest

    with user_errors():
        adapter = get_ingest("synthetic-bimodal")
        adapter.report(adapter.run(None, out, samples=samples, seed=seed, overwrite=overwrite, quiet=quiet), quiet)


@ingest_app.command("csv")
def ingest_csv_command(
    file: Annotated[Path, typer.Argument(help="CSV (with a header) or Parquet file, one row per agent and time.")],
    out: OutDir,
    dt: Annotated[float, typer.Option(help="Seconds between frames.")],
    columns: Annotated[Optional[str], typer.Option(
        help="Column mapping role=name,... with roles scene, agent, frame or time, x, y, type "
             "(defaults: scene_id, agent_id, frame, x, y; no type column means pedestrians).")] = None,
    past: Annotated[int, typer.Option(help="Observed steps per sample (including t0).")] = 8,
    future: Annotated[int, typer.Option(help="Predicted steps per sample.")] = 12,
    name: Annotated[Optional[str], typer.Option(help="Dataset name (default: the file's stem).")] = None,
    protocol: Annotated[Optional[str], typer.Option(
        help="folds (cross-validation: train --fold F tests on fold F), fixed (train / val / test from --split-col "
             "or a --test-fraction holdout) or train-is-test (every sample tests; a --val-fraction validates; "
             "for multi-future data). Default: fixed with --split-col, else folds.")] = None,
    split_by: Annotated[str, typer.Option(
        help="What folds, holdouts and validation sets are made of: time (cuts of each scene's timeline; windows "
             "across a cut are dropped), scene (whole scenes, seeded), group (whole groups of identical inputs, "
             "seeded) or auto (time unless its cuts drop more than half of the windows, then scene).")] = "auto",
    folds: Annotated[int, typer.Option(help="Folds of --protocol folds.")] = 5,
    val_fraction: Annotated[float, typer.Option(
        help="Part validating: the end of each time block or timeline, or a seeded share of the units.")] = 0.2,
    test_fraction: Annotated[Optional[float], typer.Option(
        help="--protocol fixed without --split-col: the part held out for test (timelines' ends or units).")] = None,
    split_col: Annotated[Optional[str], typer.Option(
        help="Column holding train/val/test per row, read at each sample's t0 row (--protocol fixed).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the scene / group assignment.")] = 0,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """Bring-your-own trajectories from a CSV or Parquet table."""
    from ..ingest.csv import ColumnMap
    from ..ingest.registry import get_ingest

    with user_errors():
        adapter = get_ingest("csv")
        result = adapter.run(file, out, dt=dt, columns=ColumnMap.parse(columns), n_past=past, n_future=future,
                             dataset=name, split_col=split_col, folds=folds, val_fraction=val_fraction,
                             protocol=protocol, split_by=split_by, test_fraction=test_fraction, seed=seed,
                             overwrite=overwrite, quiet=quiet)
        adapter.report(result, quiet)


@app.command("inspect")
def inspect_command(
    data: Annotated[Path, typer.Argument(help="A dataset directory written by `trajflow ingest`.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary as JSON on stdout.")] = False,
    check_tracks: Annotated[bool, typer.Option(
        "--check-tracks/--no-check-tracks",
        help="Read every tracks shard to validate its rows (NaN/inf, duplicated or unsorted keys, unknown scenes, "
             "incomplete sample windows); --no-check-tracks skips this full read for huge datasets.")] = True,
) -> None:
    """Summarise a dataset: scenes, agents, rows, samples per fold and split, dt, agent types; validate its rows."""
    from ..stages.inspect import summarize

    with user_errors():
        summary = summarize(data, check_tracks_contents=check_tracks)
    if as_json:
        typer.echo(json.dumps(summary, indent=2, default=str))
        return
    _print_summary(summary)


def _print_summary(summary: dict) -> None:
    overview = Table(title=f"{summary['dataset']}  ({summary['path']})", show_header=False)
    for key in ("schema_version", "written_by", "protocol", "dt", "scenes", "agents", "track_rows",
                "track_shards", "samples", "groups", "has_map", "tracks_checked"):
        overview.add_row(key, str(summary[key]))
    overview.add_row("horizons (past/future)",
                     ", ".join(f"{h['n_past']}/{h['n_future']} ({h['len']})" for h in summary["horizons"]))
    stdout.print(overview)
    splits = Table(title="samples by fold and split")
    for column in ("fold", "split", "samples", "groups"):
        splits.add_column(column, justify="right" if column in ("samples", "groups") else "left")
    for row in summary["samples_by_fold_and_split"]:
        splits.add_row(str(row["fold"] or "-"), str(row["split"] or "-"), str(row["samples"]), str(row["groups"]))
    stdout.print(splits)
    types = Table(title="agent types")
    for column in ("agent_type", "agents", "rows"):
        types.add_column(column)
    for row in summary["agent_types"]:
        types.add_row(row["agent_type"], str(row["agents"]), str(row["rows"]))
    stdout.print(types)


@app.command("eval")
def eval_command(
    run: Annotated[Path, typer.Argument(help="A run directory written by `trajflow train`.")],
    data: Annotated[Optional[Path], typer.Option(help="Dataset to evaluate on (default: the run's).")] = None,
    samples: Annotated[int, typer.Option(help="Futures drawn per test problem.")] = 100,
    k: Annotated[Optional[int], typer.Option(
        help="Draws used by minADE_K / minFDE_K (default: 20, or --samples when fewer).")] = None,
    workers: Annotated[Optional[int], typer.Option(help="Processes for the ROME fits (default: all cores).")] = None,
    metric: Annotated[Optional[list[str]], typer.Option(
        "--metric", help="Metric to compute (repeatable; default: all of min_ade, min_fde, min_ade_joint, "
                         "min_fde_joint, nll, nll_joint, jsd).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the sampling and the ROME fits.")] = 0,
    steps: Annotated[Optional[int], typer.Option(
        help="Predicted steps (default: the dataset's n_future; with --extended-horizon the longest n_future_max). "
             "Fewer than n_future scores only those steps: warned and recorded in eval.json.")] = None,
    extended_horizon: Annotated[bool, typer.Option(
        "--extended-horizon",
        help="Also score each sample over its own ground-truth horizon (samples column n_future_max; rounD: up "
             "to 35 steps) as *_ext metrics, as the paper does for rounD. Models without an auto-regressive "
             "decoder are extended at constant velocity past their trained horizon (recorded in eval.json).")
    ] = False,
    max_pooled: Annotated[Optional[int], typer.Option(
        help="Cap on pooled predictions per identical-input group for ROME (default: all).")] = None,
    rome_kde: Annotated[str, typer.Option(
        help="How ROME's densities are computed: exact, or reference (romepy's arithmetic through scikit-learn, "
             "to the bit, rounding residue included: docs/rome.md; needs the reference extra).")] = "exact",
    device: Annotated[str, typer.Option(help="auto, cpu, cuda or cuda:N.")] = "auto",
    force: Annotated[bool, typer.Option(help="Evaluate even on data other than the run was trained on.")] = False,
    quiet: Quiet = False,
) -> None:
    """Draw samples for the test problems of the run's fold and compute minADE/minFDE, NLL and JSD (and, with
    --extended-horizon, the same over each sample's own longer ground-truth horizon as *_ext)."""
    from ..metrics import METRIC_NAMES
    from ..stages.evaluate import EvalOptions, aggregate_metrics, evaluate

    with user_errors():
        options = EvalOptions(samples=samples, k=min(20, samples) if k is None else k, workers=workers, seed=seed,
                              steps=steps, max_pooled=max_pooled, metrics=tuple(metric) if metric else METRIC_NAMES,
                              extended_horizon=extended_horizon, rome_kde=rome_kde)
        out = evaluate(run, data=data, options=options, device=device, force=force, quiet=quiet)
    if not quiet:
        table = Table(title=f"{run}: test metrics (mean)")
        table.add_column("metric")
        table.add_column("value", justify="right")
        for name, value in aggregate_metrics(out).items():
            table.add_row(name, f"{value:.4f}")
        stdout.print(table)
        stdout.print(f"wrote {out}")


@app.command("experiment")
def experiment_command(
    config: Annotated[Path, typer.Argument(help="Experiment config (TOML): data, models, folds, seeds, budgets.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Experiment directory (re-running resumes it).")],
    device: Annotated[str, typer.Option(help="auto, cpu, cuda or cuda:N.")] = "auto",
    jobs: Annotated[int, typer.Option("--jobs", "-j", min=1, help=(
        "Runs trained at once, in worker processes that share out the CPU threads. The same command may also be "
        "started again elsewhere: each run is claimed by one process."))] = 1,
    only: Annotated[Optional[list[str]], typer.Option(
        "--only", metavar="PATTERN", help=(
            "Work only on the runs whose names (MODEL-FOLD-sSEED) match; shell patterns, repeatable, e.g. "
            "--only flomo-zara2-s0 or --only 'trajflow-*'. To have one run done now beside a process that works "
            "through the plan, or to split an experiment between machines."))] = None,
    quiet: Quiet = False,
) -> None:
    """Train and evaluate every model x fold x seed of a protocol; resumable, metrics collected in OUT."""
    from ..stages.experiment import run_experiment

    with user_errors():
        result = run_experiment(config, out, device=device, quiet=quiet, jobs=jobs, only=only or ())
    index = json.loads((result / "experiment.json").read_text())
    if not quiet and index["runs"] == index["planned"]:
        stdout.print(f"experiment done: {result} (make a report with `trajflow report {result} -o REPORT`)")


@app.command("demo")
def demo_command(
    out: Annotated[Path, typer.Option("--out", "-o", help="Where data, runs and the report go.")] = Path(
        "trajflow-demo"),
    device: Annotated[str, typer.Option(help="auto, cpu, cuda or cuda:N.")] = "auto",
    quiet: Quiet = False,
) -> None:
    """The whole pipeline on built-in data: synthetic bimodal -> TrajFlow + baselines -> metrics -> report."""
    from ..stages.demo import demo

    with user_errors():
        report_dir = demo(out, device=device, quiet=quiet)
    stdout.print(f"report: {report_dir / 'report.html'} (and report.md)")


app.command("train")(train_command)
app.command("report")(report_command)
app.command("status")(status_command)
ingest_app.command("forking-paths")(ingest_forking_paths_command)
ingest_app.command("round")(ingest_round_command)
ingest_app.command("nuscenes")(ingest_nuscenes_command)
augment_app.command("forking")(augment_forking_command)
augment_app.command("scale-rotate")(augment_scale_rotate_command)


def main() -> None:
    """Entry point of the `trajflow` console script."""
    AUTO_THREADS["enabled"] = True
    app()
