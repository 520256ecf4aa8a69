"""`trajflow ingest nuscenes`: the nuScenes release, read only through nuscenes-devkit, as a unified Parquet dataset:
prediction-challenge samples (or every agent), 4 past + 12 future keyframes at 0.5 s, the ego vehicle, one map
per scene. The conventions (frames, agents, types, splits, short pasts): docs/datasets/nuscenes.md.
"""

from __future__ import annotations

import gc
import json
import re
import warnings
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
from rich.text import Text

from ..errors import DataError, TrajflowError, UsageError
from ..schemas import PROTOCOL_FIXED, DatasetMeta, DatasetWriter
from ..util.progress import make_progress, styled
from . import nuscenes_maps
from .base import Ingest, warn
from .windows import complete_windows, identical_input_groups

DATASET = "nuscenes"
DT = 0.5
N_PAST, N_FUTURE = 4, 12
MICROSECONDS = 1_000_000

#: the ego vehicle's agent_id in every scene (annotated instances get 1 + their index in instance.json)
EGO_AGENT_ID = 0
EGO_INSTANCE_TOKEN = "ego"
EGO_CATEGORY = "vehicle.ego"
#: the nuScenes data-collection car (Renault Zoe): box length and width in metres
EGO_LENGTH_M, EGO_WIDTH_M = 4.084, 1.730
#: the sensor whose keyframe ego pose positions the ego vehicle
EGO_CHANNEL = "LIDAR_TOP"

#: the 13 tables of a release, all required by the devkit
TABLES = ("attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map", "sample",
          "sample_annotation", "sample_data", "scene", "sensor", "visibility")

#: per release version: prediction-challenge split -> dataset split (protocol `fixed`)
VERSION_SPLITS: dict[str, dict[str, str]] = {
    "v1.0-mini": {"mini_train": "train", "mini_val": "test"},
    "v1.0-trainval": {"train": "train", "train_val": "val", "val": "test"},
}

#: category prefixes that are scenery, not agents
SKIPPED_CATEGORY_PREFIXES = ("movable_object.", "static_object.")

#: column order of the tracks this ingest writes (contract columns first, then nuScenes extras)
TRACK_COLUMNS = ("scene_id", "agent_id", "agent_type", "frame", "t", "x", "y", "heading", "length", "width", "z",
                 "instance_token", "category", "timestamp_us", "padded")

#: per-scene sample columns before numbering
SAMPLE_SCHEMA = {"scene_id": pl.String, "agent_id": pl.Int64, "t0_frame": pl.Int64, "instance_token": pl.String,
                 "sample_token": pl.String, "challenge_split": pl.String, "past_available": pl.Int64}

INSTALL_HINT = ("install the nuScenes extra: pip install -e '.[nuscenes]' "
                "(or: pip install nuscenes-devkit 'numpy<2' 'opencv-python-headless<4.12')")

__all__ = ["DATASET", "DT", "EGO_AGENT_ID", "N_FUTURE", "N_PAST", "VERSION_SPLITS",
           "agent_type_of", "ingest_nuscenes", "quaternion_yaw"]


@dataclass(frozen=True)
class Devkit:
    """The parts of nuscenes-devkit the ingest uses, imported once."""

    NuScenes: Any
    PredictHelper: Any
    NuScenesMap: Any
    challenge_split: Callable[..., list[str]]
    scene_lists: dict[str, list[str]]
    num_in_train_val: int
    version: str


def load_devkit() -> Devkit:
    """Import nuscenes-devkit, or say in one line how to install it.

    The devkit's map module switches matplotlib's global style when imported; the import runs inside an
    ``rc_context`` so that figures made later by trajflow keep their look.
    """
    import importlib.metadata

    import matplotlib

    try:
        with matplotlib.rc_context():
            from nuscenes import NuScenes
            from nuscenes.eval.prediction import splits as prediction_splits
            from nuscenes.map_expansion.map_api import NuScenesMap
            from nuscenes.prediction import PredictHelper
            from nuscenes.utils.splits import create_splits_scenes
    except ImportError as error:
        raise TrajflowError(f"nuscenes-devkit is not available ({error}); {INSTALL_HINT}") from None
    return Devkit(NuScenes=NuScenes, PredictHelper=PredictHelper, NuScenesMap=NuScenesMap,
                  challenge_split=prediction_splits.get_prediction_challenge_split,
                  scene_lists=create_splits_scenes(), num_in_train_val=prediction_splits.NUM_IN_TRAIN_VAL,
                  version=importlib.metadata.version("nuscenes-devkit"))


def agent_type_of(category: str) -> str | None:
    """The contract's agent type of a nuScenes category name, or None for scenery that is skipped."""
    if category == "vehicle.bicycle":
        return "bicycle"
    if category == "vehicle.motorcycle":
        return "motorcycle"
    if category.startswith("vehicle."):
        return "vehicle"
    if category.startswith("human.pedestrian."):
        return "pedestrian"
    if category.startswith(SKIPPED_CATEGORY_PREFIXES):
        return None
    return "unknown"


def quaternion_yaw(rotation: np.ndarray) -> np.ndarray:
    """Yaw (rad) of (N, 4) [w, x, y, z] quaternions: the angle of the rotated x axis in the xy plane.

    Vectorised equivalent of the devkit's ``quaternion_yaw`` (which normalises the quaternion first).
    """
    w, x, y, z = (rotation[:, i] for i in range(4))
    norm2 = w * w + x * x + y * y + z * z
    return np.arctan2(2.0 * (x * y + w * z) / norm2, 1.0 - 2.0 * (y * y + z * z) / norm2)


def prediction_scenes_path(dataroot: Path) -> Path:
    """Where the prediction challenge's scene -> entries file lives in an official release."""
    return dataroot / "maps" / "prediction" / "prediction_scenes.json"


def check_release(dataroot: Path, version: str, *, all_agents: bool) -> None:
    """Fail fast, naming the path, on what the devkit would only report with an assertion or a traceback."""
    if version not in VERSION_SPLITS:
        raise UsageError(f"--version {version!r} is not supported; choose one of {', '.join(VERSION_SPLITS)} "
                         "(the prediction challenge is defined on these)")
    if not dataroot.is_dir():
        raise DataError("nuScenes dataroot not found (expected a folder holding v1.0-*/ and maps/)", path=dataroot)
    table_root = dataroot / version
    if not table_root.is_dir():
        found = sorted(p.name for p in dataroot.glob("v1.0-*") if p.is_dir())
        hint = f"found {', '.join(found)}; choose it with --version" if found else "no v1.0-* folder here"
        raise DataError(f"version folder '{version}' not found ({hint})", path=table_root)
    for table in TABLES:
        if not (table_root / f"{table}.json").is_file():
            raise DataError(f"table '{table}' is missing (a nuScenes release has the 13 tables "
                            f"{', '.join(TABLES)})", path=table_root / f"{table}.json")
    if not all_agents and not prediction_scenes_path(dataroot).is_file():
        raise DataError(f"prediction_scenes.json not found, so the prediction-challenge samples cannot be defined; "
                        f"add it from the nuScenes map expansion or pass --all-agents to make samples from every "
                        f"agent with {N_PAST} past and {N_FUTURE} future keyframes",
                        path=prediction_scenes_path(dataroot))


def open_release(devkit: Devkit, dataroot: Path, version: str) -> Any:
    """Load the release with the devkit's ``NuScenes``, translating its assertions into errors naming paths."""
    table_root = dataroot / version

    class _NuScenes(devkit.NuScenes):  # type: ignore[misc, name-defined]
        """NuScenes whose table loading names the file that fails."""

        def __load_table__(self, table_name: str) -> Any:
            path = table_root / f"{table_name}.json"
            try:
                return super().__load_table__(table_name)
            except json.JSONDecodeError as error:
                raise DataError(f"table is not valid JSON ({error})", path=path) from None
            except (OSError, UnicodeDecodeError) as error:
                raise DataError(f"table cannot be read ({error})", path=path) from None

    try:
        return _NuScenes(version=version, dataroot=str(dataroot), verbose=False)
    except AssertionError as error:
        missing_mask = re.fullmatch(r"map mask (.+) does not exist", str(error))
        if missing_mask:
            raise DataError(f"semantic map named by {version}/map.json does not exist (the release's maps/*.png "
                            "belong in DATAROOT/maps/)", path=missing_mask.group(1)) from None
        raise DataError(f"nuscenes-devkit cannot load the release: {error}", path=table_root) from None
    except KeyError as error:
        raise DataError(f"tables are inconsistent: a record refers to token or field {error} that does not exist",
                        path=table_root) from None
    except (TypeError, IndexError, AttributeError, ValueError) as error:
        raise DataError(f"unexpected table content ({type(error).__name__}: {error})", path=table_root) from None


@dataclass(frozen=True)
class Target:
    """One prediction-challenge entry: the instance to predict at a sample, and the challenge split."""

    instance_token: str
    sample_token: str
    challenge_split: str


def challenge_targets(devkit: Devkit, nusc: Any, dataroot: Path, version: str) -> dict[str, list[Target]]:
    """The entries of every challenge split of `version`, grouped by scene token."""
    path = prediction_scenes_path(dataroot)
    by_scene: dict[str, list[Target]] = defaultdict(list)
    for split in VERSION_SPLITS[version]:
        try:
            with warnings.catch_warnings():  # the devkit leaves the file to the garbage collector
                warnings.simplefilter("ignore", ResourceWarning)
                entries = devkit.challenge_split(split, dataroot=str(dataroot))
        except json.JSONDecodeError as error:
            raise DataError(f"not valid JSON ({error})", path=path) from None
        except (AttributeError, TypeError) as error:
            raise DataError(f"expected an object mapping scene names to lists of '<instance_token>_<sample_token>' "
                            f"strings ({error})", path=path) from None
        for entry in entries:
            instance, sep, sample = str(entry).partition("_")
            if not sep:
                raise DataError(f"entry {entry!r} is not '<instance_token>_<sample_token>'", path=path)
            try:
                scene_token = nusc.get("sample", sample)["scene_token"]
                nusc.get("instance", instance)
            except KeyError:
                raise DataError(f"entry {entry!r} names a sample or instance that is not in {version}",
                                path=path) from None
            by_scene[scene_token].append(Target(instance, sample, split))
    return by_scene


def scene_challenge_splits(devkit: Devkit, version: str) -> dict[str, str]:
    """Scene name -> the challenge split its scene list puts it in (as ``get_prediction_challenge_split`` does)."""
    lists = devkit.scene_lists
    if version == "v1.0-mini":
        return {**{name: "mini_train" for name in lists["mini_train"]},
                **{name: "mini_val" for name in lists["mini_val"]}}
    cut = devkit.num_in_train_val
    return {**{name: "train_val" for name in lists["train"][:cut]},
            **{name: "train" for name in lists["train"][cut:]},
            **{name: "val" for name in lists["val"]}}


@dataclass
class Keyframes:
    """A scene's keyframes in order: sample tokens, microsecond timestamps, and token -> frame."""

    tokens: list[str]
    timestamps: np.ndarray

    @property
    def frame_of(self) -> dict[str, int]:
        return {token: frame for frame, token in enumerate(self.tokens)}

    def times(self) -> pl.DataFrame:
        """frame, t (s since the first keyframe), timestamp_us and sample_token of every keyframe."""
        return pl.DataFrame({"frame": np.arange(len(self.tokens), dtype=np.int64),
                             "t": (self.timestamps - self.timestamps[0]) / MICROSECONDS,
                             "timestamp_us": self.timestamps, "sample_token": self.tokens})


def scene_keyframes(nusc: Any, scene: dict, table_root: Path) -> Keyframes:
    """Follow the scene's sample chain from first_sample_token (the devkit's own order of keyframes)."""
    tokens, stamps = [], []
    token = scene["first_sample_token"]
    while token:
        if len(tokens) > len(nusc.sample):
            raise DataError(f"the sample chain of scene '{scene['name']}' loops", path=table_root / "sample.json")
        try:
            sample = nusc.get("sample", token)
        except KeyError:
            raise DataError(f"scene '{scene['name']}' refers to sample {token} that does not exist",
                            path=table_root / "sample.json") from None
        tokens.append(token)
        stamps.append(sample["timestamp"])
        token = sample["next"]
    if not tokens:
        raise DataError(f"scene '{scene['name']}' has no samples (empty first_sample_token)",
                        path=table_root / "scene.json")
    return Keyframes(tokens=tokens, timestamps=np.asarray(stamps, dtype=np.int64))


def _ego_pose(nusc: Any, sample: dict) -> dict | None:
    """The ego pose of a keyframe: from its LIDAR_TOP sample_data, else from its first channel by name."""
    data = sample.get("data", {})
    channel = EGO_CHANNEL if EGO_CHANNEL in data else min(data, default=None)
    if channel is None:
        return None
    return nusc.get("ego_pose", nusc.get("sample_data", data[channel])["ego_pose_token"])


def scene_tracks(nusc: Any, scene_id: str, keyframes: Keyframes, table_root: Path) -> pl.DataFrame:
    """Tracks rows of one scene: the ego vehicle and every annotated agent at every keyframe, sorted."""
    instances: list[str] = []
    categories: list[str] = []
    frames: list[int] = []
    translations: list[list[float]] = []
    sizes: list[list[float]] = []
    rotations: list[list[float]] = []
    for frame, sample_token in enumerate(keyframes.tokens):
        sample = nusc.get("sample", sample_token)
        pose = _ego_pose(nusc, sample)
        if pose is not None:
            instances.append(EGO_INSTANCE_TOKEN)
            categories.append(EGO_CATEGORY)
            frames.append(frame)
            translations.append(pose["translation"])
            sizes.append([EGO_WIDTH_M, EGO_LENGTH_M, np.nan])  # [width, length, height]; height is not kept
            rotations.append(pose["rotation"])
        for annotation_token in sample["anns"]:
            annotation = nusc.get("sample_annotation", annotation_token)
            if agent_type_of(annotation["category_name"]) is None:
                continue
            instances.append(annotation["instance_token"])
            categories.append(annotation["category_name"])
            frames.append(frame)
            translations.append(annotation["translation"])
            sizes.append(annotation["size"])
            rotations.append(annotation["rotation"])
    translation = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    size = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    heading = quaternion_yaw(np.asarray(rotations, dtype=np.float64).reshape(-1, 4))
    agent_ids = [EGO_AGENT_ID if token == EGO_INSTANCE_TOKEN else nusc.getind("instance", token) + 1
                 for token in instances]
    times = keyframes.times()
    tracks = (pl.DataFrame({
        "scene_id": pl.Series([scene_id] * len(frames), dtype=pl.String),
        "agent_id": pl.Series(agent_ids, dtype=pl.Int64),
        "agent_type": pl.Series([agent_type_of(c) or "unknown" for c in categories], dtype=pl.String),
        "frame": pl.Series(frames, dtype=pl.Int64),
        "x": translation[:, 0], "y": translation[:, 1], "heading": heading,
        "length": size[:, 1], "width": size[:, 0], "z": translation[:, 2],
        "instance_token": pl.Series(instances, dtype=pl.String),
        "category": pl.Series(categories, dtype=pl.String),
    }).with_columns(pl.when(pl.col("instance_token") == EGO_INSTANCE_TOKEN).then(pl.lit("vehicle"))
                    .otherwise(pl.col("agent_type")).alias("agent_type"))
        .join(times.select("frame", "t", "timestamp_us"), on="frame", how="left")
        .with_columns(padded=pl.lit(False))
        .sort("agent_id", "frame"))
    duplicated = tracks.filter(pl.struct("agent_id", "frame").is_duplicated())
    if duplicated.height:
        first = duplicated.row(0, named=True)
        raise DataError(f"instance {first['instance_token']} is annotated twice in sample "
                        f"{keyframes.tokens[first['frame']]} of scene '{scene_id}'",
                        path=table_root / "sample_annotation.json")
    return tracks.select(TRACK_COLUMNS)


def challenge_samples(helper: Any, scene_id: str, targets: list[Target], keyframes: Keyframes,
                      tracks: pl.DataFrame, dropped: Counter, path: Path) -> pl.DataFrame:
    """The samples of one scene's challenge entries, with the number of past positions the devkit returns.

    Entries whose devkit future is not 12 consecutive keyframes, or whose instance is of a skipped category, are
    dropped and counted in `dropped`.
    """
    frame_of = keyframes.frame_of
    agent_of = dict(tracks.filter(pl.col("agent_id") != EGO_AGENT_ID)
                    .select("instance_token", "agent_id").unique().iter_rows())
    rows = []
    for target in targets:
        t0 = frame_of[target.sample_token]
        try:
            past = helper.get_past_for_agent(target.instance_token, target.sample_token, (N_PAST - 1) * DT,
                                             in_agent_frame=False, just_xy=False)
            future = helper.get_future_for_agent(target.instance_token, target.sample_token, N_FUTURE * DT,
                                                 in_agent_frame=False, just_xy=False)
        except KeyError:
            raise DataError(f"entry '{target.instance_token}_{target.sample_token}': the instance is not annotated "
                            "in that sample", path=path) from None
        if [frame_of.get(record["sample_token"]) for record in future] != list(range(t0 + 1, t0 + N_FUTURE + 1)):
            dropped[f"with a future shorter than {N_FUTURE} keyframes"] += 1
            continue
        if target.instance_token not in agent_of:
            dropped["of a category that is not an agent"] += 1
            continue
        past_frames = {frame_of.get(record["sample_token"], -1) for record in past}
        rows.append({"scene_id": scene_id, "agent_id": agent_of[target.instance_token], "t0_frame": t0,
                     "instance_token": target.instance_token, "sample_token": target.sample_token,
                     "challenge_split": target.challenge_split,
                     "past_available": 1 + sum(1 for f in past_frames if t0 - N_PAST < f < t0)})
    return pl.DataFrame(rows, schema=SAMPLE_SCHEMA)


def every_agent_samples(scene_id: str, tracks: pl.DataFrame, keyframes: Keyframes,
                        challenge_split: str | None) -> pl.DataFrame:
    """--all-agents: every annotated agent at every keyframe with 4 past and 12 future keyframes."""
    real = tracks.filter(~pl.col("padded") & (pl.col("agent_id") != EGO_AGENT_ID))
    windows = complete_windows(real, N_PAST, N_FUTURE)
    tokens = real.select("agent_id", "instance_token").unique()
    return (windows.join(tokens, on="agent_id", how="left")
            .join(keyframes.times().select(pl.col("frame").alias("t0_frame"), "sample_token"), on="t0_frame",
                  how="left")
            .select(pl.lit(scene_id).alias("scene_id"), "agent_id", "t0_frame", "instance_token", "sample_token",
                    pl.lit(challenge_split, dtype=pl.String).alias("challenge_split"),
                    pl.lit(N_PAST, dtype=pl.Int64).alias("past_available"))
            .cast(SAMPLE_SCHEMA))


def pad_short_pasts(tracks: pl.DataFrame, samples: pl.DataFrame, keyframes: Keyframes) -> pl.DataFrame:
    """Add `padded` rows for the past frames of sample targets that have no annotation there.

    Each missing frame repeats the agent's next real row (position, heading, size), so a past that starts late
    repeats its first position; `t` is the keyframe's time, or frame × dt before the scene's first keyframe.
    """
    wanted = (samples.filter(pl.col("past_available") < N_PAST)
              .select("agent_id", pl.int_ranges(pl.col("t0_frame") - (N_PAST - 1), pl.col("t0_frame") + 1)
                      .alias("frame"))
              .explode("frame").unique())
    missing = wanted.join(tracks.select("agent_id", "frame"), on=["agent_id", "frame"], how="anti")
    if missing.height == 0:
        return tracks
    real = tracks.drop("t", "timestamp_us", "padded").rename({"frame": "source_frame"})
    filled = (missing.join(real, on="agent_id", how="inner")
              .filter(pl.col("source_frame") > pl.col("frame"))
              .sort("agent_id", "frame", "source_frame")
              .unique(["agent_id", "frame"], keep="first", maintain_order=True)
              .drop("source_frame")
              .join(keyframes.times().select("frame", "t", "timestamp_us"), on="frame", how="left")
              .with_columns(pl.col("t").fill_null(pl.col("frame").cast(pl.Float64) * DT), padded=pl.lit(True)))
    return pl.concat([tracks, filled.select(TRACK_COLUMNS)]).sort("agent_id", "frame")


def _scene_bounds(tracks: pl.DataFrame) -> tuple[float, float, float, float]:
    """x_min, y_min, x_max, y_max of every position of the scene (the map raster covers them)."""
    row = tracks.select(pl.col("x").min().alias("x0"), pl.col("y").min().alias("y0"), pl.col("x").max().alias("x1"),
                        pl.col("y").max().alias("y1")).row(0)
    return float(row[0]), float(row[1]), float(row[2]), float(row[3])


def _number_samples(parts: list[pl.DataFrame], tracks: pl.DataFrame, mapping: dict[str, str]) -> pl.DataFrame:
    """One samples table: ids in (scene, t0, agent) order, splits mapped, joint and identical-input groups."""
    samples = (pl.concat(parts) if parts else pl.DataFrame(schema=SAMPLE_SCHEMA))
    samples = (samples.unique(["scene_id", "agent_id", "t0_frame"], keep="first", maintain_order=True)
               .sort("scene_id", "t0_frame", "agent_id")
               .with_row_index("sample_id")
               .select(pl.col("sample_id").cast(pl.Int64), "scene_id", "agent_id", "t0_frame",
                       pl.lit(N_PAST, dtype=pl.Int64).alias("n_past"),
                       pl.lit(N_FUTURE, dtype=pl.Int64).alias("n_future"),
                       pl.col("challenge_split").replace_strict(mapping, default=None, return_dtype=pl.String)
                       .alias("split"),
                       pl.lit(None, dtype=pl.String).alias("fold"),
                       pl.struct("scene_id", "t0_frame").rank("dense").cast(pl.Int64).sub(1).alias("joint_id"),
                       "challenge_split", "instance_token", "sample_token", "past_available"))
    if samples.height == 0:
        return samples.with_columns(group_id=pl.lit(0, dtype=pl.Int64))
    return samples.with_columns(group_id=identical_input_groups(samples, tracks))


def ingest_nuscenes(dataroot: str | Path, out: str | Path, *, version: str = "v1.0-mini", all_agents: bool = False,
                    overwrite: bool = False, quiet: bool = False) -> Path:
    """Ingest the nuScenes release at `dataroot` (``<version>/`` tables, ``maps/``) into `out`; returns `out`.

    Samples are the prediction-challenge entries (``all_agents``: every agent with 4 past and 12 future
    keyframes); maps are rasterised when the map expansion is present. The dataset is written to a temporary
    directory and moved into place only when complete.
    """
    dataroot, out = Path(dataroot), Path(out)
    check_release(dataroot, version, all_agents=all_agents)
    devkit = load_devkit()
    writer = DatasetWriter(out, DatasetMeta(dataset=DATASET, dt=DT, protocol=PROTOCOL_FIXED), overwrite=overwrite)
    mapping = VERSION_SPLITS[version]
    with make_progress(quiet) as progress:
        loading = progress.add_task(f"loading {version} with nuscenes-devkit", total=None)
        nusc = open_release(devkit, dataroot, version)
        targets = {} if all_agents else challenge_targets(devkit, nusc, dataroot, version)
        helper = None if all_agents else devkit.PredictHelper(nusc)
        progress.update(loading, total=1, completed=1)
        scene_splits = scene_challenge_splits(devkit, version)
        scenes = sorted(nusc.scene, key=lambda record: record["name"])
        if len({scene["name"] for scene in scenes}) != len(scenes):
            raise DataError("scene names are not unique", path=dataroot / version / "scene.json")
        dropped: Counter = Counter()
        scene_rows, sample_parts, slim_parts = [], [], []
        bounds: dict[str, tuple[float, float, float, float]] = {}
        with writer:
            task = progress.add_task("reading nuScenes scenes", total=len(scenes))
            for scene in scenes:
                scene_id = scene["name"]
                keyframes = scene_keyframes(nusc, scene, dataroot / version)
                tracks = scene_tracks(nusc, scene_id, keyframes, dataroot / version)
                if all_agents:
                    samples = every_agent_samples(scene_id, tracks, keyframes, scene_splits.get(scene_id))
                else:
                    samples = challenge_samples(helper, scene_id, targets.get(scene["token"], []), keyframes,
                                                tracks, dropped, prediction_scenes_path(dataroot))
                    tracks = pad_short_pasts(tracks, samples, keyframes)
                writer.add_tracks(tracks)
                sample_parts.append(samples)
                slim_parts.append(tracks.select("scene_id", "agent_id", "agent_type", "frame", "x", "y"))
                bounds[scene_id] = _scene_bounds(tracks)
                log = nusc.get("log", scene["log_token"])
                scene_rows.append(_scene_row(scene, log["location"], version, len(keyframes.tokens),
                                             scene_splits.get(scene_id), mapping))
                progress.advance(task)
            # the devkit's tables (GBs for trainval; NuScenes <-> explorer is a reference cycle) are not needed
            # for the maps: free them before a map expansion is loaded, so the two peaks never add up
            del nusc, helper, targets
            gc.collect()
            locations = {row["scene_id"]: row["location"] for row in scene_rows}
            maps = nuscenes_maps.rasterise_scene_maps(devkit.NuScenesMap, dataroot, locations, bounds,
                                                      writer.root, progress)
            if dropped:
                reasons = ", ".join(f"{count} {why}" for why, count in dropped.items())
                warn(f"{prediction_scenes_path(dataroot)}: dropped {sum(dropped.values())} prediction-challenge "
                     f"entr{'y' if sum(dropped.values()) == 1 else 'ies'} ({reasons})")
            samples = _number_samples(sample_parts, pl.concat(slim_parts), mapping)
            if samples.height == 0:
                source = "every agent's windows" if all_agents else str(prediction_scenes_path(dataroot))
                raise TrajflowError(f"{dataroot}: no samples ({source} gave no agent with {N_PAST} past and "
                                    f"{N_FUTURE} future keyframes)")
            scenes_table = _scenes_table(scene_rows, maps)
            writer.finish(scenes_table, samples, lineage=_lineage(dataroot, version, devkit, all_agents, mapping,
                                                                  dropped, bool(maps)))
    return out


def _scene_row(scene: dict, location: str, version: str, n_keyframes: int, challenge_split: str | None,
               mapping: dict[str, str]) -> dict[str, Any]:
    """The scenes-table row of one scene (map columns are added once the maps are rasterised)."""
    return {"dataset": DATASET, "scene_id": scene["name"], "location": location, "dt": DT,
            "source": f"{version}/scene.json#{scene['token']}", "fold": None,
            "split": mapping.get(challenge_split or ""), "challenge_split": challenge_split,
            "scene_token": scene["token"], "description": scene.get("description", ""), "keyframes": n_keyframes}


def _scenes_table(rows: list[dict[str, Any]], maps: dict[str, nuscenes_maps.MapRef]) -> pl.DataFrame:
    """The scenes table with map columns (null for scenes without a map)."""
    for row in rows:
        ref = maps.get(row["scene_id"])
        row["map_path"] = ref.path if ref else None
        row["map_m_per_px"] = ref.m_per_px if ref else None
        row["map_world_to_px"] = ref.world_to_px if ref else None
    return pl.DataFrame(rows, schema_overrides={
        "fold": pl.String, "split": pl.String, "challenge_split": pl.String, "keyframes": pl.Int64,
        "map_path": pl.String, "map_m_per_px": pl.Float64, "map_world_to_px": pl.List(pl.Float64)})


def _lineage(dataroot: Path, version: str, devkit: Devkit, all_agents: bool, mapping: dict[str, str],
             dropped: Counter, has_maps: bool) -> dict[str, Any]:
    """What the manifest records about how the dataset was made."""
    return {
        "raw": str(dataroot.resolve()), "version": version, "nuscenes_devkit": devkit.version,
        "samples": "all-agents" if all_agents else "prediction-challenge", "split_mapping": mapping,
        "n_past": N_PAST, "n_future": N_FUTURE, "ego_agent_id": EGO_AGENT_ID,
        "dropped_challenge_entries": dict(dropped),
        "skipped_categories": [f"{prefix}*" for prefix in SKIPPED_CATEGORY_PREFIXES],
        "maps": ({"m_per_px": nuscenes_maps.M_PER_PX, "margin_m": nuscenes_maps.MARGIN_M,
                  "grey_levels": nuscenes_maps.GREY_LEVELS} if has_maps else None),
    }


def wrote_line(out: Path, summary: dict[str, Any]) -> Text:
    """The line after the ingest: scenes, rows, samples per split, groups and whether there are maps."""
    splits = ", ".join(f"{row['split']} {row['samples']}" for row in summary["samples_by_fold_and_split"])
    maps = "with maps" if summary["has_map"] else "no maps"
    return styled(("wrote", "green"), f" {out}: {summary['scenes']} scenes, {summary['track_rows']} track rows, "
                  f"{summary['samples']} samples ({splits}), {summary['groups']} groups, {maps}")


def read_files(dataroot: Path, options: dict[str, Any]) -> list[Path]:
    """The files an ingest of `dataroot` reads: the version's tables and maps/ (not the sensor data: samples/,
    sweeps/, which are most of a release's bytes)."""
    version = options.get("version", "v1.0-mini")
    return sorted(p for folder in (dataroot / version, dataroot / "maps") if folder.is_dir()
                  for p in folder.rglob("*") if p.is_file())


ADAPTER = Ingest(name="nuscenes", dataset=DATASET, dt=DT, folds=None, raw="the nuScenes root (DATAROOT)",
                 function=ingest_nuscenes, summary=wrote_line, inputs=read_files)
