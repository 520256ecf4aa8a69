"""Windows and identical-input groups: positions the grouping grid cannot hold are named, not a bare cast error."""

from __future__ import annotations

import polars as pl
import pytest

from trajflow_pipeline.errors import DataError
from trajflow_pipeline.ingest.windows import identical_input_groups


def tracks(x: float) -> pl.DataFrame:
    return pl.DataFrame({"scene_id": ["s"] * 3, "agent_id": [1, 1, 1], "agent_type": ["pedestrian"] * 3,
                         "frame": [0, 1, 2], "x": [0.0, x, 2.0], "y": [0.0, 0.0, 0.0]})


SAMPLES = pl.DataFrame({"scene_id": ["s"], "agent_id": [1], "t0_frame": [1], "n_past": [2]})


def test_ordinary_positions_group() -> None:
    assert identical_input_groups(SAMPLES, tracks(1.0)).to_list() == [0]


@pytest.mark.parametrize(("x", "why"), [(1e300, "beyond the largest magnitude"), (float("inf"), "not finite")])
def test_a_position_off_the_grid_is_named(x: float, why: str) -> None:
    with pytest.raises(DataError, match=rf"of agent 1 in scene 's' at frame 1 is {why}"):
        identical_input_groups(SAMPLES, tracks(x))
