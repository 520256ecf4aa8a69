"""`trajflow ingest ...`: one command per registered ingest (trajflow_pipeline.ingest.registry), each parsing its
options and running the adapter inside :func:`user_errors`, so every problem ends as one line and an exit code."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ..errors import UsageError
from .common import OutDir, Overwrite, Quiet, user_errors
from .render import report_written

ingest_app = typer.Typer(help="Turn raw datasets into the unified Parquet scene dataset.", no_args_is_help=True)


@ingest_app.command("eth-ucy")
def ingest_eth_ucy_command(
    ctx: typer.Context,
    raw: Annotated[Path, typer.Argument(help="The Trajectron++ layout (<location>/{train,val,test}/*.txt) or a "
                                             "folder of the eight full sequences (e.g. all_data/).")],
    out: OutDir,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """ETH/UCY pedestrians: leave-one-location-out folds, 8 past + 12 future steps at 0.4 s."""
    from ..ingest.registry import get_ingest

    with user_errors(ctx):
        adapter = get_ingest("eth-ucy")
        report_written(adapter.run(raw, out, overwrite=overwrite, quiet=quiet), quiet, adapter.summary)


@ingest_app.command("synthetic-bimodal")
def ingest_synthetic_command(
    ctx: typer.Context,
    out: OutDir,
    samples: Annotated[int, typer.Option(help="Number of futures (half per mode).")] = 3000,
    seed: Annotated[int, typer.Option(help="Random seed; the same seed gives byte-identical files.")] = 0,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """The paper's synthetic bimodal set: one past of 10 steps, two future modes of 14 steps at 0.25 s."""
    from ..ingest.registry import get_ingest

    with user_errors(ctx):
        adapter = get_ingest("synthetic-bimodal")
        result = adapter.run(None, out, samples=samples, seed=seed, overwrite=overwrite, quiet=quiet)
        report_written(result, quiet, adapter.summary)


@ingest_app.command("csv")
def ingest_csv_command(
    ctx: typer.Context,
    file: Annotated[Path, typer.Argument(help="CSV (with a header) or Parquet file, one row per agent and time.")],
    out: OutDir,
    dt: Annotated[float, typer.Option(help="Seconds between frames.")],
    columns: Annotated[Optional[str], typer.Option(
        help="Column mapping role=name,... with roles scene, agent, frame or time, x, y, type "
             "(defaults: scene_id, agent_id, frame, x, y; no type column means pedestrians).")] = None,
    past: Annotated[int, typer.Option(help="Observed steps per sample (including t0).")] = 8,
    future: Annotated[int, typer.Option(help="Predicted steps per sample.")] = 12,
    name: Annotated[Optional[str], typer.Option(help="Dataset name (default: the file's stem).")] = None,
    protocol: Annotated[Optional[str], typer.Option(
        help="folds (cross-validation: train --fold F tests on fold F), fixed (train / val / test from --split-col "
             "or a --test-fraction holdout) or train-is-test (every sample tests; a --val-fraction validates; "
             "for multi-future data). Default: fixed with --split-col, else folds.")] = None,
    split_by: Annotated[str, typer.Option(
        help="What folds, holdouts and validation sets are made of: time (cuts of each scene's timeline; windows "
             "across a cut are dropped), scene (whole scenes, seeded), group (whole groups of identical inputs, "
             "seeded) or auto (time unless its cuts drop more than half of the windows, then scene).")] = "auto",
    folds: Annotated[int, typer.Option(help="Folds of --protocol folds.")] = 5,
    val_fraction: Annotated[float, typer.Option(
        help="Part validating: the end of each time block or timeline, or a seeded share of the units.")] = 0.2,
    test_fraction: Annotated[Optional[float], typer.Option(
        help="--protocol fixed without --split-col: the part held out for test (timelines' ends or units).")] = None,
    split_col: Annotated[Optional[str], typer.Option(
        help="Column holding train/val/test per row, read at each sample's t0 row (--protocol fixed).")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the scene / group assignment.")] = 0,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """Bring-your-own trajectories from a CSV or Parquet table."""
    from ..ingest.csv import ColumnMap
    from ..ingest.registry import get_ingest

    with user_errors(ctx):
        adapter = get_ingest("csv")
        result = adapter.run(file, out, dt=dt, columns=ColumnMap.parse(columns), n_past=past, n_future=future,
                             dataset=name, split_col=split_col, folds=folds, val_fraction=val_fraction,
                             protocol=protocol, split_by=split_by, test_fraction=test_fraction, seed=seed,
                             overwrite=overwrite, quiet=quiet)
        report_written(result, quiet, adapter.summary)


LevelxRaw = Annotated[Path, typer.Argument(help="Folder of levelX recordings (XX_tracks.csv, XX_tracksMeta.csv, "
                                                "XX_recordingMeta.csv and XX_background.png, highD: XX_highway.png; "
                                                "or its data/ sub-folder), or one file of the recording to read.")]
Recordings = Annotated[Optional[list[str]], typer.Option(
    "--recording", "-r", help="Recording number to read (e.g. 00); repeat for several. Default: all.")]
Classes = Annotated[Optional[str], typer.Option(
    help="--problems all-agents: the levelX classes predicted, e.g. car,truck (default: every class but trailer; "
         "exiD: motor vehicles).")]
Stride = Annotated[Optional[int], typer.Option(
    help="--problems all-agents: a sample every N frames of 0.2 s of each agent (default 5).")]

levelx_app = typer.Typer(help="The levelX drone datasets (rounD, highD, inD, exiD, uniD) through one reader: 15 past / "
                              "25 future steps at 0.2 s, 5 folds of whole episodes, the image as the map.",
                         no_args_is_help=True)
ingest_app.add_typer(levelx_app, name="levelx")


def _levelx(ctx: typer.Context, member: str, raw: Path, out: Path, quiet: bool, **options: object) -> None:
    """Run the levelX member's adapter with its options and print its line."""
    from ..ingest.registry import get_ingest

    with user_errors(ctx):
        adapter = get_ingest(member)
        report_written(adapter.run(raw, out, quiet=quiet, **options), quiet, adapter.summary)


def _round(ctx: typer.Context, raw: Path, out: Path, recording: Optional[list[str]], geometry: Optional[Path],
           problems: str, classes: Optional[str], stride: Optional[int], overwrite: bool, quiet: bool) -> None:
    """rounD, as `ingest round` and `ingest levelx round`."""
    from ..ingest.registry import get_ingest
    from ..ingest.round_geometry import load_geometry_file

    with user_errors(ctx):
        config = load_geometry_file(geometry) if geometry is not None else None
        adapter = get_ingest("round")
        result = adapter.run(raw, out, recordings=recording, geometry=config, problems=problems, classes=classes,
                             stride=stride, overwrite=overwrite, quiet=quiet)
        report_written(result, quiet, adapter.summary)


Geometry = Annotated[Optional[Path], typer.Option(
    help="JSON roundabout geometry: one object with centre (a list x, y), inner_radius, outer_radius, or an object "
         "mapping locationId to one. Default: inferred per recording from circulating traffic.")]
RoundProblems = Annotated[str, typer.Option(
    help="gap-acceptance (entering target + circulating ego, joint) or all-agents (every agent of --classes).")]


@ingest_app.command("round")
def ingest_round_command(
    ctx: typer.Context,
    raw: LevelxRaw,
    out: OutDir,
    recording: Recordings = None,
    geometry: Geometry = None,
    problems: RoundProblems = "gap-acceptance",
    classes: Classes = None,
    stride: Stride = None,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """rounD gap-acceptance scenarios: entering target + circulating ego, 15 past / 25 (up to 35) future steps at
    0.2 s, 5 folds, background maps (the same as `ingest levelx round`)."""
    _round(ctx, raw, out, recording, geometry, problems, classes, stride, overwrite, quiet)


@levelx_app.command("round")
def levelx_round_command(
    ctx: typer.Context,
    raw: LevelxRaw,
    out: OutDir,
    recording: Recordings = None,
    geometry: Geometry = None,
    problems: RoundProblems = "gap-acceptance",
    classes: Classes = None,
    stride: Stride = None,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """rounD: gap acceptance at the roundabouts (entering target + circulating ego, joint) or every agent."""
    _round(ctx, raw, out, recording, geometry, problems, classes, stride, overwrite, quiet)


@levelx_app.command("highd")
def levelx_highd_command(
    ctx: typer.Context,
    raw: LevelxRaw,
    out: OutDir,
    recording: Recordings = None,
    problems: Annotated[str, typer.Option(
        help="lane-change (the changing vehicle + the follower in the target lane, joint) or all-agents.")
                        ] = "lane-change",
    classes: Classes = None,
    stride: Stride = None,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """highD: lane changes into a gap (joint) or every vehicle; y up (the image's y flipped), centres of the boxes."""
    _levelx(ctx, "highd", raw, out, quiet, recordings=recording, problems=problems, classes=classes, stride=stride,
            overwrite=overwrite)


@levelx_app.command("ind")
def levelx_ind_command(
    ctx: typer.Context,
    raw: LevelxRaw,
    out: OutDir,
    recording: Recordings = None,
    problems: Annotated[str, typer.Option(
        help="gap-acceptance (a left-turning vehicle + an oncoming one it may cut off, joint) or all-agents.")
                        ] = "gap-acceptance",
    classes: Classes = None,
    stride: Stride = None,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """inD: gap acceptance at the intersections (joint) or every road user."""
    _levelx(ctx, "ind", raw, out, quiet, recordings=recording, problems=problems, classes=classes, stride=stride,
            overwrite=overwrite)


@levelx_app.command("exid")
def levelx_exid_command(
    ctx: typer.Context,
    raw: LevelxRaw,
    out: OutDir,
    recording: Recordings = None,
    problems: Annotated[str, typer.Option(help="all-agents (exiD has no scenario of its own).")] = "all-agents",
    classes: Classes = None,
    stride: Stride = None,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """exiD: every vehicle at the highway entries and exits (the lanelet2 maps are not read; the image is the map)."""
    _levelx(ctx, "exid", raw, out, quiet, recordings=recording, problems=problems, classes=classes, stride=stride,
            overwrite=overwrite)


@levelx_app.command("unid")
def levelx_unid_command(
    ctx: typer.Context,
    raw: LevelxRaw,
    out: OutDir,
    recording: Recordings = None,
    problems: Annotated[str, typer.Option(help="all-agents (uniD has no scenario of its own).")] = "all-agents",
    classes: Classes = None,
    stride: Stride = None,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """uniD: every road user of the campus (pedestrians, cyclists, vehicles)."""
    _levelx(ctx, "unid", raw, out, quiet, recordings=recording, problems=problems, classes=classes, stride=stride,
            overwrite=overwrite)


@ingest_app.command("nuscenes")
def ingest_nuscenes_command(
    ctx: typer.Context,
    dataroot: Annotated[Path, typer.Argument(help="nuScenes root holding the v1.0-*/ tables and maps/ "
                                                  "(maps/prediction/prediction_scenes.json, maps/expansion/).")],
    out: OutDir,
    version: Annotated[str, typer.Option("--version", help="Release folder: v1.0-mini or v1.0-trainval.")
                       ] = "v1.0-mini",
    all_agents: Annotated[bool, typer.Option(
        "--all-agents", help="Samples from every annotated agent with 4 past and 12 future keyframes instead of "
                             "the prediction-challenge entries (needed when prediction_scenes.json is absent).")
                          ] = False,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """nuScenes via nuscenes-devkit: prediction-challenge samples (4 past + 12 future at 0.5 s), ego vehicle, maps."""
    with user_errors(ctx):  # the devkit (slow, an optional extra) is imported only now; missing: one line
        from ..ingest.registry import get_ingest

        adapter = get_ingest("nuscenes")
        result = adapter.run(dataroot, out, version=version, all_agents=all_agents, overwrite=overwrite, quiet=quiet)
        report_written(result, quiet, adapter.summary)


@ingest_app.command("forking-paths")
def ingest_forking_paths_command(
    ctx: typer.Context,
    raw: Annotated[Path, typer.Argument(help="The Forking Paths release root, its next_x_v1_dataset/ folder or "
                                             "the bbox/ folder of <scene>_<moment>_<xagent>_<dest>_<annotator>_<cam>"
                                             ".json files.")],
    out: OutDir,
    camera: Annotated[str, typer.Option(help="Camera whose files are read (cam4 is the top-down view).")] = "cam4",
    fps: Annotated[Optional[str], typer.Option(
        help="Frame rate: one number for all scenes or scene=fps pairs (default 25 for zara/eth/hotel, 30 "
             "otherwise).")] = None,
    scale: Annotated[Optional[str], typer.Option(
        help="Metres per pixel: one number or scene=value pairs (defaults exist for cam4, derived from the "
             "release's camera set-up).")] = None,
    folds: Annotated[int, typer.Option(help="Cross-validation folds (whole groups per fold).")] = 5,
    seed: Annotated[int, typer.Option(help="Seed of the fold and train/val assignment.")] = 0,
    overwrite: Overwrite = False,
    quiet: Quiet = False,
) -> None:
    """Forking Paths: several annotated futures per past, 8 past + 12 future steps at 0.4 s, 5-fold CV."""
    from ..ingest.registry import get_ingest

    with user_errors(ctx):
        adapter = get_ingest("forking-paths")
        result = adapter.run(raw, out, camera=camera, fps=parse_per_scene("--fps", fps),
                             scale=parse_per_scene("--scale", scale), folds=folds, seed=seed, overwrite=overwrite,
                             quiet=quiet)
        report_written(result, quiet, adapter.summary)


def parse_per_scene(option: str, text: Optional[str]) -> float | dict[str, float] | None:
    """`30` (every scene) or `zara01=25,0400=30` (per scene; others keep their default) -> float, dict or None."""
    if text is None or not text.strip():
        return None
    try:
        if "=" not in text:
            return float(text)
        values: dict[str, float] = {}
        for item in text.split(","):
            scene, sep, value = item.partition("=")
            if not sep or not scene.strip():
                raise ValueError(item)
            values[scene.strip()] = float(value)
        return values
    except ValueError:
        raise UsageError(f"{option}: expected a number or scene=number pairs separated by commas, got {text!r}") \
            from None
