"""A machine without a working compiler, for the tests of what compiled pieces do when compiling fails."""

from __future__ import annotations

import pytest
import torch

#: the one line a compiled piece should report for the failure below
NO_COMPILER = "RuntimeError: InductorError: no working C++ compiler found"


def without_compiler(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make torch.compile return functions that fail on their first call, as inductor does without a C++
    compiler (compiling is lazy), with a message of two lines."""
    def compile_that_fails(function: object, **options: object) -> object:
        def fails(*inputs: object) -> None:
            raise RuntimeError("InductorError: no working C++ compiler found\ndetails")
        return fails

    monkeypatch.setattr(torch, "compile", compile_that_fails)
