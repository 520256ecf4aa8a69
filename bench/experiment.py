"""An experiment run locally with `-j 2` and on Ray (`--ray local`, 2 CPUs) in one process: Ray's overhead per run.

    python bench/experiment.py                       # configs/paper/synthetic_bimodal_quick.toml
    python bench/experiment.py --tiny                # 80 synthetic samples, 2-epoch budgets (seconds per run)

Each experiment goes into a fresh temporary directory (the dataset is ingested once, before timing). Printed: the
wall time of each backend, Ray's start-up (`ray.init`), the mean wall time of one run (from the local pass:
2 x its wall time / runs, as 2 runs go at once), and Ray's overhead per run ((Ray wall - local wall) / runs x 2),
also as a share of a run. Both passes must end with the same metrics (checked).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import polars as pl
from polars.testing import assert_frame_equal

from trajflow_pipeline.stages.experiment import run_experiment
from trajflow_pipeline.stages.experiment_config import load_experiment

QUICK = Path(__file__).resolve().parents[1] / "configs" / "paper" / "synthetic_bimodal_quick.toml"
TINY = '''name = "tiny"
[data]
path = "{data}"
ingest = "synthetic-bimodal"
samples = 80
[protocol]
models = ["cv", "trajflow-no-ae"]
seeds = [0, 1]
[train]
set = ["train.flow_max_epochs=2", "train.flow_min_epochs=1", "model.flow_layers=2", "model.flow_hidden=[16, 16]"]
[eval]
samples = 10
k = 5
workers = 1
'''


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true", help="a tiny synthetic experiment instead of the quick one")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        config = root / "exp.toml"
        if args.tiny:
            config.write_text(TINY.format(data=(root / "data").as_posix()))
        else:
            text = QUICK.read_text().replace('path = "data/synthetic_bimodal"',
                                             f'path = "{(root / "data").as_posix()}"')
            config.write_text(text)
        runs = len(load_experiment(config).models) * len(load_experiment(config).seeds)
        run_experiment(config, root / "warm", quiet=True, only=["cv-*"])  # ingests the data, outside the timing
        started = time.perf_counter()
        local = run_experiment(config, root / "local", quiet=True, jobs=2)
        local_s = time.perf_counter() - started
        import ray

        started = time.perf_counter()
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        startup_s = time.perf_counter() - started
        started = time.perf_counter()
        on_ray = run_experiment(config, root / "ray", quiet=True, ray="auto")
        ray_s = time.perf_counter() - started
        ray.shutdown()
        assert_frame_equal(pl.read_parquet(on_ray / "metrics.parquet"), pl.read_parquet(local / "metrics.parquet"))
    per_run = 2 * local_s / runs
    overhead = 2 * (ray_s - local_s) / runs
    print(f"{runs} runs, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}; same metrics on both backends")
    print(f"local -j 2: {local_s:.1f} s; Ray: {ray_s:.1f} s, plus {startup_s:.1f} s for ray.init")
    print(f"a run: {per_run:.1f} s; Ray's overhead per run: {overhead:.2f} s ({100 * overhead / per_run:.1f} %), "
          f"{2 * (ray_s + startup_s - local_s) / runs:.2f} s with start-up "
          f"({100 * (ray_s + startup_s - local_s) / (local_s):.1f} %)")


if __name__ == "__main__":
    main()
