"""`trajflow eval RUN`: parse the evaluation options, call :func:`trajflow_pipeline.stages.evaluate.evaluate`, print
the means (cli/render.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..util.progress import say, stdout
from .common import Quiet, user_errors
from .render import print_metric_means


def eval_command(
    ctx: typer.Context,
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
    ray: Annotated[Optional[str], typer.Option(
        "--ray", metavar="ADDRESS", help=(
            "Spread the ROME fits over a Ray cluster: auto (the one `ray start` runs here), HOST:PORT or "
            "ray://HOST:PORT, or local (a Ray instance on this machine); needs the ray extra. Same numbers; "
            "--workers is then not used."))] = None,
    force: Annotated[bool, typer.Option(help="Evaluate even on data other than the run was trained on.")] = False,
    quiet: Quiet = False,
) -> None:
    """Draw samples for the test problems of the run's fold and compute minADE/minFDE, NLL and JSD (and, with
    --extended-horizon, the same over each sample's own longer ground-truth horizon as *_ext)."""
    from ..metrics import METRIC_NAMES
    from ..stages.evaluate import EvalOptions, aggregate_metrics, evaluate

    with user_errors(ctx):
        options = EvalOptions(samples=samples, k=min(20, samples) if k is None else k, workers=workers, seed=seed,
                              steps=steps, max_pooled=max_pooled, metrics=tuple(metric) if metric else METRIC_NAMES,
                              extended_horizon=extended_horizon, rome_kde=rome_kde)
        out = evaluate(run, data=data, options=options, device=device, force=force, quiet=quiet, ray=ray)
    if not quiet:
        print_metric_means(f"{run}: test metrics (mean)", aggregate_metrics(out))
        say(f"wrote {out}", out=stdout)
