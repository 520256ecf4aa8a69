"""DDP training: two CPU processes with the gloo backend end with identical weights; rank 0 writes the run."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import torch
import torch.multiprocessing as mp

from trajflow_pipeline import data as data_module
from trajflow_pipeline.model import load_model
from trajflow_pipeline.model.toy import bimodal_batch
from train_fakes import FakeProblems

OVERRIDES = ["train.ae_min_epochs=0", "train.flow_min_epochs=0", "train.ae_max_epochs=2",
             "train.flow_max_epochs=2", "train.ae_batch_size=16", "train.flow_batch_size=16", "model.flow_layers=4",
             "model.flow_hidden=[16, 16]", "model.gnn_layers=2",
             # the closed-form standardize stage runs on every rank; its buffers must agree too
             "model.flow_standardize=true"]


def _fake_load_problems(dataset_dir: object, fold: str | None = None, split: str = "train") -> FakeProblems:
    n = 61 if split == "train" else 13            # odd sizes: shards are padded to equal length
    batch, _ = bimodal_batch(n, seed=0 if split == "train" else 1, neighbours=2)
    return FakeProblems(batch=batch, n_past=batch.n_past, n_future=batch.n_future)


def _worker(rank: int, world: int, port: int, out: str) -> None:
    os.environ.update({"RANK": str(rank), "LOCAL_RANK": str(rank), "WORLD_SIZE": str(world),
                       "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)})
    torch.set_num_threads(1)
    data_module.load_problems = _fake_load_problems
    from trajflow_pipeline.training import train

    train(Path(out) / "data", Path(out) / "run", model="trajflow", device="cpu", overrides=OVERRIDES, quiet=True)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def test_two_gloo_processes_end_with_identical_weights(tmp_path: Path) -> None:
    mp.start_processes(_worker, args=(2, _free_port(), str(tmp_path)), nprocs=2, join=True, start_method="spawn")
    run = tmp_path / "run"
    info = json.loads((run / "run.json").read_text())
    assert info["world_size"] == 2 and info["status"] == "finished"
    digests = info["rank_weight_digests"]
    assert len(digests) == 2 and digests[0] == digests[1] and info["ranks_consistent"]
    assert (run / "final" / "model.safetensors").is_file()
    assert load_model(run / "final").stages == ("autoencoder", "standardize", "flow")
