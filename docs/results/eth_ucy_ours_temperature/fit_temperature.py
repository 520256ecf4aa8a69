"""The stage "temperature" (model.flow_temperature_grid) run on finished runs: a copy of each run as if it had
trained with the grid, for `trajflow eval` (the figures of README.md).

    trajflow ingest eth-ucy ../shared/data/eth_ucy -o data/eth_ucy
    python docs/results/eth_ucy_ours_temperature/fit_temperature.py data/eth_ucy docs/results/eth_ucy_ours/models probe/
    for run in probe/*/; do trajflow eval "$run" --data data/eth_ucy; done

The stage comes after the flow and changes nothing the flow learnt, so it can run after the fact: for each run
(a finished run with final/, e.g. a published models/RUN), the training loop's own pieces
(`validation_subset`, `sample_nll`) score the grid on the same fixed validation problems of the run's fold (the
training locations' held-back problems; never the test location) with the run's seed, and the copy under OUT/RUN
gets what a run trained with the grid writes: its config with the grid, final/ with the fitted temperature, the
stage's row in train_log.parquet and its record (the whole curve) in run.json's "best".
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import math
import shutil
import time
from pathlib import Path

import polars as pl
import torch

from trajflow_pipeline.model import load_model, save_model
from trajflow_pipeline.model.checkpoint import model_digest
from trajflow_pipeline.model.models import FlowModel, build_model
from trajflow_pipeline.rundir import CONFIG_FILE, FINAL_DIR, LOG_FILE, MODEL_INFO_FILE, RUN_FILE, read_run_config
from trajflow_pipeline.training.data import load_data
from trajflow_pipeline.training.loop import sample_nll, validation_subset
from trajflow_pipeline.training.state import LOG_SCHEMA

GRID = (1.0, 1.1, 1.2, 1.3, 1.5)


def with_fitted_temperature(run: Path, data: Path, out: Path, grid: tuple[float, ...], problems: int) -> dict:
    """Write `out`: `run` as if trained with model.flow_temperature_grid = `grid` (and `problems`); return the
    stage's record (run.json's best["temperature"])."""
    config = read_run_config(run)
    config = dataclasses.replace(config, model=dataclasses.replace(
        config.model, flow_temperature_grid=tuple(grid), flow_temperature_problems=problems)).validate()
    trained = load_model(run / FINAL_DIR)
    model = build_model(config.model, trained.spec, seed=config.train.seed)
    missing, unexpected = model.load_state_dict(trained.state_dict(), strict=False)
    if set(missing) != {"fitted_temperature"} or unexpected:
        raise SystemExit(f"{run}: its weights do not fit the model with the grid ({missing}, {unexpected})")
    info = json.loads((run / RUN_FILE).read_text())
    training = load_data(data, info.get("fold"), config)
    start = time.perf_counter()
    subset = validation_subset(len(training.val), problems, config.train.seed)
    curve = {}
    for temperature in grid:
        model.set_sampling_temperature(temperature)
        curve[temperature] = sample_nll(model, training.val, training.val_groups, subset, config.train)
    chosen = min((t for t in grid if math.isfinite(curve[t])), key=curve.__getitem__)
    model.set_sampling_temperature(chosen)
    seconds = time.perf_counter() - start
    record = {"epoch": 1, "temperature": chosen, "val_nll": curve[chosen], "problems": len(subset),
              "val_nll_by_temperature": {f"{t:g}": curve[t] for t in grid}}

    shutil.rmtree(out, ignore_errors=True)
    (out / FINAL_DIR).mkdir(parents=True)
    (out / CONFIG_FILE).write_text(config.to_toml())
    save_model(model, out / FINAL_DIR, extra={"dataset": trained.spec.dataset, "fold": info.get("fold"),
                                              "seed": config.train.seed, "fingerprint": info.get("fingerprint")})
    model_info = json.loads((run / FINAL_DIR / MODEL_INFO_FILE).read_text())
    model_info["config"] = config.to_dict()
    (out / FINAL_DIR / MODEL_INFO_FILE).write_text(json.dumps(model_info, indent=2) + "\n")
    log = pl.read_parquet(run / LOG_FILE)
    row = pl.DataFrame([{"epoch": 1, "stage": FlowModel.TEMPERATURE, "train_loss": math.nan,
                         "val_loss": curve[chosen], "lr": 0.0, "seconds": seconds, "skipped_steps": 0,
                         "samples_per_s": len(subset) * len(grid) / seconds, "val_nll": curve[chosen]}],
                       schema=LOG_SCHEMA)
    pl.concat([log.select(list(LOG_SCHEMA)).cast(LOG_SCHEMA), row]).write_parquet(out / LOG_FILE)
    # what tells this final model from the run's own (rundir.is_evaluated compares an evaluation with it)
    info.update(rank_weight_digests=[model_digest(model)], ranks_consistent=True,
                finished=dt.datetime.now(dt.timezone.utc).isoformat())
    info["best"] = {**info["best"], FlowModel.TEMPERATURE: record}
    info["temperature_fitted_after_training"] = {"from_run": str(run), "seconds": seconds,
                                                 "threads": torch.get_num_threads()}
    (out / RUN_FILE).write_text(json.dumps(info, indent=1) + "\n")
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", type=Path, help="the ETH/UCY dataset directory (trajflow ingest eth-ucy)")
    parser.add_argument("models", type=Path, help="a folder of finished runs, e.g. docs/results/eth_ucy_ours/models")
    parser.add_argument("out", type=Path, help="where the copies go (OUT/RUN, replaced)")
    parser.add_argument("--only", nargs="+", default=None, help="run names (default: every run in MODELS)")
    parser.add_argument("--grid", type=float, nargs="+", default=list(GRID))
    parser.add_argument("--problems", type=int, default=2000, help="validation problems per run (default 2000)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    for run in sorted(p for p in args.models.iterdir() if (p / FINAL_DIR).is_dir()):
        if args.only and run.name not in args.only:
            continue
        record = with_fitted_temperature(run, args.data, args.out / run.name, tuple(args.grid), args.problems)
        print(f"{run.name}: T = {record['temperature']:g}; validation NLL "
              + ", ".join(f"{t}: {v:.2f}" for t, v in record["val_nll_by_temperature"].items()), flush=True)


if __name__ == "__main__":
    main()
