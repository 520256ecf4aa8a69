"""Compiled training pieces: one backend, one probe at stage start, one way to fail (stay eager and say why)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import torch

#: torch.compile's backend for the compiled training pieces (the flow's log-density, the GNN's edge block):
#: inductor generates the fused kernels; tests use "aot_eager", which traces the same forward and backward graphs
#: without generating code (seconds, not the minute or two inductor takes on a 2-core CPU).
COMPILE_BACKEND = "inductor"

Function = TypeVar("Function", bound=Callable[..., torch.Tensor])


def compile_probed(function: Function, probe: Callable[[Function], object], *,
                   dynamic: bool) -> tuple[Function | None, str | None]:
    """`function` compiled by torch.compile (whole graph, static or `dynamic` shapes) and tried once by `probe`,
    which calls it forward and backward: compiling is lazy, and a machine that cannot compile (no C++ compiler)
    should find out at stage start, not in the middle of a run. Returns (compiled, None), or (None, the reason in
    one line) when compiling or the probe failed."""
    compiled = torch.compile(function, backend=COMPILE_BACKEND, dynamic=dynamic, fullgraph=True)
    try:
        probe(compiled)
    except Exception as error:  # noqa: BLE001 -- compilers fail in many ways; every one means "stay eager"
        message = str(error).strip()
        return None, f"{type(error).__name__}: {message.splitlines()[0] if message else ''}"
    return compiled, None
