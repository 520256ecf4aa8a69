"""The training helpers the benches use, from this release's `training` package or, for the releases before it
(c91cb8d and earlier, the reference of issue 24), from `stages/train.py`, so that `--against` runs either tree."""

from __future__ import annotations

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



def with_fixed_targets(model, stage: str, batch):  # type: ignore[no-untyped-def]
    """`batch` carrying what `stage` fits where training computes it once per stage (as the training loop does);
    unchanged for releases without ``fixed_targets`` or where the stage has none."""
    fixed = getattr(model, "fixed_targets", None)
    targets = None if fixed is None else fixed(stage, batch)
    return batch if targets is None else replace(batch, targets=targets)


__all__ = ["adamw", "finite_gradients", "load_data", "with_fixed_targets"]
