"""One image's hierarchy result as the API's response models.

:func:`localize_response` is the only place that turns a :class:`~hmpf.hierarchy.HierarchyResult`
into a :class:`~service.schemas.LocalizeResponse`: the match (with its position and whether it
is accepted), the final ranking, each tier's candidates and the GPS prior's report;
:func:`with_sequence` adds sequence mode's report and makes its estimate the answer (accepted
when locked). Numbers that are not finite (a method that scored NaN) are reported as ``None``,
never as a number that looks real, and a match without a finite score is never accepted.

*Acceptance* is decided by the core's one policy (:class:`hmpf.acceptance.Policy`, the
version's ``loaded.acceptance``), the same code every evaluation runs: ``p_correct`` from the
version's confidence model (every bundled preset ships one) and ``accepted``, or the
quality / lock rule for a config without a model. The features need reference ids along
the routes, so a result run under a GPS prior (its indices are positions in the allowed ids)
is first put back on the whole map (:func:`on_references`).

Matches are *places* (their original reference's id, name and position); a match also says
which stored image of the place matched (``experience``: the original reference, or a fleet
experience with its provenance), read from the result's ``matched_rows`` in a version with
experiences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hmpf.acceptance import Decision
from hmpf.hierarchy import HierarchyResult, TierResult, entries_at
from hmpf.sequence import Estimate
from service.engine import Loaded, confidence
from service.schemas import (
    AcceptedBy,
    Candidate,
    Experience,
    LocalizeParams,
    LocalizeResponse,
    Match,
    PriorReport,
    SequenceReport,
    TierReport,
)
from service.track import Step

__all__ = ["localize_response", "on_references", "sequence_decision", "with_sequence"]


def localize_response(
    loaded: Loaded,
    result: HierarchyResult | None,
    allowed: np.ndarray | None,
    params: LocalizeParams,
    timing: dict[str, Any],
) -> LocalizeResponse:
    """The answer to one image.

    Args:
        loaded: the index version the query ran on.
        result: the hierarchy's result, or None when the GPS prior left no reference.
        allowed: the reference ids the prior allowed (the result's indices are positions in
            it), or None without a prior.
        params: the request's fields (``top_k``, ``vehicle_id``, the prior).
        timing: the query's stage times in ms, reported as they are.
    """
    refs = _References(loaded.reader.refs.names, allowed)
    match = None if result is None else _match(loaded, result, refs)
    return LocalizeResponse(
        match=match,
        single=match,
        candidates=[] if result is None else _ranking(result, refs, params.top_k),
        tiers=[] if result is None else _tiers(loaded, result, refs),
        prior=_prior(loaded, params, allowed),
        timing_ms=timing,
        index_version=loaded.version,
        vehicle_id=params.vehicle_id,
        threshold=loaded.threshold,
    )


@dataclass(frozen=True)
class _References:
    """Maps the result's indices to reference ids and names (through the prior's ids)."""

    names: list[str]
    allowed: np.ndarray | None

    def id_of(self, i: int) -> int:
        return int(self.allowed[i]) if self.allowed is not None else int(i)

    def name_of(self, i: int) -> str:
        return self.names[self.id_of(i)]

    @property
    def searched(self) -> int:
        """How many references the hierarchy ran over."""
        return len(self.names) if self.allowed is None else len(self.allowed)


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def on_references(result: HierarchyResult, allowed: np.ndarray | None, n: int) -> HierarchyResult:
    """``result`` with reference ids for indices, over all ``n`` references of the map.

    Without a prior (``allowed`` None) the result itself. With one, its indices are
    positions in ``allowed``: they are mapped to the ids, and each tier's scores are spread
    over the whole map, NaN outside the prior (a reference the prior left out was not
    scored), so that :func:`~hmpf.confidence.answer_features` measures route distances
    between the right references and reads the same scores as the hierarchy did.
    """
    if allowed is None:
        return result
    ids = np.asarray(allowed, dtype=np.int64)

    def spread(x: np.ndarray) -> np.ndarray:
        full = np.full(n, np.nan)
        full[ids] = np.asarray(x, dtype=np.float64)
        return full

    tiers = [
        TierResult(
            list(t.methods),
            ids if t.inputs is None else ids[np.asarray(t.inputs, dtype=np.int64)],
            {m: spread(s) for m, s in t.scores.items()},
            ids[np.asarray(t.candidates, dtype=np.int64)],
            t.time_ms,
            {m: spread(r) for m, r in t.raw.items()},
        )
        for t in result.tiers
    ]
    return HierarchyResult(
        match=int(ids[result.match]) if result.match >= 0 else -1,
        quality=result.quality,
        final_candidates=ids[np.asarray(result.final_candidates, dtype=np.int64)],
        combined=result.combined,
        tiers=tiers,
        fusion_ms=result.fusion_ms,
        matched_rows=result.matched_rows,  # by place id already
    )


def with_sequence(
    response: LocalizeResponse,
    loaded: Loaded,
    step: Step,
    track: str,
    result: HierarchyResult | None = None,
    decision: Decision | None = None,
) -> LocalizeResponse:
    """``response`` in sequence mode: the frame's :class:`~service.track.Step` as its
    ``sequence`` report (``track``: the signed token to hand back), and the estimate as the
    ``match``; the single-frame match stays the answer only when the filter has no estimate
    (a frame out of order, an empty belief).

    The estimate is accepted as the one policy decides (:func:`sequence_decision`: the
    version's sequence model over the frame's features with the estimate's, ``result``: the
    frame's result on reference ids, :func:`on_references`, None: no result; or the lock
    rule; with hysteresis, never off the map). ``decision``: the one already made for this
    estimate (and recorded in the track); None: made here. The estimate's ``experience`` is
    the image of its place that matched this frame (read from ``result``).
    """
    est = step.estimate
    mass = 0.0 if est is None else min(1.0, max(0.0, est.mass))
    estimate = None
    if est is None or est.ref < 0:  # out of order, or the belief holds no hypothesis
        decision = None
    else:
        if decision is None:
            decision = sequence_decision(loaded, est, result)
        estimate = _reference_match(
            loaded,
            est.ref,
            score=None,
            confidence=mass,
            accepted=decision.accepted,
            p_correct=decision.p_correct,
            accepted_by=decision.accepted_by,
            matched_rows=None if result is None else result.matched_rows,
        )
    use = estimate is not None
    report = SequenceReport(
        status=step.status,
        reset_reason=step.reason,
        match=estimate,
        mass=mass,
        locked=decision is not None and decision.accepted,
        off_map=decision is not None and decision.off_map,
        off_map_probability=0.0 if est is None else _unit(est.off_map),
        frames=0 if est is None else est.frames,
        speed=None if est is None else _finite(est.speed),
        steps=step.steps,
        track=track,
    )
    return response.model_copy(
        update={
            "match": estimate if use else response.single,
            "match_source": "sequence" if use else "single",
            "sequence": report,
        }
    )


def sequence_decision(
    loaded: Loaded, estimate: Estimate, result: HierarchyResult | None
) -> Decision:
    """The policy's decision on a sequence ``estimate`` (``result``: the frame's result on
    reference ids, :func:`on_references`; None: no result)."""
    return loaded.acceptance.sequence(result, estimate, loaded.sequence.routes, loaded.profile)


def _unit(x: float) -> float:
    """``x`` clipped to [0, 1] (NaN: 0)."""
    return min(1.0, max(0.0, float(x))) if math.isfinite(x) else 0.0


def _match(loaded: Loaded, result: HierarchyResult, refs: _References) -> Match | None:
    if result.match < 0:
        return None
    score = _finite(result.quality)
    acc = loaded.acceptance
    # Only a model reads route distances: without one the match and its quality decide,
    # which need no spreading over the whole map.
    on_map = result if acc.model is None else on_references(result, refs.allowed, len(refs.names))
    decision = acc.single(on_map, loaded.sequence.routes, loaded.profile)
    return _reference_match(
        loaded,
        refs.id_of(result.match),
        score=score,
        confidence=confidence(result.quality, len(result.final_candidates)),
        accepted=decision.accepted,
        p_correct=decision.p_correct,
        accepted_by=decision.accepted_by,
        matched_rows=result.matched_rows,
    )


def _reference_match(
    loaded: Loaded,
    ref_id: int,
    *,
    score: float | None,
    confidence: float,
    accepted: bool,
    accepted_by: AcceptedBy,
    p_correct: float | None = None,
    matched_rows: np.ndarray | None = None,
) -> Match:
    """Place ``ref_id`` (its original reference, with its position when known) as a
    :class:`Match`; ``matched_rows``: the query's matched row per place
    (:attr:`~hmpf.hierarchy.HierarchyResult.matched_rows`)."""
    meta = loaded.reader.refs.meta
    lat = float(meta["lat"][ref_id]) if "lat" in meta else float("nan")
    lon = float(meta["lon"][ref_id]) if "lon" in meta else float("nan")
    return Match(
        reference_id=ref_id,
        name=loaded.reader.refs.names[ref_id],
        lat=_finite(lat),
        lon=_finite(lon),
        score=score,
        confidence=confidence,
        p_correct=p_correct,
        accepted=accepted,
        accepted_by=accepted_by,
        experience=_experience(loaded, ref_id, matched_rows),
    )


def _experience(loaded: Loaded, place: int, matched_rows: np.ndarray | None) -> Experience | None:
    """The stored image of ``place`` that matched: the row ``matched_rows`` names; in a
    version without experiences the place's own (only) image. None where the query did not
    score the place (or a version with experiences gave no rows)."""
    reader = loaded.reader
    if matched_rows is None:
        if reader.has_experiences:
            return None
        row = place
    else:
        row = int(matched_rows[place])
        if row < 0:
            return None
    e = reader.experience(row)
    return Experience(
        row=e.row,
        name=e.name,
        original=e.original,
        vehicle=e.vehicle,
        time=e.time,
        p_correct=e.p_correct,
        log=e.log,
        version=e.version,
    )


def _ranking(result: HierarchyResult, refs: _References, top_k: int) -> list[Candidate]:
    """The final candidates by Combined score, best first, at most ``top_k``."""
    z = dict(zip(result.final_candidates.tolist(), result.combined.tolist(), strict=True))
    return [
        Candidate(reference_id=refs.id_of(i), name=refs.name_of(i), score=_finite(z[int(i)]))
        for i in result.ranking()[:top_k]
    ]


def _tiers(loaded: Loaded, result: HierarchyResult, refs: _References) -> list[TierReport]:
    configured = loaded.hierarchy.config.tiers
    reports = []
    for t, tier in enumerate(result.tiers):
        unique = list(dict.fromkeys(int(i) for i in tier.candidates))
        # the candidates' entries only (a later tier's whole arrays are the map's size)
        at = np.asarray(unique, dtype=np.int64)
        scores = {m: entries_at(tier.scores, m, at).tolist() for m in tier.methods}
        candidates = [
            Candidate(
                reference_id=refs.id_of(i),
                name=refs.name_of(i),
                scores={m: _finite(scores[m][j]) for m in tier.methods},
            )
            for j, i in enumerate(unique)
        ]
        inputs = refs.searched if tier.inputs is None else int(len(np.unique(tier.inputs)))
        reports.append(
            TierReport(
                tier=t + 1,
                methods=tier.methods,
                k=configured[t].k,
                inputs=inputs,
                candidates=candidates,
                time_ms=tier.time_ms,
            )
        )
    return reports


def _prior(
    loaded: Loaded, params: LocalizeParams, allowed: np.ndarray | None
) -> PriorReport | None:
    if params.lat is None:
        return None
    assert params.lon is not None and params.radius_m is not None
    return PriorReport(
        lat=params.lat,
        lon=params.lon,
        radius_m=params.radius_m,
        applied=loaded.has_positions,
        references=None if allowed is None else int(len(allowed)),
        reason=None if loaded.has_positions else "the index has no reference positions",
    )
