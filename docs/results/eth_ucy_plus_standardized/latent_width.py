"""How wide the flows of published twin runs draw in their latent space, on training, validation and test
problems (README.md, "In the latent space").

    python docs/results/eth_ucy_plus_standardized/latent_width.py zara1-s2 docs/results/eth_ucy_plus_standardized \
        docs/results/eth_ucy_ours docs/results/eth_ucy_plus_standardized_tail15

The first folder's run must have a standardized flow (`model.flow_standardize`): its `flow.shift` and
`flow.scale` (the training latents' means and standard deviations) are the units of every figure, for every
run. All runs must share one autoencoder (twins: the same targets for the same problems), else the script stops.
For each split it takes the same 1,500 problems (seeded), draws 100 latents per problem from each run's flow
with its own sampling temperature, and prints, averaged over problems and latent dimensions:

- truth std: the spread of the true latents over the problems (1 on the training split, by construction);
- outside 5: the share of problems whose true latent lies beyond 5 standard deviations in some dimension (beyond
  the splines of a flow standardized with tail bound 5, where it can put almost no mass);
- per run, cond width: the standard deviation of its 100 draws per problem (the width of its conditional
  distribution), and centre rmse: the root mean square distance of the draws' mean from the true latent.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from trajflow_pipeline.data import load_problems
from trajflow_pipeline.model.batch import SceneBatch
from trajflow_pipeline.model.checkpoint import load_model
from trajflow_pipeline.model.models import FlowModel
from trajflow_pipeline.rundir import FINAL_DIR

PROBLEMS = 1500
DRAWS = 100


def latent_figures(models: dict[str, FlowModel], batch: SceneBatch, generator: torch.Generator
                   ) -> tuple[float, float, dict[str, tuple[float, float]]]:
    """The true latents' std and share outside ±5, and per model its draws' (cond width, centre rmse), all in the
    first model's standardized units (see the module docstring)."""
    reference = next(iter(models.values()))
    shift, scale = reference.flow.shift, reference.flow.scale
    truth = (reference.targets(reference.normalize(batch)) - shift) / scale
    outside = float((truth.abs() > 5).any(dim=1).float().mean())
    per_model = {}
    for name, model in models.items():
        norm = model.normalize(batch)
        if not torch.allclose((model.targets(norm) - shift) / scale, truth, atol=1e-4):
            raise SystemExit(f"error: {name}: its autoencoder is not the first run's; compare twins only")
        context = model.context(batch, norm.frame, norm.local_past)
        temperature = model.sampling_temperature()
        noise = model.flow.noise(context, DRAWS, generator, temperature)
        draws = (model.flow.from_noise(noise, context, temperature)[0] - shift) / scale      # (draws, problems, D)
        centre = (draws.mean(dim=0) - truth).pow(2).mean().sqrt()
        per_model[name] = (float(draws.std(dim=0).mean()), float(centre))
    return float(truth.std(dim=0).mean()), outside, per_model


def split_line(models: dict[str, FlowModel], data: Path, fold: str, split: str, seed: int = 0) -> str:
    """The figures of `PROBLEMS` seeded problems of `split` as one line."""
    generator = torch.Generator().manual_seed(seed)
    batch = load_problems(data, fold=fold, split=split).batch
    batch = batch.index(torch.randperm(len(batch), generator=generator)[:PROBLEMS])
    truth_std, outside, per_model = latent_figures(models, batch, generator)
    return (f"{split:5s} ({len(batch)} problems): truth std {truth_std:.3f}, outside 5 {outside:.4f}"
            + "".join(f" | {name}: cond width {width:.3f}, centre rmse {centre:.3f}"
                      for name, (width, centre) in per_model.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("fold_seed", help="FOLD-SEED of the runs, e.g. zara1-s2")
    parser.add_argument("folders", nargs="+", type=Path,
                        help="published folders holding models/trajflow-FOLD-SEED, the standardized one first")
    parser.add_argument("--data", type=Path, default=Path("data/eth_ucy"), help="the dataset (default: %(default)s)")
    args = parser.parse_args()
    fold = args.fold_seed.rsplit("-s", 1)[0]
    torch.set_num_threads(1)
    models: dict[str, FlowModel] = {}
    for folder in args.folders:
        final = folder / "models" / f"trajflow-{args.fold_seed}" / FINAL_DIR
        if not final.is_dir():
            raise SystemExit(f"error: {final}: no published model of trajflow-{args.fold_seed} in {folder}")
        models[folder.name] = load_model(final).eval()
    if not next(iter(models.values())).flow.standardize:
        raise SystemExit(f"error: {args.folders[0]}: the first run's flow is not standardized; it sets the units")
    with torch.no_grad():
        for split in ("train", "val", "test"):
            print(split_line(models, args.data, fold, split), flush=True)


if __name__ == "__main__":
    main()
