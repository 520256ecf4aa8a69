"""The one list of ingests: registry name -> adapter module, imported only when its adapter is asked for (so the
CLI starts without loading every dataset's dependencies)."""

from __future__ import annotations

import importlib

from ..errors import UsageError
from .base import Ingest

#: registry name -> the module of trajflow_pipeline.ingest whose ADAPTER it is
_MODULES = {"eth-ucy": "eth_ucy", "synthetic-bimodal": "synthetic", "csv": "csv", "round": "round",
            "nuscenes": "nuscenes", "forking-paths": "forking_paths", "highd": "highd", "ind": "ind", "exid": "exid",
            "unid": "unid"}
#: the levelX family (``trajflow ingest levelx MEMBER``; rounD also as ``trajflow ingest round``)
LEVELX = ("round", "highd", "ind", "exid", "unid")
#: every registered ingest, in the order the CLI lists them
NAMES = tuple(_MODULES)


def get_ingest(name: str) -> Ingest:
    """The adapter registered as `name`; an unknown name is a UsageError listing the registered ones."""
    module = _MODULES.get(name)
    if module is None:
        raise UsageError(f"unknown ingest {name!r}; choose from {', '.join(NAMES)}")
    adapter: Ingest = importlib.import_module(f"{__package__}.{module}").ADAPTER
    return adapter
