"""Bring-your-own CSV / Parquet: column mapping, time grids, identical-input groups, splits and bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
from typer.testing import CliRunner

from test_ingest_bad_input import assert_one_line_error
from trajflow_pipeline.cli.app import app
from trajflow_pipeline.data import list_folds, select_samples
from trajflow_pipeline.errors import DataError, UsageError
from trajflow_pipeline.schemas import open_dataset
from trajflow_pipeline.ingest.csv import ColumnMap, ingest_csv

runner = CliRunner()


def walkers(scenes: int = 2, agents: int = 3, frames: int = 30, seed: int = 0) -> pl.DataFrame:
    rng = np.random.default_rng(seed)
    rows = []
    for s in range(scenes):
        for a in range(agents):
            start = rng.normal(size=2) * 5
            velocity = rng.normal(size=2)
            for f in range(frames):
                rows.append({"sid": f"scene{s}", "who": f"p{a}", "time": f * 0.5, "px": start[0] + velocity[0] * f * 0.5,
                             "py": start[1] + velocity[1] * f * 0.5, "cls": ["Person", "Car", "bike"][a % 3]})
    return pl.DataFrame(rows)


def test_mapped_columns_time_and_types(tmp_path: Path) -> None:
    path = tmp_path / "walkers.csv"
    walkers(frames=100).write_csv(path)
    out = ingest_csv(path, tmp_path / "ds", dt=0.5, n_past=4, n_future=6,
                     columns=ColumnMap.parse("scene=sid,agent=who,time=time,x=px,y=py,type=cls"))
    ds = open_dataset(out)
    tracks = ds.tracks()
    assert tracks.height == 2 * 3 * 100
    assert set(tracks.get_column("agent_type")) == {"pedestrian", "vehicle", "bicycle"}
    assert set(tracks.get_column("agent_label")) == {"p0", "p1", "p2"}
    samples = ds.samples()
    assert (samples.get_column("n_past") == 4).all()
    assert ds.meta.protocol == "folds" and list_folds(ds) == ["0", "1", "2", "3", "4"]
    for fold in list_folds(ds):
        test = set(select_samples(ds, fold, "test").get_column("sample_id"))
        train = set(select_samples(ds, fold, "train").get_column("sample_id"))
        assert test and train and not test & train


def test_identical_inputs_share_a_group_even_across_scenes(tmp_path: Path) -> None:
    """Same pasts of the same agents -> one group; a different future does not matter, other context does."""
    base = walkers(scenes=1, agents=2, frames=12)
    future_differs = base.with_columns(sid=pl.lit("copy"), px=pl.when((pl.col("who") == "p0") & (pl.col("time") > 3.0))
                                       .then(pl.col("px") + 2.0).otherwise(pl.col("px")))
    lonely = base.filter(pl.col("who") == "p0").with_columns(sid=pl.lit("lonely"))
    moved = base.with_columns(sid=pl.lit("moved"), px=pl.col("px") + 0.01)
    path = tmp_path / "multi.parquet"
    pl.concat([base, future_differs, lonely, moved]).write_parquet(path)
    out = ingest_csv(path, tmp_path / "ds", dt=0.5, n_past=4, n_future=6, split_col=None, folds=2,
                     columns=ColumnMap.parse("scene=sid,agent=who,time=time,x=px,y=py,type=cls"))
    samples = open_dataset(out).samples()
    assert set(samples.get_column("t0_frame")) == {3, 4, 5}
    for (t0, agent), part in samples.group_by("t0_frame", "agent_id"):
        group = dict(part.select("scene_id", "group_id").iter_rows())
        assert group["scene0"] == group["copy"]
        assert group["moved"] != group["scene0"]
        if "lonely" in group:
            assert group["lonely"] not in (group["scene0"], group["moved"])
    assert samples.get_column("group_id").n_unique() == 3 * (2 + 2 + 1)


def test_split_column_gives_a_fixed_protocol(tmp_path: Path) -> None:
    frame = walkers().with_columns(split=pl.when(pl.col("sid") == "scene0").then(pl.lit("train")).otherwise(pl.lit("Test")))
    path = tmp_path / "w.csv"
    frame.write_csv(path)
    out = ingest_csv(path, tmp_path / "ds", dt=0.5, split_col="split",
                     columns=ColumnMap.parse("scene=sid,agent=who,time=time,x=px,y=py"))
    ds = open_dataset(out)
    assert ds.meta.protocol == "fixed"
    assert set(select_samples(ds, None, "test").get_column("scene_id")) == {"scene1"}
    assert set(select_samples(ds, None, "train").get_column("scene_id")) == {"scene0"}


@pytest.mark.parametrize(("edit", "message"), [
    (lambda f: f.drop("py"), "missing column(s) py"),
    (lambda f: f.with_columns(px=pl.when(pl.int_range(pl.len()) == 5).then(pl.lit("x")).otherwise(pl.col("px").cast(pl.String))),
     "w.csv:7: column 'px' holds 'x'"),
    (lambda f: f.with_columns(py=pl.when(pl.int_range(pl.len()) == 2).then(float("nan")).otherwise(pl.col("py"))),
     "w.csv:4: column 'py' holds 'NaN'"),
    (lambda f: f.with_columns(time=pl.when(pl.int_range(pl.len()) == 3).then(1.3).otherwise(pl.col("time"))),
     "w.csv:5: time 1.3 is not on the --dt 0.5 grid"),
    (lambda f: pl.concat([f, f.slice(4, 1)]), "w.csv:182: duplicate row for scene 'scene0', agent 1, frame 4 "
     "(first at line 6)"),
    (lambda f: f.head(0), "file has no rows"),
])
def test_bad_csv_input(tmp_path: Path, edit, message: str) -> None:
    path = tmp_path / "w.csv"
    edit(walkers()).write_csv(path)
    with pytest.raises(DataError) as caught:
        ingest_csv(path, tmp_path / "ds", dt=0.5, columns=ColumnMap.parse("scene=sid,agent=who,time=time,x=px,y=py"))
    assert message in str(caught.value)
    assert not (tmp_path / "ds").exists()


def test_ragged_csv_line_and_bad_options(tmp_path: Path) -> None:
    path = tmp_path / "r.csv"
    path.write_text("scene_id,agent_id,frame,x,y\na,1,0,0,0\na,1,1,1,1,9\n")
    result = runner.invoke(app, ["ingest", "csv", str(path), "-o", str(tmp_path / "o"), "--dt", "0.4"])
    assert result.exit_code == 1 and "r.csv:3: expected 5 fields" in result.output
    with pytest.raises(UsageError, match="role=column"):
        ColumnMap.parse("colour=c")
    for dt in ("-1", "nan", "inf"):
        result = runner.invoke(app, ["ingest", "csv", str(path), "-o", str(tmp_path / "o"), "--dt", dt])
        assert result.exit_code == 2 and "--dt must be a positive number of seconds" in result.output
        assert not (tmp_path / "o").exists()


def test_paths_with_glob_characters_are_paths(tmp_path: Path) -> None:
    """`[`, `]`, `*` and `?` in file and folder names are characters: the file named is read (alone), the dataset
    folder written and read back; a pattern that names no file is 'not found', not a merge of its matches."""
    folder = tmp_path / "g[1] *?"
    folder.mkdir()
    walkers(frames=40).write_csv(folder / "run[1].csv")
    walkers(frames=40, seed=1).write_csv(folder / "data1.csv")
    columns = ColumnMap.parse("scene=sid,agent=who,time=time,x=px,y=py")
    out = ingest_csv(folder / "run[1].csv", folder / "ds[2]", dt=0.5, n_past=4, n_future=6, folds=2,
                     columns=columns)
    assert open_dataset(out).tracks().height == 2 * 3 * 40
    result = runner.invoke(app, ["inspect", str(out)])
    assert result.exit_code == 0, result.output
    with pytest.raises(DataError, match="input file not found"):
        ingest_csv(folder / "data*.csv", folder / "merged", dt=0.5, n_past=4, n_future=6, folds=2, columns=columns)


HEADER = "scene_id,agent_id,frame,x,y,note"


def track_lines(frames: int = 30) -> list[str]:
    """One agent of scene 'a' walking along x, one CSV line per frame (file line = frame + 2)."""
    return [f"a,1,{f},{0.1 * f:.1f},0,ok" for f in range(frames)]


def replace_line(line: int, text: str) -> str:
    """The file with its data line number `line` (header is line 1) replaced by `text`."""
    lines = [HEADER, *track_lines()]
    lines[line - 1] = text
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(("text", "fragments"), [
    (replace_line(7, ",1,5,0.5,0,ok"), ["c.csv:7: empty scene cell (column 'scene_id')"]),
    (replace_line(7, "a, ,5,0.5,0,ok"), ["c.csv:7: empty agent cell (column 'agent_id')"]),
    (replace_line(7, "a,1,,0.5,0,ok"), ["c.csv:7: empty frame cell (column 'frame')"]),
    (replace_line(7, "a,1,5,0.5"), ["c.csv:7: empty y cell (column 'y')"]),
    (replace_line(7, ""), ["c.csv:7: blank line"]),
    (replace_line(7, "a,1,5,1e300,0,ok"), ["c.csv:7: column 'x' holds '1e300', beyond the largest magnitude"]),
    (replace_line(7, "a,1,5,0.5,-1e39,ok"), ["c.csv:7: column 'y' holds '-1e39', beyond"]),  # float32 overflows
    (replace_line(7, "a,1,1e300,0.5,0,ok"), ["c.csv:7: column 'frame' holds '1e300', beyond"]),
    (replace_line(7, "a,1,5,inf,0,ok"), ["c.csv:7: column 'x' holds 'inf', not a finite number"]),
    (replace_line(7, 'a,1,5,0.5,0,"o"k'), ["c.csv:7: malformed CSV"]),
    # a quoted field over two lines, then CRLF, a form feed, U+2028, U+0085 and a lone CR inside lines
    ('\n'.join([HEADER, 'a,1,0,0,0,"two\nlines"', *track_lines()[1:5], "a,1,5,zz,0,ok"]) + "\n",
     ["c.csv:8: column 'x' holds 'zz', not a number"]),
    ("\r\n".join([HEADER, "a,1,0,0,0,f\fu\u2028n\u0085l\rx", *track_lines()[1:5], "a,1,5,nan,0,ok"]) + "\r\n",
     ["c.csv:7: column 'x' holds 'nan', not a finite number"]),
    ("\n".join([HEADER, *track_lines(), track_lines()[3]]) + "\n",
     ["c.csv:32: duplicate row for scene 'a', agent 1, frame 3 (first at line 5)"]),
])
def test_problems_after_parsing_name_the_csv_line(tmp_path: Path, text: str, fragments: list[str]) -> None:
    """Every check of a cell names the input file and the line an editor shows, never an output Parquet file."""
    path = tmp_path / "c.csv"
    path.write_bytes(text.encode())
    result = runner.invoke(app, ["ingest", "csv", str(path), "-o", str(tmp_path / "out"), "--dt", "0.4", "-q"])
    assert_one_line_error(result, *fragments)
    assert result.exit_code == 1 and "parquet" not in result.output
    assert not (tmp_path / "out").exists()


def test_split_column_and_parquet_problems_are_located(tmp_path: Path) -> None:
    frame = walkers().with_columns(split=pl.lit("train"))
    path = tmp_path / "w.csv"
    frame.with_columns(split=pl.when(pl.int_range(pl.len()) == 9).then(pl.lit("")).otherwise(pl.col("split"))
                       ).write_csv(path)
    columns = ColumnMap.parse("scene=sid,agent=who,time=time,x=px,y=py")
    with pytest.raises(DataError, match=r"w\.csv:11: empty split cell \(column 'split'\)"):
        ingest_csv(path, tmp_path / "ds", dt=0.5, split_col="split", columns=columns)
    frame.with_columns(split=pl.when(pl.int_range(pl.len()) == 9).then(pl.lit("dev")).otherwise(pl.col("split"))
                       ).write_csv(path)
    with pytest.raises(DataError, match=r"w\.csv:11: split column 'split' holds 'dev'"):
        ingest_csv(path, tmp_path / "ds", dt=0.5, split_col="split", columns=columns)
    parquet = tmp_path / "w.parquet"
    frame.with_columns(sid=pl.when(pl.int_range(pl.len()) == 9).then(None).otherwise(pl.col("sid")),
                       px=pl.when(pl.int_range(pl.len()) == 12).then(1e300).otherwise(pl.col("px"))
                       ).write_parquet(parquet)
    with pytest.raises(DataError, match=r"w\.parquet \(row 9\): empty scene cell"):
        ingest_csv(parquet, tmp_path / "ds", dt=0.5, columns=columns)
    frame.with_columns(px=pl.when(pl.int_range(pl.len()) == 12).then(1e300).otherwise(pl.col("px"))
                       ).write_parquet(parquet)
    with pytest.raises(DataError, match=r"w\.parquet \(row 12\): column 'px' holds '1e\+300'"):
        ingest_csv(parquet, tmp_path / "ds", dt=0.5, columns=columns)


def test_time_far_off_and_empty_type_cells(tmp_path: Path) -> None:
    """A time whose frame is beyond 2^53 is refused at its line; an empty class label is 'unknown'."""
    frame = walkers(frames=40).with_columns(cls=pl.when(pl.int_range(pl.len()) == 3).then(pl.lit(""))
                                            .otherwise(pl.col("cls")))
    path = tmp_path / "w.csv"
    frame.write_csv(path)
    columns = ColumnMap.parse("scene=sid,agent=who,time=time,x=px,y=py,type=cls")
    out = ingest_csv(path, tmp_path / "ds", dt=0.5, n_past=4, n_future=6, folds=2, columns=columns)
    assert "unknown" in set(open_dataset(out).tracks().get_column("agent_type"))
    frame.with_columns(time=pl.when(pl.int_range(pl.len()) == 5).then(5e15).otherwise(pl.col("time"))
                       ).write_csv(path)
    with pytest.raises(DataError, match=r"w\.csv:7: time '.+' at --dt 0\.5 is frame 1e\+16, beyond"):
        ingest_csv(path, tmp_path / "ds2", dt=0.5, n_past=4, n_future=6, folds=2, columns=columns)
