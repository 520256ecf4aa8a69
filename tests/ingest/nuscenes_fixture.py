"""Writes small but complete nuScenes releases in the official format, for the nuScenes tests and the bench.

A release is a ``DATAROOT`` holding the 13 JSON tables of ``<version>/`` (attribute, calibrated_sensor, category,
ego_pose, instance, log, map, sample, sample_annotation, sample_data, scene, sensor, visibility), the semantic-prior
PNGs the ``map`` table names, ``maps/prediction/prediction_scenes.json`` and, on request, map-expansion JSONs in
``maps/expansion/``. Everything is generated from :class:`SceneSpec` / :class:`AgentSpec` values so that tests can
compare what the ingest read through nuscenes-devkit with exactly what was written: agents move at constant
velocity, keyframe timestamps are 0.5 s apart with a few milliseconds of jitter, and positions follow the real
timestamps.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

#: the 23 official nuScenes categories (category.json of v1.0)
CATEGORIES: tuple[str, ...] = (
    "animal", "human.pedestrian.adult", "human.pedestrian.child", "human.pedestrian.construction_worker",
    "human.pedestrian.personal_mobility", "human.pedestrian.police_officer", "human.pedestrian.stroller",
    "human.pedestrian.wheelchair", "movable_object.barrier", "movable_object.debris",
    "movable_object.pushable_pullable", "movable_object.trafficcone", "static_object.bicycle_rack",
    "vehicle.bicycle", "vehicle.bus.bendy", "vehicle.bus.rigid", "vehicle.car", "vehicle.construction",
    "vehicle.emergency.ambulance", "vehicle.emergency.police", "vehicle.motorcycle", "vehicle.trailer",
    "vehicle.truck",
)
ATTRIBUTES = ("vehicle.moving", "vehicle.parked", "pedestrian.moving", "cycle.with_rider")
TABLES = ("attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map", "sample",
          "sample_annotation", "sample_data", "scene", "sensor", "visibility")
SENSORS = (("LIDAR_TOP", "lidar"), ("CAM_FRONT", "camera"))
FIRST_TIMESTAMP_US = 1_532_402_927_647_951
KEYFRAME_US = 500_000
#: the camera keyframe is taken this much after the lidar keyframe (so its ego pose differs)
CAMERA_OFFSET_US = 12_000


def token(*parts: object) -> str:
    """A deterministic 32-hex-digit token, like the release's."""
    return hashlib.md5("/".join(str(part) for part in parts).encode()).hexdigest()


def quaternion(yaw: float) -> list[float]:
    """[w, x, y, z] of a rotation by `yaw` about the z axis (the release's rotation format)."""
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


@dataclass(frozen=True)
class AgentSpec:
    """One annotated object: annotated on keyframes first_frame..last_frame, moving at constant velocity."""

    category: str
    first_frame: int
    last_frame: int
    start: tuple[float, float]
    velocity: tuple[float, float] = (0.0, 0.0)
    size: tuple[float, float, float] = (1.9, 4.6, 1.7)  # width, length, height (the release's order)
    yaw: float = 0.0
    z: float = 0.9

    def position(self, seconds: float) -> tuple[float, float, float]:
        """Global position `seconds` after the scene's first keyframe."""
        return (self.start[0] + self.velocity[0] * seconds, self.start[1] + self.velocity[1] * seconds, self.z)

    def frames(self) -> range:
        return range(self.first_frame, self.last_frame + 1)


@dataclass(frozen=True)
class SceneSpec:
    """One scene: its official name, map location, number of keyframes, agents and the ego vehicle's motion."""

    name: str
    location: str
    n_frames: int
    agents: tuple[AgentSpec, ...]
    ego_start: tuple[float, float] = (0.0, 0.0)
    ego_velocity: tuple[float, float] = (5.0, 0.0)
    ego_yaw: float = 0.0
    description: str = "fixture scene"

    def ego_position(self, seconds: float) -> tuple[float, float, float]:
        return (self.ego_start[0] + self.ego_velocity[0] * seconds,
                self.ego_start[1] + self.ego_velocity[1] * seconds, 0.0)


def jitter_us(frame: int) -> int:
    """A deterministic timing jitter of a few milliseconds, so that keyframes are not exactly 0.5 s apart."""
    return ((frame * 37) % 9 - 4) * 3_000


@dataclass
class Release:
    """What was written: paths, tokens and timestamps, for comparing an ingest with the fixture."""

    root: Path
    version: str
    scenes: list[SceneSpec]
    scene_tokens: dict[str, str] = field(default_factory=dict)
    sample_tokens: dict[str, list[str]] = field(default_factory=dict)
    timestamps: dict[str, list[int]] = field(default_factory=dict)
    #: challenge entries written to prediction_scenes.json: scene name -> [(agent index, t0 frame)]
    challenge: dict[str, list[tuple[int, int]]] = field(default_factory=dict)

    def scene(self, name: str) -> SceneSpec:
        return next(scene for scene in self.scenes if scene.name == name)

    def instance_token(self, scene: str, agent: int) -> str:
        return token("instance", scene, agent)

    def seconds(self, scene: str, frame: int) -> float:
        """Seconds from the scene's first keyframe to keyframe `frame` (real timestamps)."""
        stamps = self.timestamps[scene]
        return (stamps[frame] - stamps[0]) / 1e6

    def instance_sample(self, scene: str, agent: int, frame: int) -> str:
        """The prediction-challenge token of an agent at a keyframe: '{instance_token}_{sample_token}'."""
        return f"{self.instance_token(scene, agent)}_{self.sample_tokens[scene][frame]}"

    @property
    def table_root(self) -> Path:
        return self.root / self.version


def small_scenes() -> list[SceneSpec]:
    """Two official mini scenes of a few seconds: a car, a pedestrian, a bicycle / an animal, a traffic cone."""
    car = AgentSpec("vehicle.car", 0, 19, (400.0, 1100.0), (8.0, 1.0), (1.9, 4.6, 1.7), math.atan2(1.0, 8.0))
    pedestrian = AgentSpec("human.pedestrian.adult", 2, 19, (410.0, 1095.0), (0.2, 1.2), (0.6, 0.7, 1.8),
                           math.atan2(1.2, 0.2))
    cone = AgentSpec("movable_object.trafficcone", 0, 19, (405.0, 1092.0), (0.0, 0.0), (0.4, 0.4, 1.0), 0.3)
    bicycle = AgentSpec("vehicle.bicycle", 5, 15, (395.0, 1105.0), (3.0, -0.5), (0.7, 1.8, 1.4), -0.165)
    first = SceneSpec("scene-0061", "singapore-onenorth", 20, (car, pedestrian, cone, bicycle),
                      ego_start=(390.0, 1098.0), ego_velocity=(6.0, 0.5), ego_yaw=math.atan2(0.5, 6.0),
                      description="Parked truck, construction, intersection, turn left")
    truck = AgentSpec("vehicle.truck", 0, 15, (600.0, 1600.0), (-5.0, 4.0), (2.5, 9.0, 3.2), math.atan2(4.0, -5.0))
    child = AgentSpec("human.pedestrian.child", 0, 12, (610.0, 1590.0), (1.0, 0.1), (0.4, 0.4, 1.2), 0.1)
    dog = AgentSpec("animal", 3, 8, (605.0, 1595.0), (1.5, 1.5), (0.3, 0.8, 0.5), math.pi / 4)
    second = SceneSpec("scene-0103", "boston-seaport", 16, (truck, child, dog),
                       ego_start=(590.0, 1580.0), ego_velocity=(4.0, 3.0), ego_yaw=math.atan2(3.0, 4.0),
                       description="Night, big street, bus stop")
    return [first, second]


#: prediction-challenge entries of :func:`small_scenes`: scene -> [(agent index, t0 frame)]. The pedestrian of
#: scene-0061 appears at frame 2, so its samples at t0 2 and 3 have a short past; the car at t0 10 has only
#: 9 future keyframes (dropped); the child of scene-0103 at t0 0 has no past at all.
SMALL_CHALLENGE: dict[str, list[tuple[int, int]]] = {
    "scene-0061": [(0, 3), (0, 4), (0, 7), (1, 2), (1, 3), (0, 10)],
    "scene-0103": [(0, 3), (1, 0)],
}


def write_release(root: Path, scenes: list[SceneSpec] | None = None, *, version: str = "v1.0-mini",
                  challenge: dict[str, list[tuple[int, int]]] | None = None, prediction: bool = True,
                  expansion: bool | tuple[str, ...] = False) -> Release:
    """Write a release under `root`; returns what was written.

    `challenge` defaults to :data:`SMALL_CHALLENGE` for the default scenes and to no entries otherwise;
    `expansion` writes map-expansion JSONs for every location (True) or the named ones.
    """
    if scenes is None:
        scenes = small_scenes()
        challenge = SMALL_CHALLENGE if challenge is None else challenge
    release = Release(root=root, version=version, scenes=scenes, challenge=dict(challenge or {}))
    tables: dict[str, list[dict]] = {name: [] for name in TABLES}
    tables["category"] = [{"token": token("category", name), "name": name, "description": name,
                           "index": index} for index, name in enumerate(CATEGORIES)]
    tables["attribute"] = [{"token": token("attribute", name), "name": name, "description": name}
                           for name in ATTRIBUTES]
    tables["visibility"] = [{"token": str(level), "level": f"v{20 * level}-{20 * level + 20}",
                             "description": f"visibility level {level}"} for level in range(1, 5)]
    tables["sensor"] = [{"token": token("sensor", channel), "channel": channel, "modality": modality}
                        for channel, modality in SENSORS]
    for index, scene in enumerate(scenes):
        _write_scene(release, tables, scene, FIRST_TIMESTAMP_US + index * 60_000_000)
    locations = sorted({scene.location for scene in scenes})
    for location in locations:
        logs = [row["token"] for row in tables["log"] if row["location"] == location]
        map_token = token("map", location)
        tables["map"].append({"token": map_token, "log_tokens": logs, "category": "semantic_prior",
                              "filename": f"maps/{map_token}.png"})
        (root / "maps").mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.zeros((8, 8), dtype=np.uint8), mode="L").save(root / "maps" / f"{map_token}.png")
    release.table_root.mkdir(parents=True, exist_ok=True)
    for name, rows in tables.items():
        (release.table_root / f"{name}.json").write_text(json.dumps(rows, indent=0))
    if prediction:
        write_prediction_scenes(release)
    if expansion:
        for location in (locations if expansion is True else expansion):
            write_expansion(root, location, [scene for scene in scenes if scene.location == location])
    return release


def _write_scene(release: Release, tables: dict[str, list[dict]], scene: SceneSpec, start_us: int) -> None:
    """Append one scene's log, samples, sample_data (+ sweeps), ego poses, instances and annotations."""
    name = scene.name
    log_token, scene_token = token("log", name), token("scene", name)
    tables["log"].append({"token": log_token, "logfile": f"n015-{name}", "vehicle": "n015",
                          "date_captured": "2018-07-24", "location": scene.location})
    calibrated = {channel: token("calibrated_sensor", name, channel) for channel, _ in SENSORS}
    for channel, modality in SENSORS:
        tables["calibrated_sensor"].append({
            "token": calibrated[channel], "sensor_token": token("sensor", channel),
            "translation": [0.94, 0.0, 1.84] if modality == "lidar" else [1.70, 0.01, 1.51],
            "rotation": quaternion(-math.pi / 2) if modality == "lidar" else [0.5, -0.5, 0.5, -0.5],
            "camera_intrinsic": [] if modality == "lidar" else [[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5],
                                                                 [0.0, 0.0, 1.0]]})
    samples = [token("sample", name, frame) for frame in range(scene.n_frames)]
    stamps = [start_us + frame * KEYFRAME_US + jitter_us(frame) for frame in range(scene.n_frames)]
    release.scene_tokens[name], release.sample_tokens[name], release.timestamps[name] = scene_token, samples, stamps
    tables["scene"].append({"token": scene_token, "log_token": log_token, "nbr_samples": scene.n_frames,
                            "first_sample_token": samples[0], "last_sample_token": samples[-1], "name": name,
                            "description": scene.description})
    for frame, (sample, stamp) in enumerate(zip(samples, stamps)):
        tables["sample"].append({"token": sample, "timestamp": stamp, "scene_token": scene_token,
                                 "prev": samples[frame - 1] if frame else "",
                                 "next": samples[frame + 1] if frame + 1 < scene.n_frames else ""})
    _write_sensor_data(tables, scene, samples, stamps, calibrated)
    for index, agent in enumerate(scene.agents):
        _write_agent(tables, scene, index, agent, samples, stamps)


def _write_sensor_data(tables: dict[str, list[dict]], scene: SceneSpec, samples: list[str], stamps: list[int],
                       calibrated: dict[str, str]) -> None:
    """Keyframe lidar and camera data with their ego poses, plus one lidar sweep between keyframes.

    The ego moves like an agent, its time measured from the scene's first (lidar) keyframe.
    """
    for channel, modality in SENSORS:
        records = []
        for frame, (sample, stamp) in enumerate(zip(samples, stamps)):
            offsets = [(0, True)] if modality == "camera" else [(0, True), (KEYFRAME_US // 2, False)]
            if frame + 1 == len(samples):
                offsets = offsets[:1]
            for offset, key in offsets:
                at = stamp + offset + (CAMERA_OFFSET_US if modality == "camera" else 0)
                data_token = token("sample_data", scene.name, channel, frame, offset)
                pose_token = token("ego_pose", scene.name, channel, frame, offset)
                x, y, z = scene.ego_position((at - stamps[0]) / 1e6)
                tables["ego_pose"].append({"token": pose_token, "timestamp": at, "translation": [x, y, z],
                                           "rotation": quaternion(scene.ego_yaw)})
                suffix = "pcd.bin" if modality == "lidar" else "jpg"
                folder = "samples" if key else "sweeps"
                records.append({"token": data_token, "sample_token": sample, "ego_pose_token": pose_token,
                                "calibrated_sensor_token": calibrated[channel], "timestamp": at,
                                "fileformat": suffix.split(".")[0], "is_key_frame": key,
                                "height": 0 if modality == "lidar" else 900,
                                "width": 0 if modality == "lidar" else 1600,
                                "filename": f"{folder}/{channel}/{scene.name}__{channel}__{at}.{suffix}"})
        for index, record in enumerate(records):
            record["prev"] = records[index - 1]["token"] if index else ""
            record["next"] = records[index + 1]["token"] if index + 1 < len(records) else ""
        tables["sample_data"].extend(records)


def _write_agent(tables: dict[str, list[dict]], scene: SceneSpec, index: int, agent: AgentSpec,
                 samples: list[str], stamps: list[int]) -> None:
    """One instance and its chain of sample annotations (prev / next links)."""
    instance = token("instance", scene.name, index)
    annotations = [token("sample_annotation", scene.name, index, frame) for frame in agent.frames()]
    tables["instance"].append({"token": instance, "category_token": token("category", agent.category),
                               "nbr_annotations": len(annotations), "first_annotation_token": annotations[0],
                               "last_annotation_token": annotations[-1]})
    for position, frame in enumerate(agent.frames()):
        x, y, z = agent.position((stamps[frame] - stamps[0]) / 1e6)
        tables["sample_annotation"].append({
            "token": annotations[position], "sample_token": samples[frame], "instance_token": instance,
            "visibility_token": "4", "attribute_tokens": [], "translation": [x, y, z], "size": list(agent.size),
            "rotation": quaternion(agent.yaw), "num_lidar_pts": 12, "num_radar_pts": 1,
            "prev": annotations[position - 1] if position else "",
            "next": annotations[position + 1] if position + 1 < len(annotations) else ""})


def write_prediction_scenes(release: Release) -> Path:
    """maps/prediction/prediction_scenes.json: scene name -> ['{instance_token}_{sample_token}', ...]."""
    entries = {scene: [release.instance_sample(scene, agent, frame) for agent, frame in pairs]
               for scene, pairs in release.challenge.items()}
    path = release.root / "maps" / "prediction" / "prediction_scenes.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(entries))
    return path


#: a map shape: an axis-aligned rectangle (x0, y0, x1, y1) or a polygon's exterior [(x, y), ...], in metres
Shape = tuple[float, float, float, float] | list[tuple[float, float]]


@dataclass(frozen=True)
class MapRects:
    """Shapes (mostly rectangles) in metres for the three rasterised layers of one location."""

    drivable: tuple[Shape, ...]
    walkways: tuple[Shape, ...]
    crossings: tuple[Shape, ...]


def map_rects(scenes: list[SceneSpec]) -> MapRects:
    """A road along the first scene's ego path, a walkway north of it and a crossing across it."""
    ex, ey = scenes[0].ego_start
    return MapRects(drivable=((ex - 20.0, ey - 8.0, ex + 200.0, ey + 30.0),),
                    walkways=((ex - 20.0, ey + 30.0, ex + 200.0, ey + 36.0),),
                    crossings=((ex + 20.0, ey - 8.0, ex + 26.0, ey + 30.0),))


def write_expansion(root: Path, location: str, scenes: list[SceneSpec], rects: MapRects | None = None,
                    version: str = "1.3") -> Path:
    """maps/expansion/<location>.json in the map-expansion format the devkit reads (nodes, polygons, layers).

    The drivable area is one record with one polygon per shape; walkways and crossings are one record each.
    """
    rects = rects or map_rects(scenes)  # `scenes` only place the default layout
    nodes: list[dict] = []
    polygons: list[dict] = []

    def polygon(label: str, shape: Shape) -> str:
        if isinstance(shape, tuple):
            x0, y0, x1, y1 = shape
            shape = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
        corner_tokens = []
        for corner, (x, y) in enumerate(shape):
            corner_tokens.append(token("node", location, label, corner))
            nodes.append({"token": corner_tokens[-1], "x": x, "y": y})
        polygons.append({"token": token("polygon", location, label), "exterior_node_tokens": corner_tokens,
                         "holes": []})
        return polygons[-1]["token"]

    drivable = [{"token": token("drivable_area", location),
                 "polygon_tokens": [polygon(f"drivable{i}", shape) for i, shape in enumerate(rects.drivable)]}]
    walkways = [{"token": token("walkway", location, i), "polygon_token": polygon(f"walkway{i}", shape)}
                for i, shape in enumerate(rects.walkways)]
    crossings = [{"token": token("ped_crossing", location, i), "polygon_token": polygon(f"crossing{i}", shape),
                  "road_segment_token": ""} for i, shape in enumerate(rects.crossings)]
    content = {"version": version, "canvas_edge": [3000.0, 3000.0], "node": nodes, "polygon": polygons,
               "line": [], "drivable_area": drivable, "road_segment": [], "road_block": [], "lane": [],
               "ped_crossing": crossings, "walkway": walkways, "stop_line": [], "carpark_area": [],
               "road_divider": [], "lane_divider": [], "traffic_light": [], "arcline_path_3": {},
               "connectivity": {}, "lane_connector": []}
    path = root / "maps" / "expansion" / f"{location}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content))
    return path


def large_scenes(n_scenes: int, agents_per_scene: int, n_frames: int = 40, seed: int = 0,
                 names: list[str] | None = None) -> list[SceneSpec]:
    """Random scenes for the bench: agents of mixed classes entering and leaving, moving at constant velocity."""
    rng = np.random.default_rng(seed)
    classes = ("vehicle.car", "vehicle.car", "human.pedestrian.adult", "vehicle.truck", "vehicle.bicycle",
               "vehicle.motorcycle", "movable_object.barrier", "human.pedestrian.child")
    locations = ("singapore-onenorth", "boston-seaport", "singapore-queenstown", "singapore-hollandvillage")
    scenes = []
    for index in range(n_scenes):
        origin = rng.uniform(200.0, 1500.0, size=2)
        agents = []
        for _ in range(agents_per_scene):
            category = str(rng.choice(classes))
            first = int(rng.integers(0, n_frames // 2))
            last = int(rng.integers(min(first + 4, n_frames - 1), n_frames))
            speed = 1.3 if category.startswith("human") else 0.0 if category.startswith("movable") else 8.0
            heading = float(rng.uniform(-math.pi, math.pi))
            velocity = (speed * math.cos(heading), speed * math.sin(heading))
            start = tuple(float(v) for v in origin + rng.normal(scale=40.0, size=2))
            agents.append(AgentSpec(category, first, last, start, velocity, (1.9, 4.6, 1.7), heading))
        name = names[index] if names else f"scene-{index + 1:04d}"
        scenes.append(SceneSpec(name, locations[index % len(locations)], n_frames, tuple(agents),
                                ego_start=(float(origin[0]), float(origin[1])), ego_velocity=(7.0, 1.0),
                                ego_yaw=math.atan2(1.0, 7.0)))
    return scenes


def challenge_every(scenes: list[SceneSpec], step: int = 4, n_past: int = 4, n_future: int = 12
                    ) -> dict[str, list[tuple[int, int]]]:
    """Challenge entries for the bench: every vehicle every `step` keyframes where its full future exists."""
    entries: dict[str, list[tuple[int, int]]] = {}
    for scene in scenes:
        pairs = [(index, t0) for index, agent in enumerate(scene.agents) if agent.category.startswith("vehicle")
                 for t0 in range(agent.first_frame + 1, agent.last_frame - n_future + 1, step)]
        if pairs:
            entries[scene.name] = pairs
    return entries


def city_shapes(n_drivable: int = 300, n_walkways: int = 3000, n_crossings: int = 600, extent: float = 3000.0,
                seed: int = 0) -> MapRects:
    """Irregular polygons spread over a city-sized area, about as many nodes as a real map expansion layer set."""
    rng = np.random.default_rng(seed)

    def blobs(count: int, radius: float, vertices: int) -> tuple[Shape, ...]:
        shapes = []
        for cx, cy in rng.uniform(0.0, extent, size=(count, 2)):
            angles = np.linspace(0.0, 2 * math.pi, vertices, endpoint=False)
            radii = radius * rng.uniform(0.7, 1.0, size=vertices)
            shapes.append([(float(cx + r * math.cos(a)), float(cy + r * math.sin(a))) for a, r in zip(angles, radii)])
        return tuple(shapes)

    return MapRects(drivable=blobs(n_drivable, 60.0, 300), walkways=blobs(n_walkways, 15.0, 20),
                    crossings=blobs(n_crossings, 5.0, 8))
