"""torch's thread count follows the CPUs other processes leave idle (console script), or --threads."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from trajflow_pipeline.cli import app as cli
from trajflow_pipeline.model.runtime import _cpu_times, busy_cpus, fit_threads_to_idle_cpus, map_in_threads


@pytest.fixture
def restore_threads(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    before = torch.get_num_threads()
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    yield
    torch.set_num_threads(before)


def test_cpu_counters_are_read_from_the_first_line(tmp_path: Path) -> None:
    stat = tmp_path / "stat"
    # user nice system idle iowait irq softirq steal guest guest_nice
    stat.write_text("cpu  100 5 20 800 40 3 2 0 7 0\ncpu0 50 2 10 400 20 1 1 0 3 0\n")
    assert _cpu_times(stat) == (130, 970)
    stat.write_text("intr 1 2 3\n")
    assert _cpu_times(stat) is None
    assert _cpu_times(tmp_path / "missing") is None


def test_busy_cpus_falls_back_to_the_load_average_when_counters_do_not_move(tmp_path: Path) -> None:
    stat = tmp_path / "stat"
    stat.write_text("cpu  100 5 20 800 40 3 2 0 0 0\n")
    assert busy_cpus(0.0, stat=stat) == pytest.approx(os.getloadavg()[0], abs=0.5)


def test_busy_cpus_on_this_machine_is_within_its_cpus() -> None:
    busy = busy_cpus(0.05)
    assert busy is not None and 0.0 <= busy <= (os.cpu_count() or 1) + 0.5


@pytest.mark.parametrize(("busy", "expected"), [(0.0, None), (0.4, None), (0.6, 1), (1.9, 1), (7.0, 1)])
def test_threads_are_lowered_to_the_idle_cpus(restore_threads: None, monkeypatch: pytest.MonkeyPatch,
                                              busy: float, expected: int | None) -> None:
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    torch.set_num_threads(2)
    lowered = fit_threads_to_idle_cpus(busy)
    assert lowered == (None if expected is None else (2, expected))
    assert torch.get_num_threads() == (2 if expected is None else expected)


def test_a_user_thread_setting_is_kept(restore_threads: None, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    torch.set_num_threads(2)
    assert fit_threads_to_idle_cpus(2.0) is None and torch.get_num_threads() == 2


def test_threads_option_sets_torch_threads_and_rejects_zero(restore_threads: None, tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(cli.app, ["--threads", "1", "eval", str(tmp_path / "no-run")])
    assert result.exit_code == 1 and "run directory not found" in result.output
    assert torch.get_num_threads() == 1
    result = runner.invoke(cli.app, ["--threads", "0", "eval", str(tmp_path / "no-run")])
    assert result.exit_code == 2 and "--threads" in result.output


def test_console_script_lowers_threads_for_model_commands_only(restore_threads: None,
                                                              monkeypatch: pytest.MonkeyPatch,
                                                              tmp_path: Path) -> None:
    calls: list[str] = []
    monkeypatch.setattr("trajflow_pipeline.model.runtime.fit_threads_to_idle_cpus",
                        lambda: calls.append("fit") or (2, 1))
    runner = CliRunner()
    console_script = {"auto_threads": True}  # what main() gives the app
    result = runner.invoke(cli.app, ["eval", str(tmp_path / "no-run")], obj=console_script)
    assert calls == ["fit"] and "1 torch thread(s) instead of 2" in result.output
    runner.invoke(cli.app, ["inspect", str(tmp_path / "no-data")], obj=console_script)
    assert calls == ["fit"]


def test_map_in_threads_keeps_order_grad_mode_and_the_thread_count(restore_threads: None) -> None:
    """On a CPU with two torch threads the items run in two Python threads at one torch thread each, in order,
    with the caller's gradient mode; the thread count is restored afterwards, also when an item fails."""
    import threading

    torch.set_num_threads(2)
    seen: list[tuple[int, bool, int, str]] = []

    def work(item: int) -> int:
        seen.append((item, torch.is_grad_enabled(), torch.get_num_threads(), threading.current_thread().name))
        return item * item

    with torch.no_grad():
        assert map_in_threads(work, list(range(6)), torch.device("cpu")) == [i * i for i in range(6)]
    assert torch.get_num_threads() == 2
    assert {grad for _, grad, _, _ in seen} == {False} and {threads for _, _, threads, _ in seen} == {1}
    assert all(name.startswith("trajflow-chunk") for *_, name in seen)

    def fail(item: int) -> int:
        raise ValueError(f"item {item}")

    with pytest.raises(ValueError, match="item"):
        map_in_threads(fail, [1, 2], torch.device("cpu"))
    assert torch.get_num_threads() == 2


def test_map_in_threads_runs_in_the_caller_with_one_thread_or_one_item(restore_threads: None) -> None:
    import threading

    caller = threading.current_thread().name
    torch.set_num_threads(1)
    assert map_in_threads(lambda _: threading.current_thread().name, [1, 2], torch.device("cpu")) == [caller] * 2
    torch.set_num_threads(2)
    assert map_in_threads(lambda _: threading.current_thread().name, [1], torch.device("cpu")) == [caller]
