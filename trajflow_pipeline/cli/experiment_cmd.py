"""`trajflow experiment CONFIG -o EXP` and `trajflow demo`: parse the options and run the experiment stage."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..util.progress import say, stdout
from .common import Quiet, user_errors


def experiment_command(
    ctx: typer.Context,
    config: Annotated[Path, typer.Argument(help="Experiment config (TOML): data, models, folds, seeds, budgets.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Experiment directory (re-running resumes it).")],
    device: Annotated[str, typer.Option(help="auto, cpu, cuda or cuda:N.")] = "auto",
    jobs: Annotated[int, typer.Option("--jobs", "-j", min=1, help=(
        "Runs trained at once, in worker processes that share out the CPU threads. The same command may also be "
        "started again elsewhere: each run is claimed by one process."))] = 1,
    only: Annotated[Optional[list[str]], typer.Option(
        "--only", metavar="PATTERN", help=(
            "Work only on the runs whose names (MODEL-FOLD-sSEED) match; shell patterns, repeatable, e.g. "
            "--only flomo-zara2-s0 or --only '*-eth-*' ('trajflow-*' also matches trajflow-no-ae's runs). To have "
            "one run done now beside a process that works "
            "through the plan, or to split an experiment between machines."))] = None,
    ray: Annotated[Optional[str], typer.Option(
        "--ray", metavar="ADDRESS", help=(
            "Run each run as a task on a Ray cluster: auto (the one `ray start` runs here), HOST:PORT or "
            "ray://HOST:PORT, or local (a Ray instance on this machine); needs the ray extra, and OUT on a file "
            "system every node shares. Instead of --jobs."))] = None,
    cpus_per_run: Annotated[int, typer.Option(
        "--cpus-per-run", min=1, help="With --ray: CPUs each run asks for (its torch threads and ROME workers).")
    ] = 1,
    set_: Annotated[Optional[list[str]], typer.Option(
        "--set", metavar="KEY=VALUE", help=(
            "Override a value of the config file, repeatable: a dotted key into its tables and a TOML value, e.g. "
            "--set data.raw=/data/eth_ucy (so nobody edits a committed config to point at their data), "
            "--set augment.0.copies=50 (the first augmentation step)."))] = None,
    no_report: Annotated[bool, typer.Option(
        "--no-report", help="Do not write the report (OUT/report) at the end.")] = False,
    autoencoder_from: Annotated[Optional[Path], typer.Option(
        "--autoencoder-from", metavar="DIR", help=(
            "Another experiment directory, or a folder docs/results/publish.py wrote: each new TrajFlow run whose "
            "twin (DIR/runs/RUN or DIR/models/RUN) is finished takes its autoencoder and trains only the flow; the "
            "configs may differ only in flow and context-encoder settings (paired ablations)."))] = None,
    quiet: Quiet = False,
) -> None:
    """Build the data stages that changed, train and evaluate every model x fold x seed, write the report; resumable."""
    from ..stages.experiment import REPORT_DIR, experiment_complete, run_experiment

    with user_errors(ctx):
        result = run_experiment(config, out, device=device, quiet=quiet, jobs=jobs, only=only or (), ray=ray,
                                cpus_per_run=cpus_per_run, overrides=set_ or (), report=not no_report,
                                autoencoder_from=autoencoder_from)
        done = experiment_complete(result)
    if not quiet and done:
        where = (f"report: {result / REPORT_DIR / 'report.html'}" if not no_report
                 else f"make a report with `trajflow report {result} -o REPORT`")
        say(f"experiment done: {result} ({where})", out=stdout)


def demo_command(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option("--out", "-o", help="Where data, runs and the report go.")] = Path(
        "trajflow-demo"),
    device: Annotated[str, typer.Option(help="auto, cpu, cuda or cuda:N.")] = "auto",
    quiet: Quiet = False,
) -> None:
    """The whole pipeline on built-in data: synthetic bimodal -> TrajFlow + baselines -> metrics -> report."""
    from ..stages.demo import demo

    with user_errors(ctx):
        report_dir = demo(out, device=device, quiet=quiet)
    say(f"report: {report_dir / 'report.html'} (and report.md)", out=stdout)
