"""The paper's metrics as pure numpy / ROME functions: minADE_K / minFDE_K (indep and joint), NLL (indep and
joint) and JSD from ROME density estimates, with ROME fits spread over processes.

Knows nothing about files, models or Parquet: inputs are arrays in metres, pred (A, S, T, 2), gt (A, T, 2),
optional integer keys joint_key (A,) and group_id (A,), and an optional per-agent horizon (A,) when agents have
ground truth for different numbers of steps (rounD's extended evaluation). `compute_metrics` is the eval stage's
entry point; the per-metric functions are for direct use (figures such as minADE as a function of K, notebooks).
"""

from trajflow_pipeline.metrics.compute import METRIC_NAMES, check_metric_names, compute_metrics
from trajflow_pipeline.metrics.density import (DensityResults, density_metrics, jsd, jsd_groups, nll_indep,
                                               nll_joint)
from trajflow_pipeline.metrics.displacement import (DEFAULT_K, ade_fde_per_draw, min_ade, min_ade_joint, min_fde,
                                                    min_fde_joint)
from trajflow_pipeline.metrics.divergence import jsd_from_log_densities
from trajflow_pipeline.metrics.parallel import RomeTally, RomeTask, fit_and_score, run_rome_tasks

__all__ = [
    "DEFAULT_K",
    "METRIC_NAMES",
    "DensityResults",
    "RomeTally",
    "RomeTask",
    "ade_fde_per_draw",
    "check_metric_names",
    "compute_metrics",
    "density_metrics",
    "fit_and_score",
    "jsd",
    "jsd_from_log_densities",
    "jsd_groups",
    "min_ade",
    "min_ade_joint",
    "min_fde",
    "min_fde_joint",
    "nll_indep",
    "nll_joint",
    "run_rome_tasks",
]
