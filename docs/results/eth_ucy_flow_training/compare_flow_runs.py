"""Compare evaluated TrajFlow runs on one fold that differ only in how their flow was trained (learning rate,
patience): the settings that differ, the flow epochs each trained and kept, and the test metrics, as means and
over agents (median, upper quartile, and the share of agents each run fits better than the first).

    python docs/results/eth_ucy_flow_training/compare_flow_runs.py OUT RUN [RUN ...]

Writes OUT/runs.parquet (one row per run), OUT/flow_loss.png (each run's flow validation loss per epoch, its
training loss dashed) and OUT/models/<run>/ (what docs/results/publish.py publishes of a run, plus its eval.json),
and prints the rows as a Markdown table. The first RUN is the reference.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import asdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import polars as pl  # noqa: E402

from trajflow_pipeline.model.config import load_config  # noqa: E402
from trajflow_pipeline.stages.evaluate import EVAL_DIR  # noqa: E402
from trajflow_pipeline.util.atomic import atomic_directory  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from publish import publish_run  # noqa: E402

#: per-agent metrics summarised beyond their mean (lower is better for all)
PER_AGENT = ("nll", "nll_joint", "min_ade")


def differing_settings(runs: list[Path]) -> list[str]:
    """The [train] settings (device aside) whose values are not the same in every run's config.toml."""
    configs = [asdict(load_config(run / "config.toml").train) for run in runs]
    return [key for key in configs[0] if key != "device" and len({repr(c[key]) for c in configs}) > 1]


def per_agent(run: Path) -> pl.DataFrame:
    """The run's per-agent (per-group for joint metrics) rows: metric, unit (agent index or group key), value."""
    rows = pl.read_parquet(run / EVAL_DIR / "metrics.parquet").filter(~pl.col("aggregate"))
    unit = pl.when(pl.col("metric").str.ends_with("_joint")).then(pl.col("group_key")).otherwise(pl.col("agent_index"))
    return rows.select("metric", unit.alias("unit"), "value")


def summarise(run: Path, settings: list[str], reference: pl.DataFrame) -> dict[str, object]:
    """One row: the run's differing settings, flow epochs (trained, best), best validation loss and test metrics."""
    info = json.loads((run / "run.json").read_text())
    train = asdict(load_config(run / "config.toml").train)
    flow_epochs = pl.read_parquet(run / "train_log.parquet").filter(pl.col("stage") == "flow").height
    means = pl.read_parquet(run / EVAL_DIR / "metrics.parquet").filter(pl.col("aggregate"))
    row: dict[str, object] = {"run": run.name, **{key: train[key] for key in settings},
                              "flow_epochs": flow_epochs, "best_flow_epoch": info["best"]["flow"]["epoch"],
                              "best_flow_val_loss": info["best"]["flow"]["val_loss"],
                              **dict(zip(means.get_column("metric"), means.get_column("value")))}
    paired = per_agent(run).join(reference, on=["metric", "unit"], suffix="_reference")
    for metric in PER_AGENT:
        values = paired.filter(pl.col("metric") == metric)
        row[f"{metric}_median"] = values.get_column("value").median()
        row[f"{metric}_q75"] = values.get_column("value").quantile(0.75)
        row[f"{metric}_share_better"] = (values.get_column("value") < values.get_column("value_reference")).mean()
    return row


def plot_flow_loss(runs: list[Path], path: Path) -> None:
    """Each run's flow validation loss per epoch (solid) and training loss (dashed), the best epoch marked."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    lowest, highest = float("inf"), float("-inf")
    for colour, run in zip(plt.rcParams["axes.prop_cycle"].by_key()["color"], runs):
        log = pl.read_parquet(run / "train_log.parquet").filter(pl.col("stage") == "flow")
        best = json.loads((run / "run.json").read_text())["best"]["flow"]
        ax.plot(log["epoch"], log["val_loss"], color=colour, label=f"{run.name} (validation)")
        ax.plot(log["epoch"], log["train_loss"], color=colour, linestyle="--", linewidth=0.8)
        ax.plot([best["epoch"]], [best["val_loss"]], marker="o", color=colour)
        lowest = min(lowest, float(log["val_loss"].min()), float(log["train_loss"].min()))
        highest = max(highest, float(log.filter(pl.col("epoch") >= 5)["val_loss"].max()))
    ax.set_ylim(lowest - 2, highest + 2)  # the first epochs' losses would flatten the rest
    ax.set_xlabel("flow epoch")
    ax.set_ylabel("latent NLL (nats)")
    fold = json.loads((runs[0] / "run.json").read_text()).get("fold")
    ax.set_title(f"Flow training on fold {fold} (dashed: training loss; dot: the epoch kept)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="results directory, e.g. docs/results/eth_ucy_flow_training")
    parser.add_argument("runs", type=Path, nargs="+", help="evaluated run directories; the first is the reference")
    args = parser.parse_args()
    runs: list[Path] = args.runs
    settings = differing_settings(runs)
    reference = per_agent(runs[0]).rename({"value": "value_reference"})
    table = pl.DataFrame([summarise(run, settings, reference) for run in runs])
    args.out.mkdir(parents=True, exist_ok=True)
    table.write_parquet(args.out / "runs.parquet")
    plot_flow_loss(runs, args.out / "flow_loss.png")
    with atomic_directory(args.out / "models") as staging:
        for run in runs:
            publish_run(run, staging / run.name)
            shutil.copy2(run / EVAL_DIR / "eval.json", staging / run.name / "eval.json")
    columns = ["run", *settings, "flow_epochs", "best_flow_epoch", "best_flow_val_loss", "min_ade", "min_fde", "nll",
               "nll_joint", "nll_median", "nll_q75", "nll_share_better"]
    print("| " + " | ".join(columns) + " |\n|" + "---|" * len(columns))
    for row in table.select(columns).iter_rows():
        print("| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row) + " |")


if __name__ == "__main__":
    main()
