"""Fuzzing the commands with malformed and odd input (hypothesis): every run ends with exit 0, or with exit 1 or 2
and one line naming the file, never a traceback, and nothing already written is lost.

Few examples with a fixed seed by default (the ``ci`` profile in conftest.py); ``pytest --hypothesis-profile long
tests/test_fuzz.py`` searches longer.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner, Result

from trajflow_pipeline.cli.app import app
from trajflow_pipeline.errors import TrajflowError

hypothesis = pytest.importorskip("hypothesis", reason="the fuzz suite needs hypothesis (the dev extra)")
from hypothesis import example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from test_ingest_bad_input import write_flat_eth  # noqa: E402
from test_inspect import write_dataset  # noqa: E402

runner = CliRunner()


def invoke(*args: str | Path) -> Result:
    return runner.invoke(app, [str(arg) for arg in args])


def assert_clean(result: Result, names: str | Path | None = None) -> None:
    """Exit 0; or exit 1 (data) or 2 (usage) with its message on the last line, one ``error:`` line naming
    `names`; never an exception that escaped the command, never a traceback."""
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output, result.output
    if result.exit_code == 0:
        return
    assert result.exit_code in (1, 2), (result.exit_code, result.output)
    lines = [line for line in result.output.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error: ")]
    assert len(errors) == 1 and lines[-1] == errors[0], result.output
    if names is not None:
        assert str(names) in errors[0], (names, errors[0])


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under `folder` with a hash of its bytes: what must not change."""
    return {str(path.relative_to(folder)): hashlib.sha256(path.read_bytes()).hexdigest()
            for path in sorted(folder.rglob("*")) if path.is_file()}


# --- dataset.json --------------------------------------------------------------------------------------------

JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
                    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner,
                                                                                max_size=3),
                    max_leaves=6)


@st.composite
def manifest_variants(draw: st.DrawFn, valid: dict) -> bytes:
    """A damaged dataset.json: one entry replaced or dropped, another JSON value, random or cut bytes."""
    kind = draw(st.sampled_from(["value", "drop", "whole", "bytes", "cut"]))
    if kind in ("value", "drop"):
        manifest, key = dict(valid), draw(st.sampled_from(sorted(valid)))
        if kind == "value":
            manifest[key] = draw(JSON)
        else:
            del manifest[key]
        return json.dumps(manifest).encode()
    if kind == "whole":
        return json.dumps(draw(JSON)).encode()
    if kind == "bytes":
        return draw(st.binary(max_size=64))
    text = json.dumps(valid).encode()
    return text[:draw(st.integers(0, len(text) - 1))]


@pytest.fixture(scope="module")
def toy_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("fuzz") / "toy")


def test_damaged_manifests_are_refused_in_one_line(toy_dataset: Path) -> None:
    from trajflow_pipeline.data.loader import load_problems

    manifest = toy_dataset / "dataset.json"
    valid_bytes = manifest.read_bytes()
    tables = {name: value for name, value in snapshot(toy_dataset).items() if name != "dataset.json"}

    @given(manifest_variants(json.loads(valid_bytes)))
    @example(json.dumps({**json.loads(valid_bytes), "dt": float("nan")}).encode())
    @example(json.dumps({**json.loads(valid_bytes), "counts": [1, 2]}).encode())
    def check(variant: bytes) -> None:
        manifest.write_bytes(variant)
        try:
            assert_clean(invoke("inspect", toy_dataset), names=toy_dataset)
            try:  # what train and eval read the dataset through
                load_problems(toy_dataset, fold="1", split="train")
            except TrajflowError as error:
                assert str(toy_dataset) in str(error) or "fold" in str(error), error
        finally:
            manifest.write_bytes(valid_bytes)
        assert {k: v for k, v in snapshot(toy_dataset).items() if k != "dataset.json"} == tables

    check()


# --- path names ----------------------------------------------------------------------------------------------

#: legal file names: any characters but '/' and NUL (and lone surrogates, which no file system name decodes to)
NAMES = (st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="/\x00"), min_size=1,
                 max_size=40)
         .filter(lambda name: name not in (".", "..") and len(os.fsencode(name)) <= 255))


@given(NAMES)
@settings(max_examples=max(10, settings.default.max_examples // 3))  # an example is four commands (15 s for 30)
@example("run[1] *?.csv")
@example(":100: [red]x[bold] :thumbs_up:")
@example("é" * 127)             # 254 bytes
@example("n" * 255)
@example("-starts-like-an-option")
def test_any_legal_name_is_a_name(tmp_path_factory: pytest.TempPathFactory, name: str) -> None:
    """A dataset written under any legal name inspects, augments into another odd name, and leaves no sibling."""
    parent = tmp_path_factory.mktemp("names")
    data = parent / name
    assert_clean(result := invoke("ingest", "synthetic-bimodal", "--samples", "20", "-o", data, "--quiet"))
    assert result.exit_code == 0 and sorted(os.listdir(parent)) == [name]
    inspected = invoke("inspect", data, "--json")
    assert inspected.exit_code == 0, inspected.output
    assert json.loads(inspected.output)["dataset"] == "synthetic_bimodal"
    augmented = parent / "augmented" / name
    assert invoke("augment", "scale-rotate", data, "-o", augmented, "--copies", "2", "--quiet").exit_code == 0
    assert invoke("inspect", augmented).exit_code == 0
    assert sorted(os.listdir(parent)) == sorted([name, "augmented"]) and os.listdir(parent / "augmented") == [name]


# --- ETH/UCY text ------------------------------------------------------------------------------------------

TOKENS = st.one_of(st.integers(-3, 40).map(lambda v: f"{10.0 * v:.1f}"),
                   st.floats(allow_nan=True, allow_infinity=True, width=64).map(repr),
                   st.sampled_from(["", "nan", "1e300", "-0", ":100:", "[red]x[/]", "\f", "\u2028", "\x85",
                                    "\x00", "é", "0x10", "1,5"]),
                   st.text(max_size=4))
LINES = st.builds(lambda tokens, sep, end: sep.join(tokens) + end, st.lists(TOKENS, min_size=0, max_size=5),
                  st.sampled_from(["\t", " ", "\t\t", ","]), st.sampled_from(["\n", "\r\n"]))


@pytest.fixture(scope="module")
def flat_eth(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_flat_eth(tmp_path_factory.mktemp("eth") / "raw", peds=2, frames=22)


@given(st.lists(LINES, max_size=8), st.integers(0, 40))
def test_malformed_eth_ucy_text_is_refused_in_one_line(flat_eth: Path, tmp_path_factory: pytest.TempPathFactory,
                                                      lines: list[str], at: int) -> None:
    """Random lines put into a valid sequence: a clean result, or one line naming the file."""
    raw = Path(shutil.copytree(flat_eth, tmp_path_factory.mktemp("raw") / "raw"))
    target = raw / "biwi_eth.txt"
    valid = target.read_bytes().decode().splitlines(keepends=True)
    at = min(at, len(valid))
    target.write_bytes("".join(valid[:at] + lines + valid[at:]).encode("utf-8", errors="surrogatepass"))
    before = snapshot(raw)
    out = raw.parent / "out"
    result = invoke("ingest", "eth-ucy", raw, "-o", out, "--quiet")
    assert_clean(result, names=target if result.exit_code == 1 and str(target) in result.output else None)
    assert snapshot(raw) == before
    assert sorted(os.listdir(raw.parent)) == (["out", "raw"] if result.exit_code == 0 else ["raw"])


BAD_LINES = ["abc\t1.0\t2.0\t3.0\n", "100.0\t1.0\n", "105.0\t1.0\t0.5\t0.5\n", "100.0\t1.0\tnan\t0.5\n",
             "100.0\t1.5\t0.5\t0.5\n", "100.0\t1.0\t1e400\t0.5\n"]


@given(st.sampled_from(BAD_LINES), st.integers(0, 43), st.sampled_from(["\n", "\r\n"]))
def test_a_bad_line_is_named_by_its_number(flat_eth: Path, tmp_path_factory: pytest.TempPathFactory, bad: str,
                                           at: int, ending: str) -> None:
    """One bad line among valid ones: the error names exactly its line (as an editor counts lines)."""
    raw = Path(shutil.copytree(flat_eth, tmp_path_factory.mktemp("raw") / "raw"))
    target = raw / "biwi_eth.txt"
    valid = target.read_text().splitlines()
    at = min(at, len(valid))
    lines = valid[:at] + [bad.rstrip("\n")] + valid[at:]
    target.write_bytes(ending.join(lines).encode() + ending.encode())
    result = invoke("ingest", "eth-ucy", raw, "-o", raw.parent / "out", "--quiet")
    assert result.exit_code == 1, result.output
    assert_clean(result, names=f"{target}:{at + 1}:")


# --- CSV text ----------------------------------------------------------------------------------------------

CELLS = st.one_of(st.integers(-2, 30).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                  st.sampled_from(["", " ", "nan", "1e300", "-1e39", '"', '"a,b"', '"x\ny"', ":100:", "[red]",
                                   "\f", "\u2028", "\r", "é"]),
                  st.text(max_size=4))
ROWS = st.one_of(st.builds(",".join, st.lists(CELLS, min_size=0, max_size=7)),  # anything
                 st.builds("{},{},{},{},{}".format, st.sampled_from(["s0", "s1", "s2"]) | CELLS,  # rows almost right
                           st.integers(0, 3).map(str) | CELLS, st.integers(0, 30).map(str) | CELLS,
                           st.floats(-10, 10).map(repr) | CELLS, st.floats(-10, 10).map(repr) | CELLS))


def valid_csv_rows() -> list[str]:
    """Two scenes of two agents over 12 frames: scene_id,agent_id,frame,x,y."""
    return [f"s{s},{a},{f},{0.4 * f:.2f},{float(a):.1f}" for s in range(2) for a in range(2) for f in range(12)]


@given(st.lists(ROWS, min_size=1, max_size=6), st.integers(0, 48), st.sampled_from(["\n", "\r\n"]),
       st.sampled_from(["folds", "train-is-test"]))
def test_malformed_csv_is_refused_in_one_line(tmp_path_factory: pytest.TempPathFactory, rows: list[str], at: int,
                                              ending: str, protocol: str) -> None:
    """Random rows put into a valid CSV: a clean result, or one line naming the file; the input is never changed
    and a failed ingest leaves nothing."""
    folder = tmp_path_factory.mktemp("csv")
    source = folder / "tracks.csv"
    valid = valid_csv_rows()
    lines = ["scene_id,agent_id,frame,x,y"] + valid[:at] + rows + valid[at:]
    source.write_bytes(ending.join(lines).encode("utf-8", errors="surrogatepass") + ending.encode())
    before = snapshot(folder)
    result = invoke("ingest", "csv", source, "-o", folder / "out", "--dt", "0.4", "--past", "2", "--future", "3",
                    "--protocol", protocol, "--folds", "2", "--split-by", "scene", "--quiet")
    assert_clean(result, names=source if result.exit_code == 1 else None)
    if result.exit_code != 0:
        assert snapshot(folder) == before
    assert sorted(os.listdir(folder)) == (["out", "tracks.csv"] if result.exit_code == 0 else ["tracks.csv"])


# --- run.json ----------------------------------------------------------------------------------------------

TINY_RUN = ["train.ae_max_epochs=1", "train.ae_min_epochs=1", "train.flow_max_epochs=1", "train.flow_min_epochs=1",
            "model.flow_layers=2", "model.flow_hidden=[8]"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from trajflow_pipeline.ingest.synthetic import ingest_synthetic_bimodal
    from trajflow_pipeline.training import train

    data = ingest_synthetic_bimodal(tmp_path_factory.mktemp("data") / "bimodal", samples=40, seed=1, quiet=True)
    return train(data, tmp_path_factory.mktemp("runs") / "run", model="trajflow", overrides=TINY_RUN, quiet=True)


def test_damaged_run_descriptions_are_refused_in_one_line(tiny_run: Path) -> None:
    """run.json variants through eval (distances only, so that a variant that still describes the run is cheap to
    evaluate) and status: a clean result, or one line naming a file of the run."""
    description = tiny_run / "run.json"
    valid_bytes = description.read_bytes()
    weights = snapshot(tiny_run / "final")

    @given(manifest_variants(json.loads(valid_bytes)))
    def check(variant: bytes) -> None:
        description.write_bytes(variant)
        try:
            assert_clean(invoke("eval", tiny_run, "--metric", "min_ade", "--samples", "4", "--k", "2", "--workers",
                                "1", "--quiet"), names=tiny_run)
            assert_clean(invoke("status", tiny_run), names=tiny_run)
        finally:
            description.write_bytes(valid_bytes)
            shutil.rmtree(tiny_run / "eval", ignore_errors=True)
        assert snapshot(tiny_run / "final") == weights

    check()
