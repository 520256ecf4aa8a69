"""`trajflow ingest levelx exid`: exiD (levelX recordings of highway entries and exits) as a unified Parquet dataset,
with the image as the map: every road user of the chosen classes (``--problems all-agents``, the only problems: the
framework has no exiD scenario), 15 past / 25 future steps at 0.2 s, 5 folds of whole agents. The specification:
docs/datasets/levelx.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from .base import Ingest
from .levelx import LAYOUTS
from .levelx_pipeline import (ALL_AGENTS, MOTOR_CLASSES, FOLDS, STRIDE, Horizons, check_problems, ingest_levelx,
                              parse_classes, wrote_line)

DATASET = "exid"
DT = 0.2
N_PAST, N_FUTURE = 15, 25
LAYOUT = LAYOUTS[DATASET]


def ingest_exid(raw: str | Path, out: str | Path, *, recordings: Sequence[int | str] | None = None,
               problems: str = ALL_AGENTS, classes: Sequence[str] | str | None = None, stride: int | None = None,
               overwrite: bool = False, quiet: bool = False) -> Path:
    """Ingest exiD recordings from `raw` (a folder, its data/ sub-folder or one recording's file) into `out`:
    every road user of `classes` every `stride` frames."""
    check_problems(problems, (), None, None)
    return ingest_levelx(LAYOUT, raw, out, horizons=Horizons(DT, N_PAST, N_FUTURE), scenario=None,
                         classes=parse_classes(classes, MOTOR_CLASSES), stride=stride or STRIDE,
                         recordings=recordings, overwrite=overwrite, quiet=quiet)


ADAPTER = Ingest(name=DATASET, dataset=DATASET, dt=DT, folds=tuple(str(fold) for fold in range(FOLDS)),
                 raw="the folder of levelX exiD recordings", function=ingest_exid, summary=wrote_line)
