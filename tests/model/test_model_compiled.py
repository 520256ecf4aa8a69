"""model/compiled.py's kept kernels, against torch itself: what one process compiled, handed to another whose
inductor cache has lost its compiled graphs, is found there instead of being generated again."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

#: compiles one small function with inductor, after preloading the kernels in
#: argv[2] when there are any, prints torch's FX-graph cache counts, and writes the kernels it has to argv[1]
_PROCESS = """
import json, sys
from pathlib import Path
import torch
from torch._dynamo.utils import counters
from trajflow_pipeline.model.compiled import compiled_kernels, preload_kernels

if len(sys.argv) > 2:
    preload_kernels(Path(sys.argv[2]).read_bytes())
torch.compile(lambda x: torch.tanh(x) * 2, backend="inductor", fullgraph=True)(torch.randn(8))
kernels = compiled_kernels()
Path(sys.argv[1]).write_bytes(kernels or b"")
print(json.dumps({key: value for key, value in counters["inductor"].items() if key.startswith("fxgraph_cache")}))
"""


def _compile_in_fresh_process(cache: Path, *arguments: Path) -> dict[str, int]:
    """Run _PROCESS in a new interpreter with `cache` as inductor's cache directory; its cache counts."""
    environment = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(cache)}
    done = subprocess.run([sys.executable, "-c", _PROCESS, *map(str, arguments)], capture_output=True, text=True,
                          env=environment, timeout=600)
    if done.returncode != 0 and "C++ compiler" in done.stderr:
        pytest.skip("inductor needs a C++ compiler, and this machine has none")
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_kept_kernels_spare_a_fresh_process_generating_them(tmp_path: Path) -> None:
    cache = tmp_path / "inductor"
    first = _compile_in_fresh_process(cache, tmp_path / "kernels-a")
    assert first.get("fxgraph_cache_miss", 0) == 1 and first.get("fxgraph_cache_hit", 0) == 0
    assert (tmp_path / "kernels-a").read_bytes()
    # the compiled graphs gone (as on another machine); inductor's other files stay, which only saves time here
    shutil.rmtree(cache / "fxgraph")
    second = _compile_in_fresh_process(cache, tmp_path / "kernels-b", tmp_path / "kernels-a")
    assert second.get("fxgraph_cache_hit", 0) == 1 and second.get("fxgraph_cache_miss", 0) == 0
    assert (tmp_path / "kernels-b").read_bytes()                       # still there to keep for the next process
