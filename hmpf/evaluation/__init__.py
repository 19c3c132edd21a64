"""Measuring hierarchies against ground truth, in the order the steps build on each other.

1. :mod:`~hmpf.evaluation.evaluate`: one hierarchy on a route (or against a built index):
   the data (:class:`EvalData`), the features every evaluation starts from
   (:func:`~hmpf.evaluation.evaluate.prepare`: fit -> extract -> stack), recall@N, the PR
   curve, one summary of a hierarchy's answers (:class:`HierarchyOutcome`) and its tier table.
2. :mod:`~hmpf.evaluation.study`: many hierarchies on one route: train/test splits, score
   banks (every method's scores gathered once) and a cost model of measured times.
3. :mod:`~hmpf.evaluation.calibrate`: the search for the best hierarchy under a time budget
   on a training split, its acceptance threshold and the paired test on the test split.
4. :mod:`~hmpf.evaluation.experiments`: the paper's studies, figures and report on banks.

Each step imports only the steps before it. The commands are ``hmpf-eval`` (1, and 4 as
``hmpf-eval experiments``) and ``hmpf-calibrate`` (3).
"""

#: Train/test split schemes of a route (:func:`hmpf.evaluation.study.split_data`); here, where
#: the commands can offer them without importing the evaluation's heavy modules.
SPLITS = ("blocks", "halves")
