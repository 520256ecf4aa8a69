"""docs/results/eth_ucy_plus_standardized/draw_spread.py: the spread, centroid error and minFDE of draws it reports."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import polars as pl
import pytest
from results_scripts import load_results_script

from trajflow_pipeline.rundir import GROUND_TRUTH_FILE, PREDICTIONS_FILE


def load_script() -> ModuleType:
    return load_results_script("eth_ucy_plus_standardized/draw_spread.py")


def write_eval(folder: Path) -> None:
    """Two agents, three draws of two steps. Agent 0's final draws (0, 0), (2, 0), (1, 3) around the centroid (1, 1),
    its truth ending at (1, 0) after starting at (0, 0); agent 1's draws all on its truth (5, 5), from (5, 1)."""
    finals = {0: [(0.0, 0.0), (2.0, 0.0), (1.0, 3.0)], 1: [(5.0, 5.0)] * 3}
    rows = [{"sample_id": agent, "draw": draw, "step": step, "x": x * step / 2, "y": y * step / 2, "log_lik": 0.0}
            for agent, points in finals.items() for draw, (x, y) in enumerate(points) for step in (1, 2)]
    pl.DataFrame(rows).write_parquet(folder / PREDICTIONS_FILE)
    truth = {0: [(-1.0, 0.0), (0.0, 0.0), (0.5, 0.0), (1.0, 0.0)], 1: [(5.0, 0.0), (5.0, 1.0), (5.0, 3.0), (5.0, 5.0)]}
    pl.DataFrame([{"sample_id": agent, "group_id": agent, "joint_id": agent, "step": step, "x": x, "y": y}
                  for agent, points in truth.items() for step, (x, y) in zip((-1, 0, 1, 2), points)]
                 ).write_parquet(folder / GROUND_TRUTH_FILE)


def test_final_step_figures_per_agent(tmp_path: Path) -> None:
    script = load_script()
    write_eval(tmp_path)
    figures = script.final_step_figures(tmp_path).sort("sample_id")
    assert figures["spread"].to_list() == pytest.approx([(2 * 2 ** 0.5 + 2) / 3, 0.0])
    assert figures["centroid_error"].to_list() == pytest.approx([1.0, 0.0])
    assert figures["min_fde"].to_list() == pytest.approx([1.0, 0.0])
    assert figures["travel"].to_list() == pytest.approx([1.0, 4.0])
    line = script.summary(figures)
    assert line.startswith("2 agents, spread / centroid error / minFDE_20: 0.805 / 0.500 / 0.500 m")
