"""`trajflow train DATA -o RUN`: parse the options and call :func:`trajflow_pipeline.training.train`.

Registered by the application as ``app.command("train")(train_command)``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..model.config import MODEL_NAMES
from .common import Quiet, user_errors


def train_command(
    ctx: typer.Context,
    data: Annotated[Path, typer.Argument(metavar="DATA", help="Dataset directory written by `trajflow ingest`.")],
    out: Annotated[Path, typer.Option("--out", "-o", metavar="RUN",
                                      help="Run directory: config, checkpoints, training log, final model.")],
    fold: Annotated[Optional[str], typer.Option(help="Test fold of a cross-validation protocol (e.g. hotel, 0); "
                                                     "its training folds are used.")] = None,
    model: Annotated[Optional[str], typer.Option(help=f"Model family: {', '.join(MODEL_NAMES)} "
                                                      "(default: the config's, else trajflow).")] = None,
    config: Annotated[Optional[Path], typer.Option("--config", metavar="CFG.toml",
                                                   help="TOML file with \\[model] and \\[train] tables.")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", metavar="KEY=VALUE",
                                                      help="Override one config value, e.g. "
                                                           "train.flow_lr=3e-4 (repeatable).")] = None,
    seed: Annotated[Optional[int], typer.Option(help="Random seed (train.seed).")] = None,
    device: Annotated[Optional[str], typer.Option(help="auto, cpu, cuda or cuda:N (train.device).")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue an interrupted run from its last "
                                                          "checkpoint (on its own fold). With --set "
                                                          "train.flow_max_epochs=N, train.flow_patience=N (or "
                                                          "the ae_ ones) above the run's, a stage the larger "
                                                          "budget would not have stopped continues from its last "
                                                          "epoch (finished runs too); with --set "
                                                          "model.flow_temperature_grid=[...], a finished run fits "
                                                          "its temperature stage again on its final flow.")]
    = False,
    autoencoder_from: Annotated[Optional[Path], typer.Option(
        "--autoencoder-from", metavar="RUN",
        help="Start from the trained autoencoder of RUN (same model, data, fold and settings; only train.flow_* "
             "may differ) and train the flow only: e.g. a flow learning-rate sweep without retraining the "
             "autoencoder. Gives the run the same config would give from scratch.")] = None,
    quiet: Quiet = False,
) -> None:
    """Train a model: autoencoder pre-training, then the conditional flow (early stopping on the val split)."""
    from ..training import train

    with user_errors(ctx):
        train(data, out, fold=fold, model=model, config_path=config, overrides=tuple(set_ or ()), seed=seed,
              device=device, resume=resume, quiet=quiet, autoencoder_from=autoencoder_from)
