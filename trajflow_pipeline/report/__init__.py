"""Building blocks of `trajflow report`: collect evaluated runs, aggregate tables, draw figures, render Markdown/HTML.

The single public entry point is :func:`trajflow_pipeline.stages.report.report`; the modules here are split by
concern so each can be tested on its own:

* ``paper``    the metric columns and the paper's TrajFlow numbers (SPEC section 6);
* ``collect``  run / experiment directories -> :class:`collect.Run` records and polars frames (validated);
* ``tables``   mean ± std over folds and seeds, per-fold breakdowns, paper targets, as renderable tables;
* ``curves``   minADE as a function of K from predictions + ground truth (vectorised numpy);
* ``scenes``   the samples and arrays that the example and density figures show;
* ``figures``  matplotlib (Agg canvas, no pyplot state) -> PNG bytes;
* ``document`` a small format-neutral document model; ``render`` turns it into Markdown and HTML.
"""
