"""Times `trajflow ingest nuscenes` on a generated release and reports its peak memory.

A release in the official format (the fixture writer of the tests) with many scenes and agents, prediction-
challenge entries for every vehicle every 4 keyframes and a city-sized map expansion per location (about 155,000
nodes in 3,900 irregular polygons over 3 km x 3 km, plus a road, a walkway and a crossing at each scene) is
ingested in a fresh child process, so that the peak resident memory (VmHWM) is the ingest's own. Two more
children separate the fixed costs: one only imports trajflow and nuscenes-devkit, one also loads the release's
tables with the devkit (what the devkit itself holds for the whole run).

    python bench/nuscenes.py [--scenes 50] [--agents 40] [--frames 40] [--no-maps] [--repeat 3]
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import statistics
import sys
import tempfile
import time
import warnings
from itertools import zip_longest
from pathlib import Path
from queue import Empty

# this script is called nuscenes.py: keep its folder off the path so that `import nuscenes` finds the devkit
HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]
sys.path.insert(0, str(HERE.parent / "tests" / "ingest"))

from nuscenes_fixture import (MapRects, challenge_every, city_shapes, large_scenes,  # noqa: E402
                              write_expansion, write_release)


def _peak_rss_mib() -> float:
    """This process's peak resident set size in MiB.

    Linux's VmHWM restarts at exec, unlike ru_maxrss, which a spawned child inherits from its parent's fork.
    """
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / (1024 if sys.platform != "darwin" else 2**20)


def _child(job: str, root: str, out: str, queue: multiprocessing.Queue) -> None:
    """Run one job in a fresh process and send back (seconds, peak RSS in MiB)."""
    from trajflow_pipeline.ingest.nuscenes import ingest_nuscenes, load_devkit, open_release

    warnings.simplefilter("ignore")  # "no map expansion" under --no-maps is expected here
    devkit = load_devkit()
    start = time.perf_counter()
    if job == "load":
        open_release(devkit, Path(root), "v1.0-trainval")
    elif job == "ingest":
        ingest_nuscenes(root, out, version="v1.0-trainval", overwrite=True, quiet=True)
    queue.put((time.perf_counter() - start, _peak_rss_mib()))


def measure(job: str, root: Path, out: Path) -> tuple[float, float]:
    """(seconds, peak RSS MiB) of `job` ('import', 'load' or 'ingest') in a spawned child process."""
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=_child, args=(job, str(root), str(out), queue))
    process.start()
    while True:
        try:
            result = queue.get(timeout=1.0)
            break
        except Empty:
            if not process.is_alive():
                raise SystemExit(f"{job} child failed with exit code {process.exitcode}") from None
    process.join()
    return result


def write_bench_release(root: Path, scenes: int, agents: int, frames: int, maps: bool) -> dict[str, int]:
    """Write the release (official trainval scene names: train_val, train and val scenes) and count it."""
    from nuscenes.utils.splits import create_splits_scenes

    lists = create_splits_scenes()
    pools = [lists["train"][:200], lists["train"][200:], lists["val"]]  # train_val, train, val scenes
    names = [name for group in zip_longest(*pools) for name in group if name is not None][:scenes]
    specs = large_scenes(scenes, agents, n_frames=frames, names=names)
    challenge = challenge_every(specs)
    write_release(root, specs, version="v1.0-trainval", challenge=challenge)
    if maps:
        for location in sorted({scene.location for scene in specs}):
            here = [scene for scene in specs if scene.location == location]
            city = city_shapes(seed=len(location))
            rects = MapRects(
                drivable=city.drivable + tuple(
                    (s.ego_start[0] - 80, s.ego_start[1] - 10, s.ego_start[0] + 350, s.ego_start[1] + 60)
                    for s in here),
                walkways=city.walkways + tuple(
                    (s.ego_start[0] - 80, s.ego_start[1] + 60, s.ego_start[0] + 350, s.ego_start[1] + 66)
                    for s in here),
                crossings=city.crossings + tuple(
                    (s.ego_start[0] + 40, s.ego_start[1] - 10, s.ego_start[0] + 46, s.ego_start[1] + 60)
                    for s in here))
            write_expansion(root, location, here, rects)
    return {"annotations": sum(len(a.frames()) for s in specs for a in s.agents),
            "entries": sum(len(v) for v in challenge.values())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=50)
    parser.add_argument("--agents", type=int, default=40)
    parser.add_argument("--frames", type=int, default=40, help="keyframes per scene (real scenes have about 40)")
    parser.add_argument("--no-maps", action="store_true", help="do not write a map expansion")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root, out = Path(tmp) / "nuscenes", Path(tmp) / "data"
        start = time.perf_counter()
        counts = write_bench_release(root, args.scenes, args.agents, args.frames, not args.no_maps)
        print(f"release: {args.scenes} scenes x {args.agents} agents x {args.frames} keyframes, "
              f"{counts['annotations']} annotations, {counts['entries']} challenge entries, "
              f"maps: {not args.no_maps} (written in {time.perf_counter() - start:.1f} s)")
        _, import_rss = measure("import", root, out)
        load_s, load_rss = measure("load", root, out)
        runs = [measure("ingest", root, out) for _ in range(args.repeat)]
        from trajflow_pipeline.stages.inspect import summarize

        summary = summarize(out)
        maps = sorted((out / "maps").glob("*.png")) if (out / "maps").is_dir() else []
        print(f"dataset: {summary['scenes']} scenes, {summary['track_rows']} track rows, {summary['samples']} "
              f"samples {[(r['split'], r['samples']) for r in summary['samples_by_fold_and_split']]}, "
              f"{len(maps)} map PNGs ({sum(p.stat().st_size for p in maps) / 2**20:.1f} MiB)")
        seconds = [s for s, _ in runs]
        print(f"ingest time: median {statistics.median(seconds):.2f} s over {args.repeat} runs "
              f"({', '.join(f'{s:.2f}' for s in seconds)}); devkit table load alone {load_s:.2f} s")
        print(f"peak RSS: ingest {max(r for _, r in runs):.0f} MiB; imports only {import_rss:.0f} MiB; "
              f"imports + devkit tables {load_rss:.0f} MiB")


if __name__ == "__main__":
    main()
