"""The data of an evaluation: images with their ground truth, and the features of both.

Every evaluation starts from :func:`prepare` (fit -> extract -> stack) on an
:class:`EvalData`. The lowest step of :mod:`hmpf.evaluation`: it imports no other.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.datasets import frame_ground_truth, list_images
from hmpf.features import ExtractionResult, FeatureCache, extract_images, fit_methods
from hmpf.methods import Method

__all__ = ["EvalData", "Prepared", "prepare"]


@dataclass
class EvalData:
    """Everything an evaluation needs: images, ground truth and a description of it."""

    reference: list[Path]
    query: list[Path]
    gt: np.ndarray  # (n_query, n_ref) bool
    ground_truth: str  # e.g. "frames +-2"

    @classmethod
    def frames(cls, reference: str | Path, query: str | Path, tolerance: int) -> EvalData:
        """Two frame-aligned traverses (image folders): a match is within +-``tolerance``."""
        refs, qrys = list_images(reference), list_images(query)
        gt = frame_ground_truth(len(qrys), len(refs), tolerance)
        return cls(refs, qrys, gt, f"frames +-{tolerance}")


@dataclass
class Prepared:
    """Fit -> extract -> stack, the start of every evaluation of one :class:`EvalData`.

    Attributes:
        methods: method id -> instance, fitted on the references (never on the queries).
        db: method id -> the stacked reference set (:meth:`Method.stack`).
        queries: method id -> per-query features, in query order.
        fitted: method ids whose parameters were fitted.
        ref, qry: the extraction results (per-image times, cache hits).
        fit_s, extraction_s: wall time of fitting and of extraction.
    """

    methods: dict[str, Method]
    db: dict[str, Any]
    queries: dict[str, list[Any]]
    fitted: list[str]
    ref: ExtractionResult
    qry: ExtractionResult
    fit_s: float
    extraction_s: float

    def query(self, qi: int) -> dict[str, Any]:
        """Method id -> the features of query ``qi``."""
        return {m: feats[qi] for m, feats in self.queries.items()}


def prepare(
    methods: dict[str, Method],
    data: EvalData,
    *,
    cache: FeatureCache | None = None,
    workers: int | None = None,
    progress: bool = False,
) -> Prepared:
    """Fit ``methods`` on the references, extract (or load) every image's features, stack."""
    t0 = time.perf_counter()
    fitted = fit_methods(methods, data.reference, cache=cache)
    fit_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    ref = extract_images(
        data.reference, methods, cache=cache, workers=workers, progress=progress, desc="references"
    )
    qry = extract_images(
        data.query, methods, cache=cache, workers=workers, progress=progress, desc="queries"
    )
    extraction_s = time.perf_counter() - t0
    db = {m: methods[m].stack_references(ref.features[m]) for m in methods}
    queries = {m: list(qry.features[m]) for m in methods}
    return Prepared(methods, db, queries, fitted, ref, qry, fit_s, extraction_s)
