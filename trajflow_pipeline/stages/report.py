"""`trajflow report RUN_OR_EXPERIMENT... -o REPORT`: tables, figures and provenance of evaluated runs.

REPORT is written atomically (a complete new report replaces an older one, or nothing changes) and holds:

* ``report.md``    GitHub Markdown; figures linked from ``figures/``;
* ``report.html``  the same content, self-contained (CSS inline, figures as base64 data URIs);
* ``figures/*.png`` examples with drawn futures, the synthetic-bimodal density panel, training curves, minADE(K);
* ``report.json``  the numbers behind the tables and the runs they came from, for scripts.

Per dataset (never one mixed table): one row per model, mean ± std over folds and seeds of each run's aggregate
metric values, the best in bold, the paper's TrajFlow row and plain "met / not met" target lines, with a note
naming the settings in which the runs differ from the paper's (a reduced budget, a change of ours); per-fold
breakdowns; the medians of the unbounded NLL metrics beside their means; then the figures. A provenance section
lists, for every run, what produced its numbers.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import shutil
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
from rich.progress import Progress

from .. import __version__
from ..errors import TrajflowError, UsageError
from ..model.config import RunConfig
from ..report.collect import (PlannedRun, Run, collect, has_draws, load_run, load_train_log, metrics_frame,
                              resolve_inputs, run_medians, scan_ground_truth, scan_predictions, training_seconds)
from ..report.curves import min_ade_curve
from ..report.document import Block, Bullets, Cell, Code, Figure, Heading, Paragraph, Table
from ..report.figures import plot_density, plot_examples, plot_min_ade_k, plot_training
from ..report.paper import OUR_TRAJFLOW, dataset_label, dataset_order, model_label, model_order
from ..report.render import slug, to_html, to_markdown
from ..report.scenes import choose_examples, density_data, example_panels, reference_runs
from ..report.tables import (comparisons, fold_list, fold_stats, fold_tables, model_folds, summary_stats,
                             summary_table, targets, uneven_seeds)
from ..rundir import EVAL_DIR, GROUND_TRUTH_FILE, PREDICTIONS_FILE
from ..util.atomic import atomic_directory
from ..util.progress import duration_text, make_progress

REPORT_FILES = ("report.md", "report.html", "report.json")
FIGURE_DIR = "figures"
BIMODAL = "synthetic_bimodal"

HOW_TO_READ = (
    "minADE / minFDE: average / final displacement (m) of the best of K draws per agent (indep) or of the best "
    "joint draw over the agents predicted together (joint).",
    "NLL: negative log-likelihood (nats) of the ground-truth future under a ROME density fitted on the draws "
    "(flattened future positions in metres), indep per agent and joint over agents predicted together.",
    "JSD: Jensen–Shannon divergence between ground-truth and predicted futures within groups of identical "
    "inputs, in [0, 1] (natural-log JSD / ln 2).",
    "Every metric: lower is better. mean ± std: over all runs (folds × seeds) of a model, population std "
    "(ddof 0); a single run shows its value alone. —: not evaluated.",
)


def _check_out(out: Path, run_paths: list[Path]) -> None:
    """Refuse an output that would destroy an input run or anything other than an older report."""
    target = out.resolve()
    for path in run_paths:
        resolved = path.resolve()
        if resolved == target or target in resolved.parents:
            raise TrajflowError(f"{out}: the report would replace the input run {path}; choose another --out")
    if out.exists():
        if not out.is_dir():
            raise TrajflowError(f"{out}: exists and is not a directory; choose another --out")
        if any(out.iterdir()) and not any((out / name).is_file() for name in REPORT_FILES):
            raise TrajflowError(f"{out}: exists and is not a trajflow report; choose another --out or remove it")


def _keep_other_files(out: Path, tmp: Path) -> None:
    """Copy what an older report directory holds besides the report itself (e.g. the config and the trained models
    committed beside it) into the new one, so that regenerating a report loses nothing. Copies, not moves: until
    the new directory replaces it, the old one stays whole."""
    if not out.is_dir():
        return
    for entry in out.iterdir():
        if entry.name in (*REPORT_FILES, FIGURE_DIR):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.copytree(entry, tmp / entry.name, symlinks=True)
        else:
            shutil.copy2(entry, tmp / entry.name, follow_symlinks=False)


def _common(values: list[Any]) -> Any | None:
    """The value shared by every element, or None when they differ (or the list is empty)."""
    return values[0] if values and all(v == values[0] for v in values) else None


def _plural(count: int, word: str) -> str:
    """`1 run`, `2 runs`."""
    return f"{count} {word}{'' if count == 1 else 's'}"


def _counts(values: list[Any]) -> str:
    """`a (n), b (m)` in descending frequency."""
    return ", ".join(f"{value} ({count})" for value, count in Counter(values).most_common())


def _describe(runs: list[Run]) -> str:
    """One sentence saying which runs a dataset section aggregates."""
    models = ", ".join(model_label(m) for m in model_order([r.model for r in runs]))
    folds = sorted({r.fold for r in runs if r.fold is not None})
    seeds = sorted({r.seed for r in runs})
    parts = [f"{_plural(len(runs), 'run')} ({models})",
             f"folds {', '.join(folds)}" if folds else "no folds (one test set)",
             f"seeds {', '.join(map(str, seeds))}"]
    draws, k = _common([r.draws for r in runs]), _common([r.k for r in runs])
    if draws is not None:
        parts.append(f"{draws} draws per problem")
    if k is not None:
        parts.append(f"minADE/minFDE over K = {k} of them")
    return "; ".join(parts) + "."


def _consistency_notes(runs: list[Run]) -> list[str]:
    """Warnings about runs that should not silently be averaged together."""
    notes = []
    if len({r.k for r in runs}) > 1:
        notes.append(f"Runs use different K: {_counts([r.k for r in runs])}; minADE/minFDE mix them.")
    if len({r.draws for r in runs}) > 1:
        notes.append(f"Runs use different numbers of draws: {_counts([r.draws for r in runs])}.")
    skipped = sum(int(r.info.get("jsd_groups_skipped") or 0) for r in runs)
    identical = sum(int(r.info.get("jsd_groups_identical_futures") or 0) for r in runs)
    if skipped or identical:
        evaluated = sum(int(r.info.get("jsd_groups") or 0) for r in runs)
        reasons = [f"{skipped} with a single ground-truth future"] * bool(skipped) + [
            f"{identical} whose ground-truth futures are all the same"] * bool(identical)
        notes.append(f"JSD skipped {' and '.join(reasons)} (identical-input groups; evaluated on {evaluated} "
                     "group(s) with different futures), summed over runs.")
    notes += _evaluation_warnings(runs)
    repeated = Counter((r.model, r.fold, r.seed) for r in runs)
    for (model, fold, seed), count in sorted(repeated.items(), key=str):
        if count > 1:
            notes.append(f"{model_label(model)} fold {fold or '—'} seed {seed} appears in {count} runs; each counts "
                         "in mean ± std.")
    return notes


def _evaluation_warnings(runs: list[Run]) -> list[str]:
    """What the evaluations warned about (eval.json `warnings`, e.g. a truncated horizon), each once with the runs
    it concerns, and ROME's PCA fallbacks (eval.json `rome_*`) summed over runs."""
    notes = []
    for suffix, what in (("", "the metrics"), ("_ext", "the extended-horizon (_ext) metrics")):
        recorded = [r for r in runs if isinstance(r.info.get(f"rome_fits{suffix}"), int)]
        fallback_fits = sum(int(r.info.get(f"rome_fallback_fits{suffix}") or 0) for r in recorded)
        if fallback_fits:
            fits = sum(int(r.info[f"rome_fits{suffix}"]) for r in recorded)
            unrecorded = len(runs) - len(recorded) if suffix == "" else 0
            notes.append(f"{fallback_fits} of {fits} ROME density fits for {what}, summed over runs, re-ran a failed "
                         "PCA with added jitter (ROME's own fallback for a singular cluster)"
                         + (f"; {_plural(unrecorded, 'run')} evaluated before such fits were counted"
                            if unrecorded else "") + ".")
    concerned: dict[str, list[str]] = {}
    for run in runs:
        for warning in run.info.get("warnings") or ():
            concerned.setdefault(str(warning), []).append(run.name)
    notes += [f"Evaluation warning ({', '.join(names)}): {warning}" for warning, names in concerned.items()]
    return notes


#: config keys that say which run it is or where it ran, not how its model was made
_RUN_IDENTITY = {("model", "name"), ("train", "seed"), ("train", "device"), ("train", "compile_flow"),
                 ("train", "eval_batch_size")}


def _paper_deviations(runs: list[Run]) -> list[str]:
    """The settings in which the runs' configs (eval.json `config`) differ from the paper's, which are the built-in
    defaults: a reduced training budget or a change of ours must show next to the numbers it produced."""
    paper = RunConfig().to_dict()
    where: dict[tuple[str, str, str], list[Run]] = {}
    for run in runs:
        config = run.info.get("config")
        for section, values in (config.items() if isinstance(config, dict) else ()):
            for key, value in (values.items() if isinstance(values, dict) else ()):
                default = paper.get(section, {}).get(key)
                if (section, key) not in _RUN_IDENTITY and key in paper.get(section, {}) and value != default:
                    where.setdefault((section, key, json.dumps(value)), []).append(run)
    notes = []
    for (section, key, value), members in sorted(where.items()):
        models = ", ".join(model_label(m) for m in model_order([r.model for r in members]))
        scope = "all runs" if len(members) == len(runs) else f"{_plural(len(members), 'run')} ({models})"
        notes.append(f"{section}.{key} = {value} (paper: {json.dumps(paper[section][key])}) in {scope}")
    return [f"Settings that differ from the paper's: {'; '.join(notes)}."] if notes else []


def _example_figure(dataset: str, refs: dict[str, Run], max_examples: int) -> Figure | None:
    """Chosen samples × models: past, all ground-truth futures of the group, draws by likelihood."""
    first = next(iter(refs.values()))
    index = collect(scan_ground_truth(first).select("sample_id", "group_id"),
                    first.eval_dir / GROUND_TRUTH_FILE)
    sample_ids = choose_examples(index, max_examples)
    if not sample_ids:
        return None
    panels = {model: example_panels(run, sample_ids) for model, run in refs.items()}
    rows = [[panels[model].get(sample_id) for model in refs] for sample_id in sample_ids]
    shown = "; ".join(f"{model_label(m)}: {r.name} ({r.label})" for m, r in refs.items())
    labels = sorted({str(r.info.get("log_lik_label", "model space")) for r in refs.values()})
    caption = (f"{dataset_label(dataset)}: example predictions. Past solid black (dot: last observed position), "
               f"ground truth dashed (every future of the sample's group for multi-future data), draws coloured "
               f"and faded by their log-likelihood (in {', '.join(labels)}; relative within each panel). "
               f"Runs: {shown}.")
    png = plot_examples(rows, list(refs), f"{dataset_label(dataset)}: examples")
    return Figure(f"{FIGURE_DIR}/{slug(dataset)}-examples.png", png, f"{dataset_label(dataset)}: examples", caption)


def _density_figure(dataset: str, refs: dict[str, Run]) -> Figure | None:
    """Paper Fig. 3 for the synthetic bimodal set: ground truth vs each model's draws, coloured by density."""
    data = density_data(refs)
    if data is None:
        return None
    png = plot_density(data, f"{dataset_label(dataset)}: ground truth vs predicted futures")
    caption = (f"Positions of all future steps: the {data.futures} ground-truth futures of group {data.group_id} "
               f"and up to 3000 draws per model pooled over the group's samples (identical inputs), each point "
               f"coloured by a Gaussian kernel density of its panel's points (paper Fig. 3); shared extent. Runs: "
               + "; ".join(f"{model_label(m)}: {r.name}" for m, r in refs.items()) + ".")
    return Figure(f"{FIGURE_DIR}/{slug(dataset)}-density.png", png, f"{dataset_label(dataset)}: density", caption)


def _training_figures(dataset: str, runs: list[Run]) -> tuple[list[Figure], list[str]]:
    """Training curves per model (one panel per stage, one colour per run) and the models without logs."""
    figures, missing = [], []
    for model in model_order([r.model for r in runs]):
        members = sorted((r for r in runs if r.model == model), key=lambda r: (r.fold or "", r.seed))
        logs = [(r.label, log) for r in members if (log := load_train_log(r)) is not None and not log.is_empty()]
        if not logs:
            missing.append(model_label(model))
            continue
        png = plot_training(logs, f"{dataset_label(dataset)}: {model_label(model)} training")
        caption = (f"{model_label(model)} on {dataset_label(dataset)}: training (solid) and validation (dashed) "
                   f"loss per epoch, one panel per stage, {len(logs)} of {len(members)} runs with a log.")
        figures.append(Figure(f"{FIGURE_DIR}/{slug(dataset)}-training-{slug(model)}.png", png,
                              f"{dataset_label(dataset)}: {model_label(model)} training", caption))
    return figures, missing


def _k_curve_figure(dataset: str, runs: list[Run], progress: Progress) -> Figure | None:
    """Expected minADE_K for K = 1..S per model: mean over its runs (band: std over runs)."""
    task = progress.add_task(f"{dataset}: minADE(K)", total=len(runs))
    curves = []
    for model in model_order([r.model for r in runs]):
        per_run = []
        for run in (r for r in runs if r.model == model):
            curve = min_ade_curve(scan_predictions(run), scan_ground_truth(run),
                                  run.eval_dir / PREDICTIONS_FILE)
            per_run.extend([curve] if curve.size else [])
            progress.advance(task)
        if per_run:
            length = min(c.size for c in per_run)
            stacked = np.stack([c[:length] for c in per_run])
            curves.append((model, stacked.mean(axis=0), stacked.std(axis=0) if len(per_run) > 1 else None))
    progress.remove_task(task)
    if not curves:
        return None
    k = _common([r.k for r in runs])
    png = plot_min_ade_k(curves, k, f"{dataset_label(dataset)}: minADE vs K")
    caption = ("Expected minADE_K over random K-subsets of each problem's draws (exact, from the sorted per-draw "
               "ADEs), K = 1..S, mean over problems; line: mean over a model's runs, band: ± std over runs.")
    return Figure(f"{FIGURE_DIR}/{slug(dataset)}-min-ade-vs-k.png", png, f"{dataset_label(dataset)}: minADE vs K",
                  caption)


def _figures(dataset: str, runs: list[Run], max_examples: int, progress: Progress) -> list[Block]:
    """Every figure of one dataset section, with its heading. The figures drawn from draws show the runs that
    still have them (an evaluated copy may not: `has_draws`), and a note names the others."""
    drawn = [run for run in runs if has_draws(run)]
    blocks: list[Block] = [Heading(3, "Figures")]
    found: list[Figure | None] = []
    if drawn:
        refs = reference_runs(drawn)
        found += [_example_figure(dataset, refs, max_examples) if max_examples else None,
                  _density_figure(dataset, refs) if dataset == BIMODAL else None]
    training, without_logs = _training_figures(dataset, runs)
    found += [*training, _k_curve_figure(dataset, drawn, progress) if drawn else None]
    blocks += [figure for figure in found if figure is not None]
    if without_logs:
        blocks.append(Paragraph(f"No training log (train_log.csv / .parquet) for: {', '.join(without_logs)}."))
    if len(drawn) < len(runs):
        without = [run.name for run in runs if not has_draws(run)]
        blocks.append(Paragraph(
            f"No draws ({EVAL_DIR}/{PREDICTIONS_FILE}; an evaluated copy that left them behind) for "
            f"{_plural(len(without), 'run')} ({', '.join(without)}): the figures drawn from draws (examples"
            f"{', density' if dataset == BIMODAL else ''}, minADE vs K) leave them out"
            f"{'' if drawn else ' and are not drawn'}; `trajflow eval RUN` draws them again."))
    return blocks


MEDIANS_OF = "per run the median over agents (joint: over groups), then "
MEDIANS_WHY = (
    "The NLL columns above are means over agents (joint: over groups), as the paper reports them. ROME's "
    "log-densities are finite but unbounded, so a few ground truths far from every draw can move a mean by a lot "
    "(a single value of +2,000 nats among 1,000 moves their mean by about 2). The medians of each run's per-agent "
    "(per-group) values below show the typical problem; the paper gives no medians to compare with.")


def _median_blocks(dataset: str, runs: list[Run], metrics: pl.DataFrame, medians: pl.DataFrame) -> list[Block]:
    """The NLL medians of one dataset (`medians`: :func:`run_medians` of every run, `metrics`: the aggregates): a
    model table and, for folded data, per-fold tables (nothing without NLL), with a note naming the runs that
    report an NLL mean but no per-agent rows to take a median of."""
    values = medians.filter(pl.col("dataset") == dataset)
    if values.is_empty():
        return []
    stats = summary_stats(values)
    blocks: list[Block] = [Heading(3, "NLL medians"), Paragraph(MEDIANS_WHY)]
    missing = _without_medians(metrics.filter(pl.col("dataset") == dataset), values)
    if missing:
        them = "it" if len(missing) == 1 else "them"
        blocks.append(Bullets((f"Note: no per-agent NLL rows to take medians of in {_plural(len(missing), 'run')} "
                               f"({', '.join(missing)}); the medians below leave {them} out.",)))
    blocks.append(summary_table(stats, dataset, of=MEDIANS_OF, paper_row=False))
    if any(r.fold is not None for r in runs):
        for spec, table in fold_tables(fold_stats(values), of=MEDIANS_OF):
            blocks += [Heading(4, f"{spec.label} median, per fold"), table]
    return blocks


def _without_medians(metrics: pl.DataFrame, medians: pl.DataFrame) -> list[str]:
    """Runs with an aggregate of a metric that other runs have medians of, but without a median of their own."""
    reported = metrics.join(medians.select("metric").unique(), on="metric").select("run_index", "run", "metric")
    covered = medians.select("run_index", "metric")
    uncovered = reported.join(covered, on=["run_index", "metric"], how="anti")
    return sorted(uncovered.get_column("run").unique().to_list())


def _expected_folds(runs: list[Run], planned: tuple[PlannedRun, ...]) -> set[str | None]:
    """The folds a dataset section should cover: those of its runs and those planned by the experiments that list
    them (matched by directory: two experiments may share a name)."""
    paths = {r.path.resolve() for r in runs}
    experiments = {p.experiment_dir for p in planned if p.path.resolve() in paths}
    return {r.fold for r in runs} | {p.fold for p in planned if p.experiment_dir in experiments}


def _coverage_notes(expected: set[str | None], folds: dict[str, set[str | None]],
                    seeds: dict[str, dict[str | None, int]]) -> list[str]:
    """Notes on means that are over different things: models without runs on some of the section's folds, and
    models whose folds have different numbers of seeds."""
    notes = []
    short = [f"{model_label(m)} has none on {fold_list(expected - folds[m])}" for m in model_order(list(folds))
             if expected - folds[m]]
    if short:
        judged = (" The paper targets are not judged until TrajFlow has every fold;"
                  if expected - folds.get(OUR_TRAJFLOW, expected) else "")
        notes.append(f"Not every model has runs on every fold yet: {'; '.join(short)}. A mean over fewer folds is "
                     f"not comparable with the paper's or another model's.{judged} TrajFlow is compared with "
                     "another model on the folds both have.")
    if seeds:
        def per_fold(model: str) -> str:
            ordered = sorted(seeds[model].items(), key=lambda item: (item[0] is not None, item[0] or ""))
            return ", ".join(f"{fold_list([fold])} {count}" for fold, count in ordered)

        counts = "; ".join(f"{model_label(m)}: {per_fold(m)}" for m in model_order(list(seeds)))
        notes.append(f"Folds have different numbers of seeds ({counts}). The Results table averages runs; the "
                     "paper targets and the comparisons average each fold's mean over its seeds, so that every "
                     "fold counts once.")
    return notes


def _dataset_section(dataset: str, runs: list[Run], summary: pl.DataFrame, per_fold: pl.DataFrame,
                     values: tuple[pl.DataFrame, pl.DataFrame], planned: tuple[PlannedRun, ...], *, figures: bool,
                     max_examples: int, progress: Progress) -> list[Block]:
    """Tables, targets and figures of one dataset; `values` are every run's aggregates and NLL medians, `planned`
    the runs the experiments plan (finished or not)."""
    label = dataset_label(dataset)
    title = label if label == dataset else f"{label} (`{dataset}`)"
    stats = summary.filter(pl.col("dataset") == dataset)
    folds_stats = per_fold.filter(pl.col("dataset") == dataset)
    expected, folds = _expected_folds(runs, planned), model_folds(folds_stats)
    blocks: list[Block] = [Heading(2, title, anchor=slug(dataset)), Paragraph(_describe(runs))]
    notes = (_consistency_notes(runs) + _paper_deviations(runs)
             + _coverage_notes(expected, folds, uneven_seeds(folds_stats)))
    if notes:
        blocks.append(Bullets(tuple(f"Note: {n}" for n in notes)))
    blocks += [Heading(3, "Results"), summary_table(stats, dataset, _common([r.k for r in runs])),
               Heading(3, "Paper targets (our TrajFlow mean vs the paper's, lower is better)"),
               Bullets(tuple(targets(folds_stats, dataset, expected)))]
    versus = comparisons(folds_stats)
    if versus:
        blocks += [Heading(3, "TrajFlow against our other models (the paper claims better NLL, indep and joint, "
                              "and JSD)"),
                   Bullets(tuple(versus))]
    if any(r.fold is not None for r in runs):
        blocks.append(Heading(3, "Per fold"))
        for spec, table in fold_tables(folds_stats):
            blocks += [Heading(4, spec.label), table]
    blocks += _median_blocks(dataset, runs, *values)
    blocks += _compute(runs)
    if figures:
        blocks += _figures(dataset, runs, max_examples, progress)
    return blocks


def _compute(runs: list[Run]) -> list[Block]:
    """Per model: training and evaluation time summed over runs, and the machines that trained and evaluated them
    (eval.json, from run.json for training; older runs did not record machines)."""
    rows = []
    for model in model_order([r.model for r in runs]):
        members = [r for r in runs if r.model == model]
        trained = [s for r in members if (s := training_seconds(r)) is not None]
        evaluated = [float(r.info["seconds"]) for r in members if isinstance(r.info.get("seconds"), (int, float))]
        trained_on = _distinct(m for r in members for m in (r.info.get("training_machines") or ()))
        evaluated_on = _distinct(r.info["machine"] for r in members if r.info.get("machine"))
        rows.append(tuple(Cell(text) for text in (
            model_label(model), str(len(members)),
            duration_text(sum(trained)) + ("" if len(trained) == len(members) else f" ({len(trained)} runs)")
            if trained else "—",
            duration_text(sum(evaluated)) if evaluated else "—",
            "; ".join(trained_on) or "not recorded", "; ".join(evaluated_on) or "not recorded")))
    return [Heading(3, "Compute"),
            Paragraph("Training: the epoch times of the training logs, summed over runs (several runs may have "
                      "trained at once, so the wall time can be shorter); evaluation: eval.json's seconds, summed."),
            Table(header=("model", "runs", "training", "evaluation", "trained on", "evaluated on"),
                  rows=tuple(rows), numeric=(False, True, True, True, False, False))]


def _distinct(values: Any) -> list[str]:
    """The distinct strings of `values`, in first-seen order."""
    return list(dict.fromkeys(str(v) for v in values))


def _fingerprint_text(fingerprint: Any) -> str:
    """Short form of a data fingerprint for the provenance table (long hashes cut to 12 characters)."""
    if not isinstance(fingerprint, dict) or not fingerprint:
        return "—"
    shown = {k: str(v) for k, v in fingerprint.items() if k != "path"}
    return ", ".join(f"{k}={v[:12] + '…' if len(v) > 16 else v}" for k, v in shown.items())


def _provenance(runs: list[Run]) -> list[Block]:
    """For every run: model, dataset, fold, seed, date, version, data fingerprint, and the full config."""
    header = ("run", "model", "dataset", "fold", "seed", "draws", "K", "evaluated", "trajflow", "data", "path")
    rows = tuple(tuple(Cell(str(v)) for v in (
        run.name, run.model, run.dataset, run.fold or "—", run.seed, run.draws or "—", run.k or "—",
        run.info.get("date", "—"), _code_text(run.info),
        _fingerprint_text(run.info.get("data_fingerprint")), run.path)) for run in runs)
    blocks: list[Block] = [
        Heading(2, "Provenance", anchor="provenance"),
        Paragraph("What produced every number: each run's eval.json (model, data fingerprint, seed, trajflow "
                  "version with the code revisions that trained and evaluated it where recorded, date) and its "
                  "resolved training config."),
        Table(header=header, rows=rows, numeric=(False,) * 4 + (True,) * 3 + (False,) * 4),
    ]
    for run in runs:
        details = {key: run.info.get(key) for key in ("data_fingerprint", "log_lik_label", "metrics", "workers",
                                                      "seconds", "config") if key in run.info}
        blocks.append(Code(json.dumps(details, indent=2, default=str), "json",
                           f"Config and data fingerprint of {run.name} ({model_label(run.model)}, {run.label})"))
    return blocks


def _code_text(info: dict[str, Any]) -> str:
    """trajflow version, and the code revisions (cut to 12 characters) that trained and evaluated the run where
    they were recorded."""
    def short(revision: Any) -> str:
        commit, plus, rest = str(revision).partition("+")
        return commit[:12] + plus + rest

    text = str(info.get("trajflow_version", "—"))
    recorded = info.get("training_code_revisions")
    trained = [short(r) for r in recorded] if isinstance(recorded, list) else []
    evaluated = short(info["code_revision"]) if info.get("code_revision") else None
    if trained == [evaluated] and evaluated:
        return f"{text} ({evaluated})"
    parts = ([f"trained by {', '.join(trained)}"] if trained else []) + (
        [f"evaluated by {evaluated}"] if evaluated else [])
    return f"{text} ({'; '.join(parts)})" if parts else text


def _json_safe(value: Any) -> Any:
    """Non-finite floats as strings, so report.json is strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    return value


def _header(runs: list[Run], inputs: list[Path], experiments: tuple[str, ...], notes: tuple[str, ...],
            datasets: list[str], generated: str) -> list[Block]:
    """Title, what the report covers, how to read the numbers, and the contents."""
    source = f" from experiment{'s' if len(experiments) > 1 else ''} {', '.join(experiments)}" if experiments else ""
    labels = sorted({str(r.info["log_lik_label"]) for r in runs if r.info.get("log_lik_label")})
    reading = [*HOW_TO_READ]
    if labels:
        reading.append(f"Draw log-likelihoods in the figures are each model's own density ({', '.join(labels)}), "
                       "not a density over world trajectories; they only rank draws within a panel.")
    blocks: list[Block] = [
        Heading(1, "trajflow report"),
        Paragraph(f"{_plural(len(runs), 'evaluated run')} of {_plural(len(datasets), 'dataset')}{source}; "
                  f"generated {generated} by trajflow "
                  f"{__version__} from: {', '.join(f'`{p}`' for p in inputs)}."),
    ]
    if notes:
        blocks.append(Bullets(tuple(f"Note: {n}" for n in notes)))
    blocks += [Heading(3, "How to read it"), Bullets(tuple(reading)), Heading(3, "Contents"),
               Bullets(tuple(f"{dataset_label(d)} ({_plural(sum(r.dataset == d for r in runs), 'run')})"
                             for d in datasets) + ("Provenance",))]
    return blocks


def report(inputs: list[Path], out: Path, *, quiet: bool = False, figures: bool = True,
           max_examples: int = 4) -> Path:
    """Write the report of the evaluated runs / experiments in `inputs` to the directory `out`; returns `out`."""
    if max_examples < 0:
        raise UsageError(f"--examples must be 0 or more, got {max_examples}")
    inputs, out = [Path(p) for p in inputs], Path(out)
    resolved = resolve_inputs(inputs)
    _check_out(out, [path for path, _ in resolved.runs])
    generated = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    with make_progress(quiet) as progress:
        task = progress.add_task("reading runs", total=len(resolved.runs))
        runs = []
        for path, experiment in resolved.runs:
            runs.append(load_run(path, experiment))
            progress.advance(task)
        metrics = metrics_frame(runs)
        summary, per_fold = summary_stats(metrics), fold_stats(metrics)
        medians = metrics_frame(runs, run_medians)
        datasets = dataset_order([r.dataset for r in runs])
        blocks = _header(runs, inputs, resolved.experiments, resolved.notes, datasets, generated)
        sections = progress.add_task("building report", total=len(datasets))
        for dataset in datasets:
            blocks += _dataset_section(dataset, [r for r in runs if r.dataset == dataset], summary, per_fold,
                                       (metrics, medians), resolved.planned, figures=figures,
                                       max_examples=max_examples, progress=progress)
            progress.advance(sections)
    blocks += _provenance(runs)
    pictures = [block for block in blocks if isinstance(block, Figure)]
    machine = {
        "trajflow_version": __version__, "generated": generated, "inputs": [str(p) for p in inputs],
        "experiments": list(resolved.experiments),
        "runs": [{"path": str(r.path), "run": r.name, "model": r.model, "dataset": r.dataset, "fold": r.fold,
                  "seed": r.seed} for r in runs],
        "summary": summary.rows(named=True), "per_fold": per_fold.rows(named=True),
        "nll_medians": {"summary": summary_stats(medians).rows(named=True),
                        "per_fold": fold_stats(medians).rows(named=True)},
        "figures": [figure.path for figure in pictures],
    }
    with atomic_directory(out) as tmp:
        _keep_other_files(out, tmp)
        (tmp / FIGURE_DIR).mkdir()
        for figure in pictures:
            (tmp / figure.path).write_bytes(figure.png)
        (tmp / "report.md").write_text(to_markdown(blocks), encoding="utf-8")
        (tmp / "report.html").write_text(to_html(blocks, "trajflow report"), encoding="utf-8")
        (tmp / "report.json").write_text(json.dumps(_json_safe(machine), indent=2, default=str) + "\n",
                                         encoding="utf-8")
    return out
