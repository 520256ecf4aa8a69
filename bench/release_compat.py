"""The training helpers the benches use, from this release's `training` package or, for the releases before it
(c91cb8d and earlier, the reference of issue 24), from `stages/train.py`, so that `--against` runs either tree."""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import trajflow_pipeline

# Decided by the tree itself: an editable install elsewhere could otherwise lend its own `training` package.
if (Path(trajflow_pipeline.__file__).parent / "training").is_dir():
    from trajflow_pipeline.training.data import load_data
    from trajflow_pipeline.training.steps import adamw, finite_gradients
else:  # releases before the training package
    from trajflow_pipeline.stages.train import _adamw as adamw  # type: ignore[no-redef]
    from trajflow_pipeline.stages.train import _finite_gradients as finite_gradients  # type: ignore[no-redef]
    from trajflow_pipeline.stages.train import _load_data as load_data  # type: ignore[no-redef]


def compile_flow_stage(model, rows: int, label: str) -> None:  # type: ignore[no-untyped-def]
    """Compile `model`'s flow-stage steps for batches of `rows` (as train.compile_flow = "on" does) and say on
    stderr, after "# " (which bench/side_by_side.py passes on), how long it took or why it stays eager; releases
    without ``compile_stage`` train eager and say nothing."""
    compile_stage = getattr(model, "compile_stage", None)
    if compile_stage is None:
        return
    start = time.perf_counter()
    failure = compile_stage("flow", rows)
    print(f"# {label}: {failure or f'compiled in {time.perf_counter() - start:.0f} s'}", file=sys.stderr)


def with_fixed_targets(model, stage: str, batch):  # type: ignore[no-untyped-def]
    """`batch` carrying what `stage` fits where training computes it once per stage (as the training loop does);
    unchanged for releases without ``fixed_targets`` or where the stage has none."""
    fixed = getattr(model, "fixed_targets", None)
    targets = None if fixed is None else fixed(stage, batch)
    return batch if targets is None else replace(batch, targets=targets)


__all__ = ["adamw", "compile_flow_stage", "finite_gradients", "load_data", "with_fixed_targets"]
