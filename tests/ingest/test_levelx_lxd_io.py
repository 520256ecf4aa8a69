"""Cross-check of our levelX reader against lxd-io (a polars-based levelX reader on PyPI, not a dependency: see
docs/datasets/levelx.md for why it is not adopted); skipped when lxd-io is not installed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from levelx_fixture import write_members

from trajflow_pipeline.ingest.levelx import LAYOUTS, discover_recordings, read_raw_tracks, read_recording_meta, \
    read_tracks_meta
from trajflow_pipeline.ingest.levelx_pipeline import centred

lxd_io = pytest.importorskip("lxd_io", reason="lxd-io is not installed (pip install lxd-io)")


@pytest.mark.parametrize("member", ["round", "highd", "ind", "exid", "unid"])
def test_both_readers_agree_on_ids_and_centres(tmp_path: Path, member: str) -> None:
    root = tmp_path / f"{member}-dataset-v1.0"
    write_members(root / "data", member, 1)
    dataset = lxd_io.Dataset(root)
    layout = LAYOUTS[member]
    recording = discover_recordings(root, None, layout)[0]
    meta = read_recording_meta(recording, layout)
    tracks_meta = read_tracks_meta(recording, layout, meta)
    ours = centred(read_raw_tracks(recording, tracks_meta, layout, meta), tracks_meta, layout)
    theirs = dataset.get_recording(dataset.recording_ids[0])
    assert sorted(theirs.track_ids) == sorted(ours.get_column("trackId").unique().to_list())
    for track_id in theirs.track_ids:
        trajectory = theirs.get_track(track_id).get_local_trajectory()
        mine = ours.filter(ours["trackId"] == track_id).select("xCenter", "yCenter").to_numpy()
        flip = -1.0 if member == "highd" else 1.0  # lxd-io keeps highD's y down the image; we store y up
        np.testing.assert_allclose(mine[:, 0], trajectory[:, 0], atol=1e-6)
        np.testing.assert_allclose(mine[:, 1], flip * trajectory[:, 1], atol=1e-6)
