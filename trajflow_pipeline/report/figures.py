"""The report's figures as PNG bytes, drawn with matplotlib's object API on an Agg canvas.

No pyplot: nothing global is touched (no backend switch, no open-figure registry), so the report can run inside
other programs and threads. Each function takes plain arrays prepared by `scenes` / `curves` and returns bytes.
"""

from __future__ import annotations

import io

import numpy as np
import polars as pl
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.collections import LineCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator
from scipy.interpolate import RegularGridInterpolator
from scipy.stats import gaussian_kde

from .paper import model_label
from .scenes import DensityData, Panel

DPI = 100
#: Points a kernel density is fitted on, and the grid it is evaluated on (per axis), for the density panel.
KDE_FIT_POINTS = 1500
KDE_GRID = 96
LIKELIHOOD_CMAP = "viridis"
DENSITY_CMAP = "plasma"


def to_png(figure: Figure) -> bytes:
    """Render `figure` with the Agg canvas into PNG bytes."""
    FigureCanvasAgg(figure)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI)
    return buffer.getvalue()


def relative_scale(values: np.ndarray, low: float = 5, high: float = 95) -> np.ndarray:
    """Values mapped to [0, 1] between two percentiles (robust to outliers); non-finite values map to 0."""
    finite = np.isfinite(values)
    if not finite.any():
        return np.zeros(values.shape)
    lo, hi = np.percentile(values[finite], [low, high])
    scaled = (values - lo) / (hi - lo) if hi > lo else np.ones(values.shape)
    return np.where(finite, np.clip(scaled, 0.0, 1.0), 0.0)


def square_limits(points: np.ndarray, margin: float = 0.08) -> tuple[tuple[float, float], tuple[float, float]]:
    """Square x / y limits around (n, 2) points, so equal-aspect panels share one extent."""
    points = points[np.isfinite(points).all(axis=1)]
    if points.size == 0:
        return (-1.0, 1.0), (-1.0, 1.0)
    low, high = points.min(axis=0), points.max(axis=0)
    centre, half = (low + high) / 2, max(float((high - low).max()) / 2, 0.5) * (1 + margin)
    return (centre[0] - half, centre[0] + half), (centre[1] - half, centre[1] + half)


def _panel_extent(panel: Panel) -> np.ndarray:
    """Points that must be visible in a panel: past, all futures, and the central 98 % of the draws."""
    parts = [panel.past, *panel.futures]
    if panel.draws is not None and panel.draws.size:
        flat = panel.draws.reshape(-1, 2)
        parts.append(np.nanpercentile(flat, [1, 99], axis=0))
    return np.concatenate(parts)


def _draw_panel(ax: Axes, panel: Panel) -> None:
    """Past solid, every ground-truth future dashed, draws coloured and faded by their log-likelihood."""
    if panel.draws is not None and panel.log_lik is not None:
        strength = relative_scale(panel.log_lik)
        order = np.argsort(strength, kind="stable")
        colours = colormaps[LIKELIHOOD_CMAP](strength[order])
        colours[:, 3] = 0.12 + 0.8 * strength[order]
        ax.add_collection(LineCollection(list(panel.draws[order]), colors=colours, linewidths=0.9, zorder=2))
    alpha = float(np.clip(3.0 / np.sqrt(max(len(panel.futures), 1)), 0.05, 1.0))
    ax.add_collection(LineCollection(panel.futures, colors="black", linestyles="dashed", linewidths=1.0,
                                     alpha=alpha, zorder=3))
    ax.plot(panel.past[:, 0], panel.past[:, 1], color="black", linewidth=2.0, zorder=4)
    ax.plot(panel.past[-1:, 0], panel.past[-1:, 1], "o", color="black", markersize=3.5, zorder=5)


def _relative_colorbar(figure: Figure, axes: list[Axes], cmap: str, label: str) -> None:
    """A colour bar for values scaled to [0, 1] within each panel: its ends read low / high, not numbers."""
    bar = figure.colorbar(ScalarMappable(Normalize(0, 1), colormaps[cmap]), ax=axes, shrink=0.6, label=label)
    bar.set_ticks([0, 1], labels=["low", "high"])


def plot_examples(rows: list[list[Panel | None]], models: list[str], title: str) -> bytes:
    """Grid of example samples (rows) × models (columns), paper Fig. 1 / 3 style, shared extent per row."""
    n_rows, n_cols = len(rows), len(models)
    figure = Figure(figsize=(3.0 * n_cols + 0.8, 2.9 * n_rows + 0.9), layout="constrained")
    axes = np.atleast_2d(figure.subplots(n_rows, n_cols, squeeze=False))
    for r, panels in enumerate(rows):
        present = [p for p in panels if p is not None]
        xlim, ylim = square_limits(np.concatenate([_panel_extent(p) for p in present])) if present else ((0, 1),
                                                                                                      (0, 1))
        for c, panel in enumerate(panels):
            ax = axes[r, c]
            if r == 0:
                ax.set_title(model_label(models[c]), fontsize=10)
            if panel is None:
                ax.text(0.5, 0.5, "sample not evaluated\nin this model's run", ha="center", va="center",
                        transform=ax.transAxes, fontsize=8, color="grey")
                ax.set_xticks([])
                ax.set_yticks([])
                continue
            _draw_panel(ax, panel)
            ax.set_xlim(*xlim)
            ax.set_ylim(*ylim)
            ax.set_aspect("equal", adjustable="box")
            ax.tick_params(labelsize=7)
            if c == 0:
                ax.set_ylabel(f"sample {panel.sample_id}\ny (m)", fontsize=8)
    _relative_colorbar(figure, list(axes.ravel()), LIKELIHOOD_CMAP, "draw log-likelihood\n(relative, per panel)")
    figure.suptitle(title, fontsize=11)
    return to_png(figure)


def kde_colours(points: np.ndarray, seed: int = 0) -> np.ndarray:
    """Per-point log kernel density, scaled to [0, 1] within the cloud.

    scipy's gaussian_kde is fitted on a seeded subsample (KDE_FIT_POINTS) and evaluated on a KDE_GRID² grid
    over the cloud's extent; each point takes the bilinearly interpolated grid value. That keeps a panel of
    40,000 points well under a second while matching the point-wise density to the grid's resolution. A
    degenerate cloud (all points on a line or one point) has no density: every point gets 1.
    """
    finite = np.isfinite(points).all(axis=1)
    if finite.sum() < 3:
        return np.ones(len(points))
    cloud = points[finite]
    rng = np.random.default_rng(seed)
    fit = cloud[rng.choice(len(cloud), size=min(len(cloud), KDE_FIT_POINTS), replace=False)]
    low, high = cloud.min(axis=0), cloud.max(axis=0)
    axes = [np.linspace(lo, hi if hi > lo else lo + 1.0, KDE_GRID) for lo, hi in zip(low, high)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=0).reshape(2, -1)
    try:
        log_density = gaussian_kde(fit.T).logpdf(grid).reshape(KDE_GRID, KDE_GRID)
    except (np.linalg.LinAlgError, ValueError):
        return np.ones(len(points))
    values = np.zeros(len(points))
    values[finite] = RegularGridInterpolator(axes, log_density)(cloud)
    return np.where(finite, relative_scale(values, 1, 99), 0.0)


def plot_density(data: DensityData, title: str) -> bytes:
    """Paper Fig. 3: ground-truth futures vs each model's draws, points coloured by kernel density, one extent."""
    clouds = [("Ground truth", data.ground_truth), *((model_label(m), pts) for m, pts in data.models)]
    finite = [c[np.isfinite(c).all(axis=1)] for _, c in clouds if len(c)]
    extent = np.concatenate([data.past, *(np.percentile(c, [0.5, 99.5], axis=0) for c in finite if len(c))])
    xlim, ylim = square_limits(extent)
    figure = Figure(figsize=(3.0 * len(clouds) + 0.8, 3.4), layout="constrained")
    axes = figure.subplots(1, len(clouds), squeeze=False)[0]
    for ax, (label, points) in zip(axes, clouds):
        if len(points):
            strength = kde_colours(points)
            order = np.argsort(strength, kind="stable")
            ax.scatter(points[order, 0], points[order, 1], c=strength[order], cmap=DENSITY_CMAP, vmin=0, vmax=1,
                       s=1.5, linewidths=0, rasterized=True)
        ax.plot(data.past[:, 0], data.past[:, 1], color="black", linewidth=2.0)
        ax.set_title(f"{label} ({len(points)} points)", fontsize=9)
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)
        ax.set_aspect("equal", adjustable="box")
        ax.tick_params(labelsize=7)
    _relative_colorbar(figure, list(axes), DENSITY_CMAP, "log kernel density\n(relative, per panel)")
    figure.suptitle(title, fontsize=11)
    return to_png(figure)


def plot_training(logs: list[tuple[str, pl.DataFrame]], title: str) -> bytes:
    """Train (solid) and validation (dashed) loss vs epoch, one panel per stage, one colour per run."""
    stages = list(dict.fromkeys(s for _, log in logs for s in log.get_column("stage").to_list()))
    stages.sort(key=lambda s: {"autoencoder": 0, "flow": 1}.get(s, 2))
    figure = Figure(figsize=(4.2 * len(stages) + 1.8, 3.4), layout="constrained")
    axes = figure.subplots(1, len(stages), squeeze=False)[0]
    colours = colormaps["tab10"]
    for ax, stage in zip(axes, stages):
        for index, (label, log) in enumerate(logs):
            part = log.filter(pl.col("stage") == stage).sort("epoch")
            if part.is_empty():
                continue
            epoch = part.get_column("epoch").to_numpy()
            colour = colours(index % 10)
            # a closed-form stage (standardize, temperature) is one epoch: a point, which a line would not show
            marker = "o" if part.height == 1 else None
            ax.plot(epoch, part.get_column("train_loss").to_numpy(), color=colour, linewidth=1.2, label=label,
                    marker=marker)
            val = part.get_column("val_loss").cast(pl.Float64).fill_null(np.nan).to_numpy()
            if np.isfinite(val).any():
                ax.plot(epoch, val, color=colour, linewidth=1.2, linestyle="dashed", marker=marker,
                        fillstyle="none")
        losses = np.concatenate([log.filter(pl.col("stage") == stage).select("train_loss", "val_loss")
                                 .cast(pl.Float64).to_numpy().ravel() for _, log in logs])
        losses = losses[np.isfinite(losses)]
        if losses.size and losses.min() > 0 and losses.max() / losses.min() > 50:
            ax.set_yscale("log")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        if all(log.filter(pl.col("stage") == stage).height <= 1 for _, log in logs):
            ax.set_xticks([1])
        ax.set_title(f"stage: {stage}", fontsize=10)
        ax.set_xlabel("epoch")
        ax.set_ylabel("loss")
        ax.tick_params(labelsize=7)
    handles, labels = axes[0].get_legend_handles_labels()
    for ax in axes[1:]:
        more_handles, more_labels = ax.get_legend_handles_labels()
        handles += [h for h, lab in zip(more_handles, more_labels) if lab not in labels]
        labels += [lab for lab in more_labels if lab not in labels]
    figure.legend(handles, labels, loc="outside right upper", fontsize=7, title="solid: train, dashed: val",
                  title_fontsize=7)
    figure.suptitle(title, fontsize=11)
    return to_png(figure)


def plot_min_ade_k(curves: list[tuple[str, np.ndarray, np.ndarray | None]], k_mark: int | None,
                   title: str) -> bytes:
    """minADE vs K, one line per model (mean over runs, band ± std over runs when there are several)."""
    figure = Figure(figsize=(5.6, 3.8), layout="constrained")
    ax = figure.subplots()
    colours = colormaps["tab10"]
    for index, (model, mean, std) in enumerate(curves):
        k = np.arange(1, mean.size + 1)
        ax.plot(k, mean, color=colours(index % 10), linewidth=1.6, label=model_label(model),
                marker="o" if mean.size == 1 else None)
        if std is not None:
            ax.fill_between(k, mean - std, mean + std, color=colours(index % 10), alpha=0.2, linewidth=0)
    if k_mark is not None:
        ax.axvline(k_mark, color="grey", linestyle="dotted", linewidth=1.0, label=f"K = {k_mark} (tables)")
    ax.set_xlabel("K (draws)")
    ax.set_ylabel("expected minADE_K (m)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=11)
    return to_png(figure)
