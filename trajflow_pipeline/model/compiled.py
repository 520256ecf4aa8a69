"""Compiled training pieces: one backend, one probe at stage start, one way to fail (stay eager and say why), and
the compiled kernels as bytes that a run keeps, so that it generates them once."""

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


def compiled_kernels() -> bytes | None:
    """The kernels this process has compiled or found in torch's local cache so far, as torch.compiler's portable
    cache artifacts (None when there are none, e.g. with a backend that generates no code). A run keeps them beside
    its training state: handed to :func:`preload_kernels` in a later process, on this machine or another of the
    same kind, they spare inductor generating and building them again (measured on a 2-core AMD EPYC, the
    fold-eth flow stage: 90 s cold, 57 s with the kernels preloaded into an empty cache, 26 s with inductor's own
    cache warm; what remains is torch re-tracing the graphs, which its autograd cache does not keep for graphs
    that hold custom autograd Functions, as ours do)."""
    saved = torch.compiler.save_cache_artifacts()
    return saved[0] if saved is not None and saved[0] else None


def preload_kernels(kernels: bytes) -> None:
    """Hand kernels from :func:`compiled_kernels` (checked intact by whoever stored them) to torch's compile
    caches, so that the next compile of the same graphs on a machine of the same kind finds them; kernels made
    for other graphs, another torch or another machine are simply never looked up."""
    torch.compiler.load_cache_artifacts(kernels)
