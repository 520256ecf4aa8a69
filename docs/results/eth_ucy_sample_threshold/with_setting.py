"""A diagnostic copy of a trained run with one prediction-time model setting changed (issue 28).

    python docs/results/eth_ucy_sample_threshold/with_setting.py SRC_RUN DEST_RUN KEY VALUE

Copies SRC_RUN's final model, run.json, config.toml and training log to DEST_RUN and writes KEY = VALUE into the
model config stored with the weights (the metadata `trajflow eval` builds the model from); no weight changes.
Then `trajflow eval DEST_RUN --force` evaluates the same weights under the new setting (--force: the weights
file's digest no longer matches run.json's). Meant for settings that only drawing reads, such as
model.speed_normalize_sample_threshold; the copy is a diagnostic, not a run of a config.
"""

from __future__ import annotations

import json
import shutil
import sys
from dataclasses import fields
from pathlib import Path

from safetensors import safe_open
from safetensors.torch import load_file, save_file

from trajflow_pipeline.model.config import ModelConfig


def copy_with_setting(source: Path, dest: Path, key: str, value: float) -> None:
    """Copy the run at `source` to `dest` (replacing it) with model.`key` = `value` in its weights' metadata."""
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for name in ("run.json", "config.toml", "train_log.parquet"):
        shutil.copy(source / name, dest / name)
    shutil.copytree(source / "final", dest / "final")
    weights = dest / "final" / "model.safetensors"
    with safe_open(str(weights), "pt") as handle:
        metadata = dict(handle.metadata())
    config = json.loads(metadata["config"])
    if key not in {field.name for field in fields(ModelConfig)}:
        raise SystemExit(f"{key}: not a model setting")
    config[key] = value
    metadata["config"] = json.dumps(config, sort_keys=True)
    save_file(load_file(str(weights)), str(weights), metadata=metadata)


if __name__ == "__main__":
    src, dst, setting, number = sys.argv[1:5]
    copy_with_setting(Path(src), Path(dst), setting, float(number))
