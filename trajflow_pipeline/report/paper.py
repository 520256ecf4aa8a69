"""The report's metric columns and the paper's TrajFlow results (SPEC section 6), the targets to meet or beat."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MetricSpec:
    """One metric column: its name in metrics.parquet, its table label and how many decimals it is shown with."""

    name: str
    label: str
    decimals: int


#: The table columns in order; every one is lower-is-better (distances, negative log-likelihoods, divergence).
METRICS: tuple[MetricSpec, ...] = (
    MetricSpec("min_ade", "minADE", 3),
    MetricSpec("min_fde", "minFDE", 3),
    MetricSpec("min_ade_joint", "minADE joint", 3),
    MetricSpec("min_fde_joint", "minFDE joint", 3),
    MetricSpec("nll", "NLL indep", 2),
    MetricSpec("nll_joint", "NLL joint", 2),
    MetricSpec("jsd", "JSD", 3),
)

METRIC_BY_NAME: dict[str, MetricSpec] = {spec.name: spec for spec in METRICS}

#: Metrics named with this prefix (NLL indep / joint and their extended-horizon variants) are unbounded above: ROME's
#: log-densities are finite but can be very negative far from every draw, so a few problems can dominate their mean.
UNBOUNDED_PREFIX = "nll"

#: The paper's TrajFlow means over seeds / folds (SPEC section 6); a missing metric was not reported.
PAPER_TRAJFLOW: dict[str, dict[str, float]] = {
    "synthetic_bimodal": {"min_ade": 0.12, "min_fde": 0.20, "nll": -39.22, "jsd": 0.683},
    "forking_paths": {"min_ade": 0.42, "min_fde": 0.71, "nll": -23.69, "jsd": 0.984},
    "eth_ucy": {"min_ade": 0.33, "min_fde": 0.55, "nll": -21.05, "nll_joint": -75.79},
    "round": {"min_ade": 0.67, "min_fde": 1.38, "nll": -42.06, "nll_joint": -81.23},
    "nuscenes": {"min_ade": 1.86, "min_fde": 3.72, "nll": 16.54, "nll_joint": 45.55},
}

#: The model whose mean is compared with the paper's numbers.
OUR_TRAJFLOW = "trajflow"

#: Display names and table order of the models the pipeline knows; other models follow alphabetically.
MODEL_LABELS: dict[str, str] = {
    "trajflow": "TrajFlow",
    "trajflow-no-ae": "TrajFlow w/o AE",
    "flomo": "FloMo",
    "cv": "Constant velocity",
}

#: Display names and section order of the datasets the paper reports; other datasets follow alphabetically.
DATASET_LABELS: dict[str, str] = {
    "synthetic_bimodal": "Synthetic bimodal",
    "forking_paths": "Forking Paths",
    "eth_ucy": "ETH/UCY",
    "round": "rounD",
    "nuscenes": "nuScenes",
}


def model_label(model: str) -> str:
    """Human-readable name of a model id (the id itself for models the pipeline does not know)."""
    return MODEL_LABELS.get(model, model)


def dataset_label(dataset: str) -> str:
    """Human-readable name of a dataset id (the id itself for user datasets)."""
    return DATASET_LABELS.get(dataset, dataset)


def _order_key(known: dict[str, str], name: str) -> tuple[int, str]:
    order = list(known)
    return (order.index(name), "") if name in known else (len(order), name)


def model_order(models: list[str] | set[str]) -> list[str]:
    """Models in table order: TrajFlow, its ablation, FloMo, constant velocity, then others by name."""
    return sorted(set(models), key=lambda m: _order_key(MODEL_LABELS, m))


def dataset_order(datasets: list[str] | set[str]) -> list[str]:
    """Datasets in the paper's order, then user datasets by name."""
    return sorted(set(datasets), key=lambda d: _order_key(DATASET_LABELS, d))


#: Suffixes of the metrics `trajflow eval --extended-horizon` adds (see stages/evaluate.py) and their labels.
EXTENDED_VARIANTS: tuple[tuple[str, str], ...] = (
    ("_ext", "to own horizon"),
    ("_ext_long", "to own horizon, long samples only"),
)


def metric_columns(present: list[str] | set[str]) -> list[MetricSpec]:
    """All standard metric columns, then the extended-horizon variants present (labelled after their base metric),
    then any other metric found in the data (shown under its own name with 3 decimals)."""
    extended = [MetricSpec(f"{spec.name}{suffix}", f"{spec.label} ({label})", spec.decimals)
                for suffix, label in EXTENDED_VARIANTS for spec in METRICS if f"{spec.name}{suffix}" in present]
    known = set(METRIC_BY_NAME) | {spec.name for spec in extended}
    return [*METRICS, *extended, *(MetricSpec(name, name, 3) for name in sorted(set(present) - known))]
