"""`ingest round` on synthetic levelX recordings: resampling, geometry, gap-acceptance samples, folds, maps, CLI,
and the dataset driving a TrajFlow model with its map CNN."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch
import typer
from PIL import Image
from test_round_synth import (ARMS_DEG, CENTRE, EGO_ACCEPT, EGO_REJECT, LANE_RADIUS, MARKER, ORTHO_PX_TO_METER,
                              TARGET_ACCEPT, TARGET_REJECT, gap_scenario, write_gap_recordings, write_recording)
from typer.testing import CliRunner

from trajflow_pipeline.cli.ingest_cmd import ingest_round_command
from trajflow_pipeline.data.loader import build_problems, list_folds, load_problems
from trajflow_pipeline.data.maps import crops_for_problems, past_headings
from trajflow_pipeline.schemas import open_dataset
from trajflow_pipeline.ingest.round import N_FUTURE, N_PAST, assign_splits, ingest_round
from trajflow_pipeline.ingest.round_geometry import (RoundaboutGeometry, infer_geometry, load_geometry_file)

RECORDINGS = 3


@pytest.fixture(scope="module")
def raw(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_gap_recordings(tmp_path_factory.mktemp("round") / "raw", RECORDINGS)


@pytest.fixture(scope="module")
def data(raw: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return ingest_round(raw, tmp_path_factory.mktemp("round_out") / "round", quiet=True)


def test_tracks_are_resampled_to_5_hz_with_contract_columns(raw: Path, data: Path) -> None:
    ds = open_dataset(data)
    tracks = ds.tracks()
    raw_tracks = pl.read_csv(raw / "00_tracks.csv")
    kept = raw_tracks.filter(pl.col("frame") % 5 == 0)
    rec = tracks.filter(pl.col("scene_id") == "rec00")
    assert rec.height == kept.height
    assert ds.counts["tracks"] == sum(pl.read_csv(raw / f"{i:02d}_tracks.csv").filter(pl.col("frame") % 5 == 0).height
                                      for i in range(RECORDINGS))
    row = kept.filter((pl.col("trackId") == TARGET_ACCEPT)).row(3, named=True)
    same = rec.filter((pl.col("agent_id") == TARGET_ACCEPT) & (pl.col("frame") == row["frame"] // 5)).row(0, named=True)
    assert same["t"] == pytest.approx(row["frame"] / 25)
    assert (same["x"], same["y"], same["vx"], same["vy"]) == (row["xCenter"], row["yCenter"], row["xVelocity"],
                                                              row["yVelocity"])
    assert abs(math.remainder(same["heading"] - math.radians(row["heading"]), 2 * math.pi)) < 1e-9
    assert (same["length"], same["width"]) == (row["length"], row["width"])
    steps = rec.filter(pl.col("agent_id") == TARGET_ACCEPT).get_column("frame").diff().drop_nulls()
    assert (steps == 1).all()
    types = dict(rec.select("agent_class", "agent_type").unique().iter_rows())
    assert types == {"car": "vehicle", "van": "vehicle", "truck": "vehicle", "pedestrian": "pedestrian",
                     "bicycle": "bicycle"}
    assert ds.meta.dt == 0.2 and ds.meta.protocol == "folds"
    assert rec.get_column("heading").is_between(-math.pi, math.pi).all()


def test_roundabout_geometry_is_inferred_from_circulating_traffic(data: Path) -> None:
    scenes = open_dataset(data).scenes()
    assert scenes.get_column("geometry_source").to_list() == ["inferred"] * RECORDINGS
    for row in scenes.iter_rows(named=True):
        assert math.hypot(row["centre_x"] - CENTRE[0], row["centre_y"] - CENTRE[1]) < 0.1
        assert row["inner_radius"] == pytest.approx(LANE_RADIUS - 1.0, abs=0.3)
        assert row["outer_radius"] == pytest.approx(LANE_RADIUS + 1.0, abs=0.3)
        assert row["circulation"] == 1
    arms = json.loads((data / "dataset.json").read_text())["lineage"]["recordings"][0]["geometry"]["entry_angles"]
    assert len(arms) == 4
    # each entry arm is found just counter-clockwise of the arm's axis (entry lanes keep right)
    offsets = sorted((math.degrees(a) - arm + 180) % 360 - 180 for a in arms for arm in ARMS_DEG
                     if abs((math.degrees(a) - arm + 180) % 360 - 180) < 45)
    assert len(offsets) == 4 and all(0 < offset < 30 for offset in offsets)


def test_noisy_and_clockwise_geometry_fits() -> None:
    """The fit recovers the centre from noisy positions, and the direction of a mirrored (clockwise) roundabout."""
    rng = np.random.default_rng(1)
    frames = []
    for track in gap_scenario():
        if track.cls in ("car", "van", "truck"):
            n = len(track.positions[::5])
            frames.append(pl.DataFrame({
                "agent_id": np.full(n, track.track_id), "frame": track.initial_frame // 5 + np.arange(n),
                "x": track.positions[::5, 0] + rng.normal(0, 0.05, n), "y": track.positions[::5, 1]
                + rng.normal(0, 0.05, n), "vx": track.velocities[::5, 0], "vy": track.velocities[::5, 1]}))
    motor = pl.concat(frames).sort("agent_id", "frame")
    fitted = infer_geometry(motor, 0.2)
    assert math.hypot(fitted.centre_x - CENTRE[0], fitted.centre_y - CENTRE[1]) < 0.2
    assert fitted.direction == 1
    mirrored = infer_geometry(motor.with_columns(-pl.col("y"), -pl.col("vy")), 0.2)
    assert mirrored.direction == -1
    assert math.hypot(mirrored.centre_x - CENTRE[0], mirrored.centre_y + CENTRE[1]) < 0.2


def test_accepted_and_rejected_gaps_are_the_samples(data: Path) -> None:
    samples = open_dataset(data).samples()
    assert samples.height == 4 * RECORDINGS
    for scene, part in samples.group_by("scene_id"):
        pairs = {(row["agent_id"], row["partner_id"], row["gap"], row["role"]) for row in part.iter_rows(named=True)}
        assert pairs == {(TARGET_ACCEPT, EGO_ACCEPT, "accepted", "target"),
                         (EGO_ACCEPT, TARGET_ACCEPT, "accepted", "ego"),
                         (TARGET_REJECT, EGO_REJECT, "rejected", "target"),
                         (EGO_REJECT, TARGET_REJECT, "rejected", "ego")}, scene
    joint = samples.group_by("joint_id").agg(pl.len(), pl.col("t0_frame").n_unique().alias("t0s"),
                                             pl.col("role").sort().alias("roles"), pl.col("scene_id").n_unique())
    assert (joint.get_column("len") == 2).all() and (joint.get_column("t0s") == 1).all()
    assert joint.get_column("roles").to_list() == [["ego", "target"]] * (2 * RECORDINGS)
    assert set(samples.get_column("n_past")) == {N_PAST} and set(samples.get_column("n_future")) == {N_FUTURE}
    horizon = dict(samples.group_by("gap").agg(pl.col("n_future_max").unique()).iter_rows())
    assert horizon == {"accepted": [25], "rejected": [35]}     # the long wait needs 35 steps
    assert (samples.get_column("t0_frame") < samples.get_column("decision_frame")).all()
    accepted = samples.filter(pl.col("gap") == "accepted")
    assert (accepted.get_column("conflict_frame") > accepted.get_column("decision_frame")).all()
    rejected = samples.filter(pl.col("gap") == "rejected")
    assert (rejected.get_column("conflict_frame") == rejected.get_column("decision_frame")).all()


def test_decision_frames_match_the_tracks(data: Path) -> None:
    """Accepted: the target crosses into the carriageway at the decision; rejected: the target is still out."""
    ds = open_dataset(data)
    tracks, scenes = ds.tracks(), ds.scenes()
    geometry = scenes.row(0, named=True)
    r = ((pl.col("x") - geometry["centre_x"]) ** 2 + (pl.col("y") - geometry["centre_y"]) ** 2).sqrt()
    targets = ds.samples().filter((pl.col("role") == "target") & (pl.col("scene_id") == "rec00"))
    for row in targets.iter_rows(named=True):
        target = tracks.filter((pl.col("scene_id") == "rec00") & (pl.col("agent_id") == row["agent_id"]))
        entry = target.filter(r < geometry["outer_radius"]).get_column("frame").min()
        if row["gap"] == "accepted":
            assert entry == row["decision_frame"]
        else:
            assert entry > row["decision_frame"]


def test_windows_and_context_are_in_the_tracks(data: Path) -> None:
    ds = open_dataset(data)
    tracks = ds.tracks().select("scene_id", "agent_id", "frame", "agent_type")
    samples = ds.samples()
    need = (samples.with_columns(frame=pl.int_ranges(pl.col("t0_frame") - N_PAST + 1,
                                                     pl.col("t0_frame") + pl.col("n_future_max") + 1))
            .explode("frame").select("scene_id", "agent_id", "frame"))
    assert need.join(tracks, on=["scene_id", "agent_id", "frame"], how="anti").height == 0
    context = (samples.filter(pl.col("role") == "target").select("scene_id", pl.col("t0_frame").alias("frame"))
               .join(tracks, on=["scene_id", "frame"]).get_column("agent_type").unique().to_list())
    assert {"vehicle", "pedestrian", "bicycle"} <= set(context)


def test_folds_keep_situations_together(data: Path) -> None:
    ds = open_dataset(data)
    samples = ds.samples()
    per_situation = samples.group_by("situation_id").agg(pl.col("fold").n_unique(), pl.col("split").n_unique(),
                                                         pl.col("joint_id").n_unique())
    assert (per_situation.get_column("fold") == 1).all() and (per_situation.get_column("split") == 1).all()
    per_joint = samples.group_by("joint_id").agg(pl.col("situation_id").n_unique())
    assert (per_joint.get_column("situation_id") == 1).all()
    assert set(samples.get_column("fold")) <= {"0", "1", "2", "3", "4"}
    assert set(samples.get_column("split")) <= {"train", "val"}
    assert samples.filter(pl.col("split") == "val").get_column("situation_id").n_unique() == 1  # ceil(10 % of 6)
    folds = list_folds(ds)
    for fold in folds:
        test = load_problems(data, fold=fold, split="test")
        train_ids = set(load_problems(data, fold=fold, split="train").joint_id.tolist())
        assert not set(test.joint_id.tolist()) & train_ids
        assert test.batch.past.shape[1:] == (N_PAST, 2) and test.batch.future.shape[1:] == (N_FUTURE, 2)
    again = ingest_round(_raw_of(data), data.parent / "again", quiet=True)
    assert open_dataset(again).samples().equals(samples)       # seeded: the same input gives the same splits


def test_a_targets_gaps_form_one_situation_and_folds_balance() -> None:
    """Target 1 rejects egos 2 and 3 and accepts ego 4: one situation; 101 situations deal evenly into folds."""
    pairs = [("rec00", 0, 1, 2, 10, "rejected"), ("rec00", 1, 1, 3, 12, "rejected"), ("rec00", 2, 1, 4, 14, "accepted")]
    pairs += [("rec01", k, 100 + k, 500 + k, 10 + k, "accepted") for k in range(100)]
    rows = [{"scene_id": scene, "pair": pair, "t0_frame": t0, "gap": gap, "decision_frame": t0 + 3,
             "conflict_frame": t0 + 4, "critical_frame": None, "entry_arm": 0, "n_future_max": 25, "agent_id": agent,
             "partner_id": partner, "role": role, "n_past": N_PAST, "n_future": N_FUTURE,
             "input_key": 2 * (1000 * pair + agent) + (role == "ego")}
            for scene, pair, target, ego, t0, gap in pairs
            for agent, partner, role in ((target, ego, "target"), (ego, target, "ego"))]
    samples = assign_splits(pl.DataFrame(rows))
    first = samples.filter(pl.col("scene_id") == "rec00")
    assert first.get_column("situation_id").n_unique() == 1 and first.get_column("joint_id").n_unique() == 3
    assert first.get_column("fold").n_unique() == 1
    per_fold = samples.group_by("fold").agg(pl.col("situation_id").n_unique())
    assert sorted(per_fold.get_column("situation_id").to_list()) == [20, 20, 20, 20, 21]
    assert samples.filter(pl.col("split") == "val").get_column("situation_id").n_unique() == 11   # ceil(10 % of 101)
    assert samples.get_column("sample_id").to_list() == list(range(samples.height))


def _raw_of(data: Path) -> Path:
    return Path(json.loads((data / "dataset.json").read_text())["lineage"]["raw"])


def test_background_becomes_the_map(raw: Path, data: Path) -> None:
    scenes = open_dataset(data).scenes()
    assert scenes.get_column("map_path").n_unique() == 1       # identical backgrounds are stored once
    path = data / scenes.get_column("map_path")[0]
    with Image.open(path) as image:
        assert image.mode == "L" and image.size == Image.open(raw / "00_background.png").size
    scale = ORTHO_PX_TO_METER * 10
    assert scenes.get_column("map_m_per_px").to_list() == [pytest.approx(scale)] * RECORDINGS
    assert scenes.get_column("map_world_to_px")[0].to_list() == pytest.approx([1 / scale, 0, 0, 0, -1 / scale, 0])


def test_map_crop_of_the_background_is_aligned(data: Path) -> None:
    """The white marker of the generated background lands where the target's position and heading put it."""
    ds = open_dataset(data)
    problems = build_problems(ds, ds.samples())
    position = problems.batch.past[:, -1].numpy().astype(np.float64)
    heading = past_headings(problems.batch.past.numpy())
    metres = 1.0
    crops = crops_for_problems(data, problems.scene_id, position, heading, metres_per_pixel_out=metres)
    for crop, p, h in zip(crops[:, 0], position, heading):
        dx, dy = MARKER[0] - p[0], MARKER[1] - p[1]
        col = 128 + (math.cos(h) * dx + math.sin(h) * dy) / metres
        row = 77.5 - (-math.sin(h) * dx + math.cos(h) * dy) / metres
        near = crop[int(round(row)) - 1:int(round(row)) + 2, int(round(col)) - 1:int(round(col)) + 2]
        assert near.max() > 0.8, (row, col)
        assert crop[77:79, 127:130].max() < 0.35               # the target itself stands on asphalt


def test_trajflow_with_the_map_cnn_trains_and_predicts_35_steps(data: Path) -> None:
    from trajflow_pipeline.model.config import DataSpec, ModelConfig
    from trajflow_pipeline.model.models import build_model

    ds = open_dataset(data)
    problems = build_problems(ds, ds.samples())
    assert problems.has_map
    batch = problems.batch
    crops = crops_for_problems(data, problems.scene_id, batch.past[:, -1].numpy(), past_headings(batch.past.numpy()))
    batch.map_crop = torch.from_numpy(crops)
    torch.manual_seed(0)
    config = ModelConfig(flow_layers=2, flow_hidden=(16,))
    model = build_model(config, DataSpec(n_past=N_PAST, n_future=N_FUTURE, has_map=True, dataset="round", dt=0.2))
    assert model.context.map is not None
    for stage in model.stages:
        optimizer = torch.optim.Adam(model.stage_parameters(stage), lr=1e-3)
        losses = []
        for _ in range(3):
            optimizer.zero_grad()
            loss = model.stage_loss(stage, batch)
            loss.backward()
            optimizer.step()
            losses.append(loss.item())
        assert all(math.isfinite(value) for value in losses)
    map_weight = next(model.context.map.parameters())
    assert map_weight.grad is not None and map_weight.grad.abs().sum() > 0
    samples = model.sample(batch.without_future(), 4, steps=35)
    assert samples.trajectories.shape == (len(batch), 4, 35, 2)
    assert torch.isfinite(samples.trajectories).all() and torch.isfinite(samples.log_lik).all()


def test_one_recording_selection_and_explicit_geometry(raw: Path, tmp_path: Path) -> None:
    geometry = RoundaboutGeometry(centre_x=CENTRE[0], centre_y=CENTRE[1], inner_radius=10.5, outer_radius=13.5)
    out = ingest_round(raw / "01_tracks.csv", tmp_path / "one", geometry={1: geometry}, quiet=True)
    scenes = open_dataset(out).scenes()
    assert scenes.get_column("scene_id").to_list() == ["rec01"]
    assert scenes.row(0, named=True)["geometry_source"] == "given"
    assert scenes.row(0, named=True)["outer_radius"] == 13.5
    assert open_dataset(out).samples().get_column("gap").sort().to_list() == ["accepted"] * 2 + ["rejected"] * 2
    two = ingest_round(raw, tmp_path / "two", recordings=["2", 0], quiet=True)
    assert open_dataset(two).scenes().get_column("scene_id").to_list() == ["rec00", "rec02"]


def test_data_subfolder_and_geometry_file(raw: Path, tmp_path: Path) -> None:
    layout = tmp_path / "rounD-dataset-v1.0"
    write_recording(layout / "data", 5, gap_scenario())
    spec = tmp_path / "geometry.json"
    spec.write_text(json.dumps({"1": {"centre": list(CENTRE), "inner_radius": 10.5, "outer_radius": 13.5}}))
    config = load_geometry_file(spec)
    assert isinstance(config, dict) and config[1].outer_radius == 13.5
    out = ingest_round(layout, tmp_path / "out", geometry=config, quiet=True)
    assert open_dataset(out).samples().height == 4


def test_cli_runs_the_stage(raw: Path, tmp_path: Path) -> None:
    app = typer.Typer()
    app.command()(ingest_round_command)
    runner = CliRunner()
    result = runner.invoke(app, [str(raw), "-o", str(tmp_path / "cli"), "--recording", "00", "--recording", "01"])
    assert result.exit_code == 0, result.output
    assert "wrote" in result.output and "2 recordings" in result.output and "8 samples" in result.output
    assert open_dataset(tmp_path / "cli").scenes().height == 2
    result = runner.invoke(app, [str(raw), "-o", str(tmp_path / "cli2"), "--recording", "07", "-q"])
    assert result.exit_code == 1
    assert result.output.startswith("error: ") and "recording(s) 07 not found; found 00, 01, 02" in result.output
