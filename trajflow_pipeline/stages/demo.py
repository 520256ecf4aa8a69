"""`trajflow demo`: the whole pipeline on built-in data in minutes, ending with a report.

Ingests the synthetic bimodal set, trains TrajFlow and the baselines (trajflow-no-ae, flomo, cv) with the small
budget of the built-in `demo` experiment config, evaluates them and writes the report. Everything lands under
one output directory; re-running resumes (finished runs are skipped).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from ..util.atomic import atomic_write_text
from .experiment import run_experiment
from .report import report

DEMO_CONFIG = "demo.toml"


def builtin_config(name: str) -> str:
    """Text of a config shipped inside the package (trajflow_pipeline/configs/)."""
    return resources.files("trajflow_pipeline.configs").joinpath(name).read_text()


def demo(out: str | Path = "trajflow-demo", *, device: str = "auto", quiet: bool = False) -> Path:
    """Run the demo into `out`; returns the report directory."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    config = out / DEMO_CONFIG
    data = (out / "data" / "synthetic_bimodal").resolve()
    atomic_write_text(config, builtin_config(DEMO_CONFIG).replace("@DATA@", data.as_posix()))
    experiment = run_experiment(config, out / "experiment", device=device, quiet=quiet)
    return report([experiment], out / "report", quiet=quiet)
