"""A finished run as it stood at an earlier epoch: a copy of a published run whose final model holds the best
weights of one of its earlier training states, for `trajflow eval` (the figures of README.md, "Longer training").

    git show ba9f76a:docs/results/eth_ucy_ours/unfinished/trajflow-eth-s2/checkpoints/state.pt > e7.pt
    python docs/results/eth_ucy_ours/earlier_weights.py docs/results/eth_ucy_ours/models/trajflow-eth-s2 e7.pt \
        probe/eth-s2-e7
    trajflow eval probe/eth-s2-e7

The published resume states of a run that later finished are such earlier states: they hold the weights the run
would have kept had it stopped there (the stage's lowest validation loss so far), and resuming from them is
bit-identical to the run going on, so the copy differs from the finished run in its training length alone.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from trajflow_pipeline.model.checkpoint import load_model, load_training_state, save_model
from trajflow_pipeline.rundir import CONFIG_FILE, FINAL_DIR, LOG_FILE, RUN_FILE


def earlier_copy(run: Path, state_file: Path, out: Path) -> dict:
    """Write `out`: `run`'s config and log, and a final model with the best weights of `state_file`.

    Returns the state's stage, epoch, best epoch and best validation loss, which run.json records as `best`.
    """
    model = load_model(run / FINAL_DIR)
    state = load_training_state(state_file, expected_model=model.name)
    model.load_state_dict(state["best_weights"], strict=True)
    stage = "flow" if state["stage_index"] == 1 else "autoencoder"
    shutil.rmtree(out, ignore_errors=True)
    (out / FINAL_DIR).mkdir(parents=True)
    for name in (CONFIG_FILE, LOG_FILE):
        shutil.copy(run / name, out / name)
    save_model(model, out / FINAL_DIR)
    info = json.loads((run / RUN_FILE).read_text())
    info.pop("rank_weight_digests", None)  # the digests of the finished run's weights, not these
    summary = {"stage": stage, "epoch": state["epoch"], "best_epoch": state["best_epoch"],
               "best_val_loss": state["best_val"]}
    info["best"] = {**info.get("best", {}), stage: {"epoch": state["best_epoch"], "val_loss": state["best_val"]}}
    info["earlier_weights"] = {**summary, "state": str(state_file), "finished_run": str(run)}
    (out / RUN_FILE).write_text(json.dumps(info, indent=1) + "\n")
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a finished run (e.g. docs/results/eth_ucy_ours/models/RUN)")
    parser.add_argument("state", type=Path, help="an earlier checkpoints/state.pt of that run")
    parser.add_argument("out", type=Path, help="the copy to write (replaced if it exists)")
    args = parser.parse_args()
    print(earlier_copy(args.run, args.state, args.out))


if __name__ == "__main__":
    main()
