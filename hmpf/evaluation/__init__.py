"""Measuring hierarchies against ground truth, in layers that import only the layers below.

1. :mod:`~hmpf.evaluation.data`: the data (:class:`~hmpf.evaluation.data.EvalData`) and the
   features every evaluation starts from (:func:`~hmpf.evaluation.data.prepare`: fit ->
   extract -> stack).
2. :mod:`~hmpf.evaluation.metrics`: recall@N, the PR curve, one summary of a hierarchy's
   answers (:class:`~hmpf.evaluation.metrics.HierarchyOutcome`), precision at a threshold
   and the paired sign test.
3. :mod:`~hmpf.evaluation.sequence` (the sequence filter replayed on drives), then
   :mod:`~hmpf.evaluation.study` (many hierarchies on one route: train/test splits, score
   banks and a cost model of measured times), then :mod:`~hmpf.evaluation.acceptance`
   (acceptance policies applied to answers).
4. :mod:`~hmpf.evaluation.evaluate` (one hierarchy on a route or against a built index, with
   its report) and :mod:`~hmpf.evaluation.calibrate` (the search for the best hierarchy under
   a time budget, its acceptance threshold and the paired test on the test split).
5. :mod:`~hmpf.evaluation.experiments`: the paper's studies, figures and report on banks.

``tests/hmpf/test_import_structure.py`` checks that there is no circle. The names of layers 1
and 2 stay importable from :mod:`~hmpf.evaluation.evaluate` (and ``paired_test``,
``precision_recall_at`` from :mod:`~hmpf.evaluation.calibrate`), where they were first. The
commands are ``hmpf-eval`` (4, and 5 as ``hmpf-eval experiments``) and ``hmpf-calibrate``.
"""

#: Train/test split schemes of a route (:func:`hmpf.evaluation.study.split_data`); here, where
#: the commands can offer them without importing the evaluation's heavy modules.
SPLITS = ("blocks", "halves")
