"""Synthetic levelX recordings of every member, written in that member's exact files and columns (the data are
licensed and absent): the drone layout of rounD / inD / exiD / uniD (exiD with its lane columns, semicolon lists
included) and highD's (id, bounding box with y down the image, neighbours and lanes per row, lane markings,
XX_highway.png). The road users come from test_round_synth's `drive` (paths at 25 Hz).

Scripted recordings the tests reason about:

* :func:`highway_scenario` (highD): ``LC_TARGET`` changes from lower lane 6 to 7 in front of ``LC_FOLLOWER``
  (behind it in lane 7) and behind ``LC_LEADER``; on the upper lanes ``UP_TARGET`` changes from lane 3 to 2 in
  front of ``UP_FOLLOWER``; ``LONE_CHANGER`` changes into an empty lane (no follower: no pair). Two pairs.
* :func:`intersection_scenario` (inD): ``TURNER`` comes from the west and turns left; ``ONCOMING_FIRST`` passes
  before it (a rejected gap: the turner waits at the stop line), ``ONCOMING_AFTER`` after it (the accepted gap);
  a car crossing from the south, a right-turner, pedestrians and a cyclist form no pair. Two pairs.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import polars as pl
from PIL import Image
from test_round_synth import SIZES as ROUND_SIZES
from test_round_synth import CENTRE, FRAME_RATE, ORTHO_PX_TO_METER, Track, _hermite, background, drive, gap_scenario

#: exiD adds lane-level columns to the drone layout's tracks (semicolon lists where a vehicle spans lanelets)
EXID_EXTRA_TRACKS_COLUMNS = ("traveledDistance", "latLaneCenterOffset", "laneWidth", "laneletId", "laneChange",
                             "lonLaneletPos", "laneletLength", "leadId", "rearId", "leftLeadId", "leftRearId",
                             "leftAlongsideId", "rightLeadId", "rightRearId", "rightAlongsideId", "odrRoadId",
                             "odrSectionNo", "odrLaneId")
HIGHD_TRACKS_COLUMNS = ("frame", "id", "x", "y", "width", "height", "xVelocity", "yVelocity", "xAcceleration",
                        "yAcceleration", "frontSightDistance", "backSightDistance", "dhw", "thw", "ttc",
                        "precedingXVelocity", "precedingId", "followingId", "leftPrecedingId", "leftAlongsideId",
                        "leftFollowingId", "rightPrecedingId", "rightAlongsideId", "rightFollowingId", "laneId")
HIGHD_TRACKS_META_COLUMNS = ("id", "width", "height", "initialFrame", "finalFrame", "numFrames", "class",
                             "drivingDirection", "traveledDistance", "minXVelocity", "maxXVelocity", "meanXVelocity",
                             "minDHW", "minTHW", "minTTC", "numLaneChanges")
HIGHD_RECORDING_META_COLUMNS = ("id", "frameRate", "locationId", "speedLimit", "month", "weekDay", "startTime",
                                "duration", "totalDrivenDistance", "totalDrivenTime", "numVehicles", "numCars",
                                "numTrucks", "upperLaneMarkings", "lowerLaneMarkings")
#: (width, length) of each class (inD and uniD have truck_bus)
SIZES = {**ROUND_SIZES, "truck_bus": (2.5, 10.0)}
#: the image scale-down factor of each drone member (levelX tools, lxd-io)
SCALE_DOWN = {"round": 10, "ind": 12, "exid": 6, "unid": 2}

# ------------------------------------------------------------------------------------------------ drone layout


def write_drone_recording(folder: Path, recording_id: int, tracks: list[Track], *, member: str = "round",
                          location_id: int = 1, image: np.ndarray | None = None, frame_rate: int = FRAME_RATE,
                          ortho_px_to_meter: float = ORTHO_PX_TO_METER) -> Path:
    """Write XX_recordingMeta.csv, XX_tracksMeta.csv, XX_tracks.csv and XX_background.png of a drone member."""
    folder.mkdir(parents=True, exist_ok=True)
    prefix = folder / f"{recording_id:02d}"
    rows = []
    for track in tracks:
        n = len(track.positions)
        width, length = SIZES[track.cls]
        acceleration = np.gradient(track.velocities, axis=0) * frame_rate if n > 1 else np.zeros((n, 2))
        speed = np.linalg.norm(track.velocities, axis=1)
        columns = {
            "recordingId": np.full(n, recording_id), "trackId": np.full(n, track.track_id),
            "frame": track.initial_frame + np.arange(n), "trackLifetime": np.arange(n),
            "xCenter": track.positions[:, 0], "yCenter": track.positions[:, 1], "heading": track.heading,
            "width": np.full(n, width), "length": np.full(n, length), "xVelocity": track.velocities[:, 0],
            "yVelocity": track.velocities[:, 1], "xAcceleration": acceleration[:, 0],
            "yAcceleration": acceleration[:, 1], "lonVelocity": speed, "latVelocity": np.zeros(n),
            "lonAcceleration": np.zeros(n), "latAcceleration": np.zeros(n)}
        if member == "exid":
            travelled = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(track.positions, axis=0), axis=1))))
            lanelet = np.where(np.arange(n) % 50 == 0, "1404;1405", "1404")
            columns |= {"traveledDistance": travelled, "latLaneCenterOffset": np.where(lanelet == "1404", "0.12",
                                                                                       "0.12;-3.6"),
                        "laneWidth": np.where(lanelet == "1404", "3.75", "3.75;3.75"), "laneletId": lanelet,
                        "laneChange": np.zeros(n, dtype=np.int64),
                        "lonLaneletPos": np.where(lanelet == "1404", "12.5", "12.5;0.4"),
                        "laneletLength": np.where(lanelet == "1404", "80.2", "80.2;95.0"),
                        **{name: np.full(n, -1) for name in ("leadId", "rearId", "leftLeadId", "leftRearId",
                                                             "rightLeadId", "rightRearId")},
                        "leftAlongsideId": np.full(n, ""), "rightAlongsideId": np.full(n, ""),
                        "odrRoadId": np.full(n, 7), "odrSectionNo": np.zeros(n, dtype=np.int64),
                        "odrLaneId": np.full(n, -2)}
        rows.append(pl.DataFrame(columns))
    table = pl.concat(rows).sort("trackId", "frame")
    table.write_csv(f"{prefix}_tracks.csv", float_precision=4)
    meta = pl.DataFrame([{
        "recordingId": recording_id, "trackId": t.track_id, "initialFrame": t.initial_frame,
        "finalFrame": t.initial_frame + len(t.positions) - 1, "numFrames": len(t.positions),
        "width": SIZES[t.cls][0], "length": SIZES[t.cls][1], "class": t.cls} for t in tracks]).sort("trackId")
    meta.write_csv(f"{prefix}_tracksMeta.csv")
    vrus = sum(t.cls in ("pedestrian", "bicycle") for t in tracks)
    last = int(table.get_column("frame").max())
    pl.DataFrame([{
        "recordingId": recording_id, "locationId": location_id, "frameRate": frame_rate, "speedLimit": 13.89,
        "weekday": "monday", "startTime": 8, "duration": round(last / frame_rate, 2), "numTracks": len(tracks),
        "numVehicles": len(tracks) - vrus, "numVRUs": vrus, "latLocation": 50.7, "lonLocation": 6.1,
        "xUtmOrigin": 300000.0, "yUtmOrigin": 5600000.0, "orthoPxToMeter": ortho_px_to_meter}]).write_csv(
        f"{prefix}_recordingMeta.csv")
    if image is None:
        image = intersection_image(ortho_px_to_meter * SCALE_DOWN[member])
    Image.fromarray(image).convert("RGB").save(f"{prefix}_background.png")
    return folder


def intersection_image(metres_per_px: float, size_m: float = 130.0) -> np.ndarray:
    """A grey image of a four-arm intersection at CENTRE (roads 7 m wide), pixel = (x, -y) / metres_per_px."""
    n = int(size_m / metres_per_px)
    rows, cols = np.mgrid[0:n, 0:n]
    x, y = cols * metres_per_px, -rows * metres_per_px
    image = np.full((n, n), 150, dtype=np.uint8)
    image[(np.abs(x - CENTRE[0]) < 3.5) | (np.abs(y - CENTRE[1]) < 3.5)] = 60
    return image


# -------------------------------------------------------------------------------------------- inD intersection

TURNER, ONCOMING_FIRST, ONCOMING_AFTER, CROSSING, RIGHT_TURNER = 1, 2, 3, 4, 5
LANE = 1.75
ARM = 58.0


def _straight(start: tuple[float, float], end: tuple[float, float], n: int = 300) -> np.ndarray:
    return np.linspace(start, end, n)


def left_turn_from_west() -> np.ndarray:
    """West arm (driving east on y = cy - 1.75), a left turn, then north (x = cx + 1.75)."""
    cx, cy = CENTRE
    approach = _straight((cx - ARM, cy - LANE), (cx - 8.0, cy - LANE))
    turn = _hermite(np.array([cx - 8.0, cy - LANE]), np.array([14.0, 0.0]), np.array([cx + LANE, cy + 8.0]),
                    np.array([0.0, 14.0]))
    leave = _straight((cx + LANE, cy + 8.0), (cx + LANE, cy + ARM))
    return np.concatenate([approach, turn[1:], leave[1:]])


def right_turn_from_south() -> np.ndarray:
    """South arm (driving north on x = cx + 1.75), a right turn, then east (y = cy - 1.75)."""
    cx, cy = CENTRE
    approach = _straight((cx + LANE, cy - ARM), (cx + LANE, cy - 6.0))
    turn = _hermite(np.array([cx + LANE, cy - 6.0]), np.array([0.0, 6.0]), np.array([cx + 6.0, cy - LANE]),
                    np.array([6.0, 0.0]))
    leave = _straight((cx + 6.0, cy - LANE), (cx + ARM, cy - LANE))
    return np.concatenate([approach, turn[1:], leave[1:]])


def intersection_scenario(time_shift: float = 0.0) -> list[Track]:
    """The scripted inD recording of the module docstring."""
    cx, cy = CENTRE
    oncoming = _straight((cx + ARM, cy + LANE), (cx - ARM, cy + LANE))
    return [
        drive(TURNER, "car", left_turn_from_west(), 0.0 + time_shift, 8.0, stop_at_distance=9.0,
              go_at=7.0 + time_shift),
        drive(ONCOMING_FIRST, "car", oncoming, 0.0 + time_shift, 10.0),
        drive(ONCOMING_AFTER, "truck_bus", oncoming, 4.0 + time_shift, 7.0),
        drive(CROSSING, "car", _straight((cx - LANE, cy + ARM), (cx - LANE, cy - ARM)), 20.0 + time_shift, 9.0),
        drive(RIGHT_TURNER, "car", right_turn_from_south(), 14.0 + time_shift, 7.0),
        drive(6, "pedestrian", _straight((cx - 12.0, cy - 10.0), (cx - 12.0, cy + 10.0), 50), 2.0 + time_shift, 1.3),
        drive(7, "bicycle", _straight((cx - LANE, cy - ARM), (cx - LANE, cy + ARM)), 25.0 + time_shift, 4.5),
    ]


# ------------------------------------------------------------------------------------------------------ highD

#: lane markings, metres with y down the image: three lanes per direction (upper lanes 2-4, lower lanes 6-8)
UPPER_MARKINGS = (8.5, 12.25, 16.0, 19.75)
LOWER_MARKINGS = (24.0, 27.75, 31.5, 35.25)
ROAD_LENGTH = 400.0
HIGHD_PX_TO_METER = 0.10106
HIGHD_SCALE_DOWN = 4
LC_TARGET, LC_FOLLOWER, LC_LEADER, UP_TARGET, UP_FOLLOWER, LONE_CHANGER, UP_TRUCK = 1, 2, 3, 4, 5, 6, 7
HIGHD_SIZES = {"Car": (4.6, 1.9), "Truck": (14.0, 2.5)}  # (length along x, width along y)


def lane_centre(lane: int) -> float:
    """y (down) of a lane's centre: upper lanes 2.. between UPPER_MARKINGS, lower lanes after them."""
    if lane < len(UPPER_MARKINGS) + 1:
        index = lane - 2
        return (UPPER_MARKINGS[index] + UPPER_MARKINGS[index + 1]) / 2
    index = lane - len(UPPER_MARKINGS) - 2
    return (LOWER_MARKINGS[index] + LOWER_MARKINGS[index + 1]) / 2


def lane_of(y: np.ndarray) -> np.ndarray:
    """highD laneId of centre positions y (down)."""
    upper = np.searchsorted(UPPER_MARKINGS, y) + 1
    lower = np.searchsorted(LOWER_MARKINGS, y) + len(UPPER_MARKINGS) + 1
    return np.where(y < (UPPER_MARKINGS[-1] + LOWER_MARKINGS[0]) / 2, upper, lower)


def highway_vehicle(track_id: int, cls: str, x0: float, speed: float, lane: int, *, duration: float = 30.0,
                    change_to: int | None = None, change_at: float = 6.0, change_time: float = 4.0) -> pl.DataFrame:
    """One highD vehicle at 25 Hz (frames from 1): centre x = x0 + speed * t (negative speed: upper lanes), a
    smooth lane change centred on `change_at`; rows while the box is on the road. Columns: id, frame, cx, cy, vx,
    vy (y down), class, direction."""
    t = np.arange(int(duration * FRAME_RATE)) / FRAME_RATE
    x = x0 + speed * t
    y = np.full_like(t, lane_centre(lane))
    vy = np.zeros_like(t)
    if change_to is not None:
        shift = lane_centre(change_to) - lane_centre(lane)
        s = np.clip((t - change_at + change_time / 2) / change_time, 0.0, 1.0)
        y = y + shift * (3 * s ** 2 - 2 * s ** 3)
        vy = shift * (6 * s - 6 * s ** 2) / change_time
    length = HIGHD_SIZES[cls][0]
    keep = (x - length / 2 >= 0) & (x + length / 2 <= ROAD_LENGTH)
    frames = np.arange(len(t)) + 1
    return pl.DataFrame({"id": track_id, "frame": frames[keep], "cx": x[keep], "cy": y[keep],
                         "vx": np.full(int(keep.sum()), speed), "vy": vy[keep], "class": cls,
                         "direction": 1 if speed < 0 else 2})


def highway_scenario(time_shift: float = 0.0) -> list[pl.DataFrame]:
    """The scripted highD recording of the module docstring (lane-change times shifted by `time_shift`)."""
    k = time_shift
    return [
        highway_vehicle(LC_TARGET, "Car", 60.0, 28.0, 6, change_to=7, change_at=6.0 + k),
        highway_vehicle(LC_FOLLOWER, "Car", 20.0, 30.0, 7),
        highway_vehicle(LC_LEADER, "Truck", 110.0, 27.0, 7),
        highway_vehicle(UP_TARGET, "Car", 380.0, -29.0, 3, change_to=2, change_at=6.0 + k),
        highway_vehicle(UP_FOLLOWER, "Car", 395.0, -30.0, 2),
        highway_vehicle(LONE_CHANGER, "Car", 10.0, 25.0, 7, change_to=8, change_at=10.0 + k),
        highway_vehicle(UP_TRUCK, "Truck", 390.0, -22.0, 4),
    ]


def _neighbours(rows: pl.DataFrame) -> pl.DataFrame:
    """precedingId / followingId (0: none) per row: the next vehicle ahead / behind in the same lane and frame,
    "ahead" meaning in the driving direction."""
    along = pl.when(pl.col("direction") == 2).then(pl.col("cx")).otherwise(-pl.col("cx"))
    ordered = rows.with_columns(along=along).sort("frame", "laneId", "along")
    same = (pl.col("frame").shift(-1) == pl.col("frame")) & (pl.col("laneId").shift(-1) == pl.col("laneId"))
    before = (pl.col("frame").shift(1) == pl.col("frame")) & (pl.col("laneId").shift(1) == pl.col("laneId"))
    return ordered.with_columns(precedingId=pl.when(same).then(pl.col("id").shift(-1)).otherwise(0),
                                followingId=pl.when(before).then(pl.col("id").shift(1)).otherwise(0)).drop("along")


def write_highd_recording(folder: Path, recording_id: int, vehicles: list[pl.DataFrame], *,
                          location_id: int = 2, image: bool = True) -> Path:
    """Write XX_recordingMeta.csv, XX_tracksMeta.csv, XX_tracks.csv and XX_highway.png in highD's format."""
    folder.mkdir(parents=True, exist_ok=True)
    prefix = folder / f"{recording_id:02d}"
    rows = pl.concat(vehicles).with_columns(
        laneId=pl.Series(lane_of(pl.concat(vehicles).get_column("cy").to_numpy())))
    rows = _neighbours(rows).sort("id", "frame")
    length = pl.col("class").replace_strict({c: s[0] for c, s in HIGHD_SIZES.items()}, return_dtype=pl.Float64)
    width = pl.col("class").replace_strict({c: s[1] for c, s in HIGHD_SIZES.items()}, return_dtype=pl.Float64)
    zero = pl.lit(0)
    tracks = rows.select(
        "frame", "id", (pl.col("cx") - length / 2).alias("x"), (pl.col("cy") - width / 2).alias("y"),
        length.alias("width"), width.alias("height"), pl.col("vx").alias("xVelocity"), pl.col("vy").alias("yVelocity"),
        pl.lit(0.0).alias("xAcceleration"), pl.lit(0.0).alias("yAcceleration"),
        pl.lit(150.0).alias("frontSightDistance"), pl.lit(150.0).alias("backSightDistance"),
        pl.lit(0.0).alias("dhw"), pl.lit(0.0).alias("thw"), pl.lit(0.0).alias("ttc"),
        pl.lit(0.0).alias("precedingXVelocity"), "precedingId", "followingId",
        *[zero.alias(name) for name in ("leftPrecedingId", "leftAlongsideId", "leftFollowingId", "rightPrecedingId",
                                        "rightAlongsideId", "rightFollowingId")], "laneId")
    tracks.write_csv(f"{prefix}_tracks.csv", float_precision=2)
    meta = (rows.group_by("id").agg(
        pl.col("class").first(), pl.col("direction").first().alias("drivingDirection"),
        pl.col("frame").min().alias("initialFrame"), pl.col("frame").max().alias("finalFrame"),
        pl.len().alias("numFrames"), (pl.col("vx").abs() * (pl.len() - 1) / FRAME_RATE).first()
        .alias("traveledDistance"), pl.col("vx").min().alias("minXVelocity"), pl.col("vx").max().alias("maxXVelocity"),
        pl.col("vx").mean().alias("meanXVelocity"),
        (pl.col("laneId") != pl.col("laneId").shift(1)).sum().alias("numLaneChanges"))
        .with_columns(width=length, height=width, minDHW=pl.lit(-1.0), minTHW=pl.lit(-1.0), minTTC=pl.lit(-1.0))
        .sort("id").select(HIGHD_TRACKS_META_COLUMNS))
    meta.write_csv(f"{prefix}_tracksMeta.csv", float_precision=2)
    trucks = int((meta.get_column("class") == "Truck").sum())
    pl.DataFrame([{
        "id": recording_id, "frameRate": FRAME_RATE, "locationId": location_id, "speedLimit": -1.0,
        "month": "09.2017", "weekDay": "Tue", "startTime": "08:38", "duration": 30.0,
        "totalDrivenDistance": float(meta.get_column("traveledDistance").sum()), "totalDrivenTime": 120.0,
        "numVehicles": meta.height, "numCars": meta.height - trucks, "numTrucks": trucks,
        "upperLaneMarkings": ";".join(f"{v:g}" for v in UPPER_MARKINGS),
        "lowerLaneMarkings": ";".join(f"{v:g}" for v in LOWER_MARKINGS)}]).write_csv(f"{prefix}_recordingMeta.csv")
    if image:
        Image.fromarray(highway_image()).convert("RGB").save(f"{prefix}_highway.png")
    return folder


def highway_image() -> np.ndarray:
    """The road from above at 0.10106 * 4 m/px (pixel = (x, y) / scale, y down): asphalt between the outer
    markings, white markings, grass around."""
    scale = HIGHD_PX_TO_METER * HIGHD_SCALE_DOWN
    height, width = int(45.0 / scale), int(ROAD_LENGTH / scale)
    y = np.arange(height)[:, None] * scale + np.zeros((1, width))
    image = np.full((height, width), 140, dtype=np.uint8)
    image[(y >= UPPER_MARKINGS[0]) & (y <= LOWER_MARKINGS[-1])] = 70
    for marking in (*UPPER_MARKINGS, *LOWER_MARKINGS):
        image[np.abs(y - marking) < scale / 2] = 230
    return image


def write_members(folder: Path, member: str, count: int = 1) -> Path:
    """`count` recordings of a member's scripted scenario (rounD: the roundabout; highD: the highway; inD: the
    intersection; exiD: the highway vehicles as drone tracks; uniD: the intersection), each shifted a little."""
    for index in range(count):
        if member == "highd":
            write_highd_recording(folder, index + 1, highway_scenario(0.2 * index))
        elif member == "round":
            write_drone_recording(folder, index, gap_scenario(time_shift=0.4 * index), member="round",
                                  image=background())
        else:
            write_drone_recording(folder, index, intersection_scenario(0.4 * index), member=member)
    return folder


def highd_expected_pairs() -> set[tuple[int, int]]:
    """(target, ego) of the scripted highD lane changes into a gap."""
    return {(LC_TARGET, LC_FOLLOWER), (UP_TARGET, UP_FOLLOWER)}


def windows_per_agent(rows_at_5hz: int, n_past: int = 15, n_future: int = 25, stride: int = 5) -> int:
    """All-agents samples of one agent with `rows_at_5hz` contiguous rows: t0 from its (n_past)th row on, every
    `stride`, while n_future rows follow."""
    usable = rows_at_5hz - n_past - n_future + 1
    return 0 if usable <= 0 else math.ceil(usable / stride)
