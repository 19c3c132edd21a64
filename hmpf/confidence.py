"""Confidence of an answer: its evidence, and a calibrated probability that it is right.

A vehicle that receives a place must know whether to use it. The Combined z of the answer
(its *quality*) separates right from wrong answers poorly, so this module gathers more of
the evidence a :class:`~hmpf.hierarchy.HierarchyResult` already holds
(:func:`answer_features`) and maps it to the probability that the answer is right with a
small logistic regression (:class:`ConfidenceModel`), fitted on a training part of a route.

Around it: :func:`threshold_for_precision` (the lowest probability whose accepted answers
reach a target precision), :func:`expected_calibration_error` and :func:`reliability` (how
well the probabilities match the observed shares of right answers).

*Neighbourhood.* Two references within ``window`` route steps of each other
(:meth:`~hmpf.sequence.RouteMap.separation`) show nearly the same place: a rival next door is
not a rival, and a method whose best candidate is next door agrees with the answer.

Everything here is pure and deterministic (numpy only).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from hmpf.errors import HmpfError
from hmpf.fusion import Filled, Spread, top_k
from hmpf.methods.base import GlobalMethod
from hmpf.sequence import Estimate, RouteMap

if TYPE_CHECKING:  # annotations only: hmpf.hierarchy sits above this module (it needs hmpf.config)
    from hmpf.hierarchy import HierarchyResult

__all__ = [
    "ALL_FEATURES",
    "CAND_Z_KNOT",
    "CAND_Z_TOP",
    "MAP_FEATURES",
    "FEATURES",
    "FORMAT",
    "FORMAT_VERSION",
    "LOGIT_CLIP",
    "PROFILE_FEATURES",
    "PROFILE_SAMPLE",
    "PROFILE_SEED",
    "PROFILE_VERSION",
    "PROFILE_WINDOW",
    "SEQUENCE_FEATURES",
    "ConfidenceModel",
    "ModelError",
    "ReferenceProfile",
    "Reliability",
    "absolute_evidence",
    "answer_features",
    "expected_calibration_error",
    "feature_matrix",
    "profile_params",
    "reliability",
    "stored_map_prior",
    "threshold_for_precision",
]

#: Features of a single-frame answer, in the order :func:`answer_features` returns them.
FEATURES = (
    "quality",
    "margin",
    "agreement",
    "tier1_rank",
    "tier1_margin",
    "tier1_z",
    "n_final",
)
#: Features added when a sequence :class:`~hmpf.sequence.Estimate` is given.
SEQUENCE_FEATURES = ("sequence_mass", "sequence_logit", "sequence_agrees")
#: Absolute evidence, added when a :class:`ReferenceProfile` is given (``sequence_ref_z``
#: with an estimate too).
PROFILE_FEATURES = ("ref_z", "ref_z_low", "cand_z", "cand_z_low", "sequence_ref_z")
#: A property of the map, the same for every answer, added when the profile knows it
#: (:attr:`ReferenceProfile.map_prior`, stored by ``hmpf-index build --map-prior``).
MAP_FEATURES = ("map_prior",)
#: Every feature a model may use.
ALL_FEATURES = FEATURES + SEQUENCE_FEATURES + PROFILE_FEATURES + MAP_FEATURES
#: ``cand_z_low`` is ``min(cand_z - CAND_Z_KNOT, 0)``: the best of a dozen or more candidates'
#: z-scores lies above 0 even for a frame that scores like unrelated places (the largest of
#: several draws), so the hinge starts a little above 0. Chosen among 0, 0.5 and 1 on the
#: training parts (``bench/offmap_hinge.py``).
CAND_Z_KNOT = 0.5
#: ``cand_z`` reads at most this many final candidates, the best by Combined z: the default's
#: final tier holds up to 20; a single-tier config's final candidates are the whole map, over
#: which the best of the z-scores would grow with the map's size.
CAND_Z_TOP = 20
#: ``sequence_logit`` is clipped to +-this (a mass of 1 - 2e-9 or more reads as certain).
LOGIT_CLIP = 20.0

#: ``format`` and ``version`` of :meth:`ConfidenceModel.to_dict`: version 2 is a model with a
#: :attr:`~ConfidenceModel.gate`; a model without one is still written as version 1, so that
#: an hmpf that reads only version 1 reads it, and refuses (does not misread) a gated one.
FORMAT = "hmpf-confidence"
FORMAT_VERSION = 2
_VERSIONS = (1, 2)

#: Predictions are kept this far from 0 and 1: a model of a few coefficients is never
#: certain, and a threshold of 1.0 then accepts nothing.
_EPS = 1e-12


class ModelError(HmpfError):
    """A confidence model that cannot be used (another version, wrong features, corrupt)."""


# -- evidence of one answer ---------------------------------------------------------------------


def _finite(x: float, default: float) -> float:
    return float(x) if math.isfinite(x) else default


def _scored(scores: Mapping[str, np.ndarray], mid: str) -> int:
    """How many references a tier's score array of ``mid`` covers (without making a
    :class:`~hmpf.hierarchy.Spread` whole)."""
    return scores.n if isinstance(scores, Spread) else len(scores[mid])


def _best_of(scores: Mapping[str, np.ndarray], mid: str) -> int:
    """The reference with the highest finite score of ``mid`` (the lowest on ties), -1
    when none is finite."""
    if isinstance(scores, Spread):
        return scores.best(mid)
    s = np.asarray(scores[mid], dtype=np.float64)
    if not np.isfinite(s).any():
        return -1
    return int(np.nanargmax(np.where(np.isfinite(s), s, np.nan)))


def _filled_tier1(
    mean: Filled, match: int, routes: RouteMap, window: int, out: dict[str, float]
) -> bool:
    """:func:`answer_features`' tier-1 features (rank, margin, z) of an approximate tier 1's
    mean score from its entries and fill, without the whole array: the same rank and
    margin; the mean and spread summed as entries plus fill times the rest (equal to the
    whole array's to rounding). False (nothing set) unless every value is finite."""
    v, fill, rest = mean.values, mean.fill, mean.rest
    if not (math.isfinite(fill) and np.isfinite(v).all()):
        return False
    at = float(mean.at(np.array([match]))[0])
    rank = int(np.count_nonzero(v > at)) + (rest if fill > at else 0)
    out["tier1_rank"] = math.log1p(rank)
    rival = _best_outside_all(mean, match, routes, window, finite=True)
    out["tier1_margin"] = at - (0.0 if rival is None else rival)
    n = mean.n
    mu = (float(v.sum()) + fill * rest) / n
    sd = math.sqrt((float(np.square(v - mu).sum()) + rest * (fill - mu) ** 2) / n) if n > 1 else 0.0
    out["tier1_z"] = (at - mu) / sd if sd > 0 else 0.0
    return True


def _best_outside_all(
    values: np.ndarray | Filled,
    answer: int,
    routes: RouteMap,
    window: int,
    look: int = 64,
    *,
    finite: bool | None = None,
) -> float | None:
    """:func:`_best_outside` over every reference, looking first at the ``look`` highest
    values (finite, no NaN): the first of them far from ``answer`` is the best far one
    (every other value is at most as high). Only when none of them is far (more than
    ``look`` high values within ``window`` steps) is every reference looked at.
    ``finite``: whether every value is finite, when the caller knows."""
    n = len(values)
    if finite is None and n > 4 * look:
        finite = bool(np.isfinite(values).all())
    if n > 4 * look and finite:
        top = top_k(values, look)
        far = routes.separation(top, answer) > window
        if far.any():
            best = top[np.argmax(far)]
            return float(values.at(best[None])[0] if isinstance(values, Filled) else values[best])
    return _best_outside(np.asarray(values), np.arange(n), answer, routes, window)


def _best_outside(
    values: np.ndarray, ids: np.ndarray, answer: int, routes: RouteMap, window: int
) -> float | None:
    """Highest finite value among ``ids`` more than ``window`` route steps from ``answer``
    (None: no such entry)."""
    if not len(ids):
        return None
    far = routes.separation(ids, answer) > window
    v = values[far]
    v = v[np.isfinite(v)]
    return float(v.max()) if v.size else None


def stored_map_prior(value: object) -> float | None:
    """A map prior as stored (a manifest's or a shard map's ``map_prior``): None stays None,
    a finite number becomes a float.

    Raises:
        ValueError: anything else (the caller says whose file is damaged).
    """
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"map_prior {value!r} is not a finite number")
    return float(value)


def answer_features(
    result: HierarchyResult,
    routes: RouteMap,
    *,
    window: int = 2,
    estimate: Estimate | None = None,
    profile: ReferenceProfile | None = None,
) -> dict[str, float]:
    """The evidence of one answer (``result.match``), every value finite.

    Features (:data:`FEATURES`):

    * ``quality``: the answer's Combined z (NaN: 0, the candidates' mean).
    * ``margin``: ``quality`` minus the best Combined z among the final candidates more than
      ``window`` route steps from the answer (a rival next door is not a rival). No rival
      (every candidate in the neighbourhood, or only NaN scores there): the rival is taken
      at z = 0, the candidates' mean, so the margin is ``quality``.
    * ``agreement``: share of the final tier's methods whose own best reference (highest
      normalised score, NaN skipped) lies within ``window`` of the answer; a method with no
      finite score does not agree.
    * ``tier1_rank``: ``log1p`` of the answer's rank in tier 1's mean score (0: ranked
      first; the number of references scoring strictly higher, NaN read as the lowest; an
      answer without a finite score ranks last).
    * ``tier1_margin``: tier-1 mean score at the answer minus the best one more than
      ``window`` from it (scores in [0, 1], NaN read as 0; no rival: the rival scores 0).
    * ``tier1_z``: the answer's tier-1 mean score as a z-score over the finite scores of
      tier 1 (constant scores or NaN at the answer: 0).
    * ``n_final``: ``log1p`` of the number of distinct candidates entering the final tier
      (few: the earlier tiers' methods agreed).

    With an ``estimate`` (:data:`SEQUENCE_FEATURES`): ``sequence_mass``, the estimate's
    posterior mass (NaN or before the first frame: 0); ``sequence_logit``, the same mass as
    log-odds ``log(m / (1 - m))`` clipped to +-:data:`LOGIT_CLIP` (what separates a good
    lock from a poor one is 0.99 against 0.9999, which a linear term in the mass cannot
    express); and ``sequence_agrees``, 1.0 when the estimate lies within ``window`` of the
    single-frame answer, else 0.0.

    With a ``profile`` (:data:`PROFILE_FEATURES`): ``ref_z``, how the query's raw tier-1
    score at the answer compares with the scores the answer gets from unrelated references
    (:meth:`ReferenceProfile.z`; the only absolute evidence: every other feature compares
    the map's references with each other, so a query from a place the map does not hold
    can look as good as a right one); ``ref_z_low``, ``min(ref_z, 0)``: a hinge, so that a
    linear model can weigh a score below what unrelated frames get (a frame of a place the
    map does not hold) more steeply than it weighs how far above them a score lies;
    ``cand_z``, the highest of the same z-scores over the answer and the final tier's
    candidates, at most :data:`CAND_Z_TOP` of them (the best by Combined z): whether the
    frame scores above unrelated places *anywhere* among them (a frame of a mapped place
    whose answer is wrong usually does, a frame from elsewhere does not; over a bounded
    number of candidates, not the whole map, so its scale does not grow with the map), and
    ``cand_z_low``, ``min(cand_z - CAND_Z_KNOT, 0)`` (:data:`CAND_Z_KNOT`); with an estimate
    too, ``sequence_ref_z``, the same at the estimate's reference. No raw score there (not
    scored, a result without raw scores): 0, an unrelated reference's score (and
    ``cand_z_low`` 0 where no candidate has a z-score). A
    profile that knows its map's prior (:attr:`ReferenceProfile.map_prior`) adds
    ``map_prior``, the same for every answer.

    Without an answer (``match`` < 0, no candidates) every feature takes its "no evidence"
    value: 0, and ``tier1_rank`` the database's size (as log1p).
    """
    if window < 0:
        raise HmpfError("window must be >= 0")
    n_db = routes.n
    for tier in result.tiers:
        for mid in tier.scores:
            size = _scored(tier.scores, mid)
            if size != n_db:
                raise HmpfError(
                    f"method {mid!r} scored {size} references; the route map has {n_db}"
                )
    match = int(result.match)
    out: dict[str, float] = {}
    answered = 0 <= match < n_db
    # Final tier: Combined z over the candidates entering it.
    cands = np.asarray(result.final_candidates, dtype=np.int64)
    z = np.asarray(result.combined, dtype=np.float64)
    quality = _finite(float(result.quality), 0.0) if answered else 0.0
    out["quality"] = quality
    rival = _best_outside(z, cands, match, routes, window) if answered else None
    out["margin"] = quality - (0.0 if rival is None else rival)
    tiers = result.tiers
    agree = 0
    final_methods = tiers[-1].methods if tiers else []
    if answered:
        for mid in final_methods:
            best = _best_of(tiers[-1].scores, mid)
            if best >= 0:
                agree += bool(routes.separation(best, match) <= window)
    out["agreement"] = agree / len(final_methods) if final_methods else 0.0
    # Tier 1: the whole database.
    whole = tiers[0].whole_mean() if tiers and answered else None
    if isinstance(whole, Filled) and _filled_tier1(whole, match, routes, window, out):
        pass
    elif tiers and answered:
        mean = np.asarray(whole, dtype=np.float64)
        at = float(mean[match])
        # Tier 1 covers the whole map: one pass over it per step below, and none where
        # every score is finite (the usual case) and a step only replaces what is not.
        finite = np.isfinite(mean)
        every = bool(finite.all())
        if math.isfinite(at):
            above = mean > at if every else np.where(finite, mean, -np.inf) > at
            rank = int(np.count_nonzero(above))
        else:
            rank = n_db
        out["tier1_rank"] = math.log1p(rank)
        score0 = mean if every else np.nan_to_num(mean, nan=0.0, posinf=0.0, neginf=0.0)
        rival1 = _best_outside_all(score0, match, routes, window, finite=True)  # NaN, inf: 0
        out["tier1_margin"] = float(score0[match]) - (0.0 if rival1 is None else rival1)
        fin = mean if every else mean[finite]
        sd = float(fin.std()) if fin.size > 1 else 0.0
        out["tier1_z"] = (at - float(fin.mean())) / sd if sd > 0 and math.isfinite(at) else 0.0
    else:
        out["tier1_rank"] = math.log1p(n_db)
        out["tier1_margin"] = 0.0
        out["tier1_z"] = 0.0
    out["n_final"] = math.log1p(len(np.unique(cands))) if answered else 0.0
    if estimate is not None:
        ref = int(estimate.ref)
        valid = 0 <= ref < n_db
        mass = min(max(_finite(float(estimate.mass), 0.0), 0.0), 1.0) if valid else 0.0
        out["sequence_mass"] = mass
        with np.errstate(divide="ignore"):
            logit = float(np.log(mass) - np.log1p(-mass))
        out["sequence_logit"] = min(max(logit, -LOGIT_CLIP), LOGIT_CLIP)
        out["sequence_agrees"] = float(
            valid and answered and bool(routes.separation(ref, match) <= window)
        )
    if profile is not None:
        raw = tiers[0].raw if tiers else {}
        vals = np.empty(0)
        out["ref_z"] = 0.0
        if answered:
            # One pass over the answer and the best candidates: ref_z is the answer's entry.
            pool = top_k(z, CAND_Z_TOP) if len(cands) > CAND_Z_TOP else np.arange(len(cands))
            refs = np.unique(np.append(cands[pool], match))
            vals = profile.z_many(raw, refs)
            out["ref_z"] = _finite(float(vals[np.searchsorted(refs, match)]), 0.0)
            vals = vals[np.isfinite(vals)]
        out["ref_z_low"] = min(out["ref_z"], 0.0)
        # No z-score anywhere (no answer, no raw scores): no evidence, 0 like ref_z's.
        out["cand_z"] = float(vals.max()) if vals.size else 0.0
        out["cand_z_low"] = min(out["cand_z"] - CAND_Z_KNOT, 0.0) if vals.size else 0.0
        if estimate is not None:
            ref = int(estimate.ref)
            out["sequence_ref_z"] = _finite(profile.z(raw, ref), 0.0) if 0 <= ref < n_db else 0.0
        if profile.map_prior is not None:
            out["map_prior"] = float(profile.map_prior)
    return out


# -- absolute evidence: how a reference scores against unrelated ones -------------------------

#: :meth:`ReferenceProfile.build`'s defaults: unrelated references sampled, the route steps
#: around a reference that are not unrelated to it, the sample's seed.
PROFILE_SAMPLE, PROFILE_WINDOW, PROFILE_SEED = 256, 2, 0
#: Version of what :meth:`ReferenceProfile.build` computes: raised when the same parameters
#: would give other numbers, so that a profile stored with an index version is built anew.
PROFILE_VERSION = 1


def profile_params() -> dict[str, int]:
    """What a default :meth:`ReferenceProfile.build` computes: ``version``
    (:data:`PROFILE_VERSION`), ``sample``, ``window`` and ``seed``. A stored profile records
    them and is used only where they are still these."""
    return {
        "version": PROFILE_VERSION,
        "sample": PROFILE_SAMPLE,
        "window": PROFILE_WINDOW,
        "seed": PROFILE_SEED,
    }


@dataclass(frozen=True)
class ReferenceProfile:
    """Per reference and tier-1 global method, the mean and spread of the raw scores the
    reference gets from unrelated references (a fixed sample of the map's references more
    than ``window`` route steps away): what a query from *elsewhere* would score there.

    :meth:`z` turns a query's raw score at a reference into a z-score over that
    distribution (sign flipped for distances, so higher always means more alike). A right
    answer scores far above what unrelated places give; a query from a place the map does
    not hold scores like one of them, however much its best reference stands out among the
    others. Built from the stored descriptors alone (:meth:`build`), never from queries.

    Attributes:
        methods: the profiled method ids (the tier's global methods).
        sign: per method, +1 (higher is better) or -1 (distances).
        mean, std: (len(methods), N) per method and reference.
        map_prior: the map's prior, if known (an index version's
            :meth:`~hmpf.index.reader.IndexReader.map_prior`): every answer against this map
            gets it as its ``map_prior`` feature (:func:`answer_features`). Not part of what
            is stored with the profile.
    """

    methods: tuple[str, ...]
    sign: tuple[float, ...]
    mean: np.ndarray
    std: np.ndarray
    map_prior: float | None = None

    @classmethod
    def build(
        cls,
        methods: Mapping[str, Any],
        db: Mapping[str, Any],
        method_ids: Sequence[str],
        routes: RouteMap,
        *,
        sample: int = PROFILE_SAMPLE,
        window: int = PROFILE_WINDOW,
        chunk: int = 16384,
        seed: int = PROFILE_SEED,
    ) -> ReferenceProfile:
        """Profile the references of ``db`` for the global methods among ``method_ids``
        (local methods are skipped; none left: an empty profile whose :meth:`z` is NaN).

        Cost: ``sample`` x N scores per method (matrix products, in chunks of ``chunk``
        references, so memory stays ``sample x chunk``).
        """
        n = routes.n
        rng = np.random.default_rng(seed)
        pick = (
            np.arange(n)
            if n <= sample
            else np.sort(rng.choice(n, sample, replace=False)).astype(np.int64)
        )
        ids, signs, means, stds = [], [], [], []
        for mid in method_ids:
            m = methods[mid]
            if not isinstance(m, GlobalMethod):
                continue
            if mid not in db:
                raise HmpfError(f"no stored descriptors of method {mid!r} to profile")
            mat = db[mid]  # indexed in chunks: rows read on demand stay on disk
            if len(mat) != n:
                raise HmpfError(f"method {mid!r} holds {len(mat)} references; the map has {n}")
            q = mat[pick]
            mu, sd = np.empty(n), np.empty(n)
            for lo in range(0, n, chunk):
                cols = np.arange(lo, min(n, lo + chunk))
                S = np.asarray(m.pairwise(q, mat[cols]), dtype=np.float64)
                far = routes.separation(pick[:, None], cols[None, :]) > window
                S = np.where(far & np.isfinite(S), S, np.nan)
                cnt = np.sum(~np.isnan(S), axis=0)
                with np.errstate(invalid="ignore", divide="ignore"):
                    mu[cols] = np.nansum(S, axis=0) / cnt
                    sd[cols] = np.sqrt(np.nansum((S - mu[cols]) ** 2, axis=0) / cnt)
            ids.append(mid)
            signs.append(1.0 if m.higher_is_better else -1.0)
            means.append(mu)
            stds.append(sd)
        shape = (len(ids), n)
        return cls(
            tuple(ids),
            tuple(signs),
            np.array(means, dtype=np.float64).reshape(shape),
            np.array(stds, dtype=np.float64).reshape(shape),
        )

    @property
    def n(self) -> int:
        return int(self.mean.shape[1])

    def to_arrays(self) -> dict[str, np.ndarray]:
        """``sign`` (M,), ``mean`` and ``std`` (M, N), float64: with :attr:`methods`, what
        :meth:`from_arrays` restores the profile from, bit for bit."""
        return {
            "sign": np.asarray(self.sign, dtype=np.float64),
            "mean": np.asarray(self.mean, dtype=np.float64),
            "std": np.asarray(self.std, dtype=np.float64),
        }

    @classmethod
    def from_arrays(
        cls, methods: Sequence[str], arrays: Mapping[str, np.ndarray]
    ) -> ReferenceProfile:
        """Inverse of :meth:`to_arrays` (the arrays are copied).

        Raises:
            HmpfError: an array missing, a duplicate method, shapes that disagree with
                ``methods`` or with each other, a sign other than +1 or -1.
        """
        ids = tuple(str(m) for m in methods)
        missing = [k for k in ("sign", "mean", "std") if k not in arrays]
        if missing:
            raise HmpfError(f"reference profile lacks {', '.join(missing)}")
        if len(set(ids)) != len(ids):
            raise HmpfError(f"reference profile names a method twice: {list(ids)}")
        sign = np.array(arrays["sign"], dtype=np.float64)
        mean = np.array(arrays["mean"], dtype=np.float64)
        std = np.array(arrays["std"], dtype=np.float64)
        if sign.shape != (len(ids),) or not np.isin(sign, (1.0, -1.0)).all():
            raise HmpfError(f"reference profile: sign must be +-1 for each of {len(ids)} methods")
        if mean.ndim != 2 or mean.shape[0] != len(ids) or std.shape != mean.shape:
            raise HmpfError(
                f"reference profile: mean {mean.shape} and std {std.shape} must both be "
                f"({len(ids)}, N)"
            )
        return cls(ids, tuple(float(s) for s in sign), mean, std)

    def subset(self, keep: np.ndarray) -> ReferenceProfile:
        """The profile of the references ``keep`` (a map with some references removed)."""
        k = np.asarray(keep, dtype=np.int64)
        return ReferenceProfile(
            self.methods, self.sign, self.mean[:, k], self.std[:, k], self.map_prior
        )

    def z(self, raw: Mapping[str, np.ndarray], ref: int) -> float:
        """The lowest, over the profiled methods, of ``sign * (raw - mean) / std`` at ``ref``
        (methods without a finite raw score there, or no spread, are left out; none left:
        NaN). The lowest, not the mean: a right answer looks alike to every method, while
        a query from elsewhere can fool one (NetVLAD's centroids, fitted on the map, can
        place a foreign image close to a reference)."""
        return float(self.z_many(raw, np.array([ref], dtype=np.int64))[0])

    def z_many(self, raw: Mapping[str, np.ndarray], refs: np.ndarray) -> np.ndarray:
        """:meth:`z` at each of ``refs`` (ids outside the map: NaN), as one array."""
        refs = np.asarray(refs, dtype=np.int64).ravel()
        ok = (refs >= 0) & (refs < self.n)
        best = np.full(len(refs), np.inf)
        for i, mid in enumerate(self.methods):
            if isinstance(raw, Spread):
                # A tier's entries (an approximate tier 1's fill): read there, no array.
                if mid not in raw:
                    continue
                inside = ok & (refs < raw.n)
                x = np.full(len(refs), np.nan)
                x[inside] = raw.at(mid, refs[inside])
            else:
                r = raw.get(mid)
                if r is None:
                    continue
                r = np.asarray(r)
                inside = ok & (refs < len(r))
                x = np.full(len(refs), np.nan)
                x[inside] = r[refs[inside]]
            at = np.where(inside, refs, 0)
            mu, sd = self.mean[i, at], self.std[i, at]
            good = inside & np.isfinite(x) & np.isfinite(mu) & np.isfinite(sd) & (sd > 0)
            with np.errstate(invalid="ignore", divide="ignore"):
                v = self.sign[i] * (x - mu) / sd
            best = np.where(good, np.minimum(best, v), best)
        return np.where(np.isfinite(best), best, np.nan)


def absolute_evidence(result: HierarchyResult, profile: ReferenceProfile | None) -> float:
    """A result's absolute evidence (the sequence filter's
    :attr:`~hmpf.sequence.Evidence.absolute`): the profile's z-score
    (:meth:`ReferenceProfile.z`) of tier 1's raw scores at the single-frame answer (the
    result on reference ids); NaN without a profile, an answer or raw scores."""
    if profile is None or result.match < 0 or not result.tiers:
        return float("nan")
    return profile.z(result.tiers[0].raw, int(result.match))


def feature_matrix(rows: Sequence[Mapping[str, float]], names: Sequence[str]) -> np.ndarray:
    """(n, len(names)) matrix of feature dicts, columns in ``names`` order."""
    missing = sorted({n for r in rows for n in names if n not in r})
    if missing:
        raise ModelError(f"features missing from the answers: {', '.join(missing)}")
    return np.array([[float(r[n]) for n in names] for r in rows], dtype=np.float64).reshape(
        len(rows), len(names)
    )


# -- the model ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ConfidenceModel:
    """Logistic regression from an answer's features to the probability it is right.

    ``p = 1 / (1 + exp(-(intercept + coef . (x - mean) / scale)))``: the features are
    standardised with the training part's means and standard deviations, and the
    coefficients minimise the (optionally weighted) log-loss plus ``l2 / 2 * |coef|^2``
    (the intercept is not penalised), found by Newton's method (iteratively reweighted least
    squares) from zero: deterministic, a handful of iterations, and finite even when the
    training answers are perfectly separable.

    Why not scikit-learn: the service would gain a large dependency for a model of a
    handful of coefficients; our own fit gives the same numbers on every machine (no solver
    defaults that change between versions), and the model is stored as plain numbers in
    JSON (:meth:`to_dict`), readable and versioned, not a pickle.

    Attributes:
        features: feature names, in column order.
        mean, scale: per feature, the training mean and standard deviation (1 where the
            feature was constant).
        coef: per feature, the coefficient on the standardised feature.
        intercept: the intercept.
        l2: the regularisation strength it was fitted with.
        gate: None, or a second model (over some of :attr:`features`) of the probability
            that the query's place is in the map at all. Then this model is that of the
            answer being right *given* an in-map query, and :meth:`predict` gives their
            product, ``P(right) = P(in map) * P(right | in map)`` (a right answer is an
            in-map one): each part is fitted on what tells it (:meth:`fit_gated`), so a
            frame of a place the map does not hold gets a low probability from the gate
            however alike the map's own night frames look to the other part.
    """

    features: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    coef: tuple[float, ...]
    intercept: float
    l2: float = 1.0
    gate: ConfidenceModel | None = None

    def __post_init__(self) -> None:
        if self.gate is not None:
            if self.gate.gate is not None:
                raise ModelError("a gate has no gate of its own")
            extra = [n for n in self.gate.features if n not in self.features]
            if extra:
                raise ModelError(f"the gate reads features the model does not: {extra}")

    @classmethod
    def fit(
        cls,
        X: np.ndarray,
        y: np.ndarray,
        feature_names: Sequence[str],
        *,
        l2: float = 1.0,
        sample_weight: np.ndarray | None = None,
        offsets: Sequence[str] = (),
        max_iter: int = 100,
        tol: float = 1e-10,
    ) -> ConfidenceModel:
        """Fit on ``X`` (n, d) and right/wrong labels ``y`` (n,).

        Args:
            sample_weight: (n,) weight of each answer's log-loss (e.g. so that routes of
                different lengths pooled count alike); the means and scales are weighted
                too. None: all 1.
            offsets: names of features added to the log-odds as they are, not fitted (a
                known prior log-odds, e.g. one per map): stored with mean 0, scale 1 and
                coefficient 1, so the model predicts as any other.

        Raises:
            ModelError: shapes disagree, non-finite features or weights, fewer than 2
                answers, or ``l2`` < 0.
        """
        X = np.asarray(X, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64).ravel()
        names = tuple(str(n) for n in feature_names)
        if X.ndim != 2 or X.shape[1] != len(names) or X.shape[0] != len(y):
            raise ModelError(
                f"X must be (n, {len(names)}) for {len(y)} labels, got shape {X.shape}"
            )
        if len(set(names)) != len(names):
            raise ModelError("duplicate feature names")
        if len(y) < 2:
            raise ModelError("at least 2 answers are needed to fit")
        if not np.isfinite(X).all():
            raise ModelError("non-finite feature values")
        if not np.isin(y, (0.0, 1.0)).all():
            raise ModelError("labels must be 0 or 1")
        if not (math.isfinite(l2) and l2 >= 0):
            raise ModelError("l2 must be a finite number >= 0")
        if sample_weight is None:
            sw = np.ones(len(y))
        else:
            sw = np.asarray(sample_weight, dtype=np.float64).ravel()
            if sw.shape != y.shape or not np.isfinite(sw).all() or (sw < 0).any():
                raise ModelError("sample_weight must be (n,) finite numbers >= 0")
            if not sw.sum() > 0:
                raise ModelError("sample_weight must not be all zero")
        unknown = sorted(set(offsets) - set(names))
        if unknown:
            raise ModelError(f"offsets {unknown} are not features")
        fixed = np.array([n in set(offsets) for n in names], dtype=bool)
        free = ~fixed
        offset = X[:, fixed].sum(axis=1)
        mean = np.average(X, axis=0, weights=sw)
        scale = np.sqrt(np.average((X - mean) ** 2, axis=0, weights=sw))
        scale = np.where(scale > 1e-12 * (1 + np.abs(mean)), scale, 1.0)
        mean[fixed], scale[fixed] = 0.0, 1.0
        Z = np.hstack([np.ones((len(y), 1)), ((X - mean) / scale)[:, free]])
        penalty = np.full(Z.shape[1], float(l2))
        penalty[0] = 0.0
        w = _newton(Z, offset, y, sw, penalty, max_iter, tol)
        coef = np.ones(len(names))
        coef[free] = w[1:]
        return cls(
            names,
            tuple(float(v) for v in mean),
            tuple(float(v) for v in scale),
            tuple(float(v) for v in coef),
            float(w[0]),
            float(l2),
        )

    @classmethod
    def fit_staged(
        cls,
        X: np.ndarray,
        y: np.ndarray,
        feature_names: Sequence[str],
        staged: Sequence[str],
        *,
        l2: float = 1.0,
        sample_weight: np.ndarray | None = None,
        offsets: Sequence[str] = (),
        max_iter: int = 100,
        tol: float = 1e-10,
    ) -> ConfidenceModel:
        """A model fitted in two stages: first :meth:`fit` over the features not in
        ``staged``; then only the coefficients of ``staged`` (raw values: mean 0, scale 1;
        no intercept refitted), with the first stage's log-odds as a fixed offset. One
        ordinary model over every feature (what :meth:`to_dict` stores is version 1).

        What it is for: a term that is 0 for most in-map answers, such as the hinges
        ``ref_z_low`` and ``cand_z_low`` (a frame scoring below what unrelated places get),
        lowers the probability of answers to frames from off the map without moving any
        other answer's: where the staged features are 0 the model predicts what the first
        stage does (to rounding), so the answers accepted there stay the same. Fitted
        jointly instead, a hinge reshapes every other coefficient (measured: fewer day
        answers accepted, docs/experiments/acceptance/README.md).

        Raises:
            ModelError: as :meth:`fit`; a duplicate name, a staged name that is not a
                feature or is an offset too, or every feature staged.
        """
        names = tuple(str(n) for n in feature_names)
        later = tuple(str(n) for n in staged)
        if len(set(names)) != len(names) or len(set(later)) != len(later):
            raise ModelError("duplicate feature names")
        unknown = sorted(set(later) - set(names))
        if unknown:
            raise ModelError(f"staged {unknown} are not features")
        both = sorted(set(later) & set(offsets))
        if both:
            raise ModelError(f"{both} cannot be both staged and offsets")
        first = [i for i, n in enumerate(names) if n not in set(later)]
        if not first:
            raise ModelError("a staged fit needs a feature in its first stage")
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != len(names):
            raise ModelError(f"X must be (n, {len(names)}), got shape {X.shape}")
        if not later:
            return cls.fit(
                X, y, names, l2=l2, sample_weight=sample_weight, offsets=offsets,
                max_iter=max_iter, tol=tol,
            )  # fmt: skip
        base = cls.fit(
            X[:, first],
            y,
            [names[i] for i in first],
            l2=l2,
            sample_weight=sample_weight,
            offsets=offsets,
            max_iter=max_iter,
            tol=tol,
        )
        cols = [names.index(n) for n in later]
        H = X[:, cols]
        if not np.isfinite(H).all():
            raise ModelError("non-finite feature values")
        sw = np.ones(len(H)) if sample_weight is None else np.asarray(sample_weight, np.float64)
        yy = np.asarray(y, dtype=np.float64).ravel()
        beta = _newton(H, base.logit(X[:, first]), yy, sw, np.full(len(cols), l2), max_iter, tol)
        whole = base.with_terms(dict(zip(later, (float(b) for b in beta), strict=True)))
        # In the caller's column order.
        order = [whole.features.index(n) for n in names]
        return cls(
            names,
            tuple(whole.mean[i] for i in order),
            tuple(whole.scale[i] for i in order),
            tuple(whole.coef[i] for i in order),
            base.intercept,
            float(l2),
        )

    @classmethod
    def fit_gated(
        cls,
        X: np.ndarray,
        y: np.ndarray,
        feature_names: Sequence[str],
        inside: np.ndarray,
        *,
        l2: float = 1.0,
        sample_weight: np.ndarray | None = None,
        offsets: Sequence[str] = (),
    ) -> ConfidenceModel:
        """A model with a :attr:`gate`: the gate fitted on every row, its label whether the
        row's query is in the map (``inside``), over the features that are not
        ``offsets`` (an offset says how often a map's in-map answers are right, not
        whether a query is in it); the model itself on the in-map rows alone, with
        ``offsets``. Weights and ``l2`` as :meth:`fit` (the gate's ``P(in map)`` is for a
        stream where the off-map rows weigh their share of ``sample_weight``).

        Raises:
            ModelError: as :meth:`fit`; or ``inside`` not (n,) booleans, all True or all
                False (no gate can be fitted), or the in-map rows all right or all wrong.
        """
        X = np.asarray(X, dtype=np.float64)
        inside = np.asarray(inside)
        if inside.dtype != bool or inside.shape != (X.shape[0],):
            raise ModelError(f"inside must be ({X.shape[0]},) booleans")
        if inside.all() or not inside.any():
            raise ModelError("a gate needs in-map and off-map rows")
        y_in = np.asarray(y)[inside]
        if y_in.min() == y_in.max():
            raise ModelError("the in-map rows are all right or all wrong: nothing to learn")
        names = tuple(str(n) for n in feature_names)
        sw = np.ones(len(inside)) if sample_weight is None else np.asarray(sample_weight)
        kept = [i for i, n in enumerate(names) if n not in set(offsets)]
        if not kept:
            raise ModelError("a gate needs a feature that is not an offset")
        gate = cls.fit(
            X[:, kept], inside.astype(np.float64), [names[i] for i in kept], l2=l2, sample_weight=sw
        )
        main = cls.fit(X[inside], y_in, names, l2=l2, sample_weight=sw[inside], offsets=offsets)
        return replace(main, gate=gate)

    def with_terms(self, terms: Mapping[str, float]) -> ConfidenceModel:
        """This model with raw terms added to its log-odds: per name in ``terms``, a feature
        with mean 0, scale 1 and the given coefficient (the form of :meth:`fit_staged`'s
        second stage). What it is for: terms fitted elsewhere, kept as they are, such as
        a shipped model's off-map hinges carried into a route's own model
        (:func:`hmpf.evaluation.acceptance.carried_terms`): where they are 0 the model
        predicts as before.

        Raises:
            ModelError: a gated model, a name the model already has, or a coefficient that
                is not finite.
        """
        if self.gate is not None:
            raise ModelError("terms cannot be added to a gated model")
        names = tuple(str(n) for n in terms)
        taken = sorted(set(names) & set(self.features))
        if taken:
            raise ModelError(f"the model already has {taken}")
        coef = tuple(float(terms[n]) for n in names)
        if not all(math.isfinite(c) for c in coef):
            raise ModelError("non-finite term coefficients")
        return replace(
            self,
            features=self.features + names,
            mean=self.mean + (0.0,) * len(names),
            scale=self.scale + (1.0,) * len(names),
            coef=self.coef + coef,
        )

    def logit(self, X: np.ndarray) -> np.ndarray:
        """(n,) log-odds of (n, d) features (columns in :attr:`features` order): of the
        product with the gate's probability where there is a gate."""
        X = np.asarray(X, dtype=np.float64)
        if X.ndim == 1:
            X = X[None, :]
        if X.ndim != 2 or X.shape[1] != len(self.features):
            raise ModelError(
                f"expected {len(self.features)} features ({', '.join(self.features)}), "
                f"got shape {X.shape}"
            )
        if not np.isfinite(X).all():
            raise ModelError("non-finite feature values: no probability can be given")
        Z = (X - np.asarray(self.mean)) / np.asarray(self.scale)
        t = np.asarray(Z @ np.asarray(self.coef) + self.intercept, dtype=np.float64)
        if self.gate is None:
            return t
        cols = [self.features.index(n) for n in self.gate.features]
        return _and_logit(t, self.gate.logit(X[:, cols]))

    def predict(self, x: Mapping[str, float] | np.ndarray) -> float | np.ndarray:
        """Probability that the answer is right, in [1e-12, 1 - 1e-12].

        Args:
            x: one answer's feature dict (:func:`answer_features`; extra keys ignored, a
                missing one refused), or an (n, d) matrix (columns in :attr:`features`
                order) for an (n,) array.
        """
        if isinstance(x, Mapping):
            missing = [n for n in self.features if n not in x]
            if missing:
                raise ModelError(f"features missing: {', '.join(missing)}")
            row = np.array([[float(x[n]) for n in self.features]])
            return float(np.clip(_sigmoid(self.logit(row)), _EPS, 1 - _EPS)[0])
        return np.clip(_sigmoid(self.logit(np.asarray(x))), _EPS, 1 - _EPS)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able numbers, with the format and its version (1 without a gate)."""
        out: dict[str, Any] = {
            "format": FORMAT,
            "version": 1 if self.gate is None else FORMAT_VERSION,
            "features": list(self.features),
            "mean": list(self.mean),
            "scale": list(self.scale),
            "coef": list(self.coef),
            "intercept": self.intercept,
            "l2": self.l2,
        }
        if self.gate is not None:
            out["gate"] = self.gate.to_dict()
        return out

    @classmethod
    def from_dict(
        cls, data: Mapping[str, Any], *, expected: Sequence[str] | None = None
    ) -> ConfidenceModel:
        """Inverse of :meth:`to_dict`.

        Args:
            expected: the feature names the caller will supply (e.g. :data:`FEATURES`):
                a model over other features is refused.

        Raises:
            ModelError: another format or version, a missing key, unknown, duplicate,
                missing or extra features, lists of the wrong length, non-finite numbers
                or a scale that is not positive.
        """
        if not isinstance(data, Mapping):
            raise ModelError("a confidence model must be a mapping")
        if data.get("format") != FORMAT:
            raise ModelError(f"not a confidence model (format {data.get('format')!r})")
        version = data.get("version")
        if isinstance(version, bool) or version not in _VERSIONS:
            raise ModelError(
                f"confidence model version {version!r} is not supported (this hmpf reads "
                f"versions {', '.join(map(str, _VERSIONS))}); recalibrate"
            )
        if "gate" in data and version == 1:
            raise ModelError("a version 1 confidence model has no gate")
        keys = ("features", "mean", "scale", "coef", "intercept")
        missing_keys = [k for k in keys if k not in data]
        if missing_keys:
            raise ModelError(f"confidence model lacks {', '.join(missing_keys)}")
        raw = data["features"]
        if not isinstance(raw, list | tuple) or not all(isinstance(n, str) for n in raw):
            raise ModelError("'features' must be a list of names")
        names = tuple(raw)
        known = set(ALL_FEATURES)
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ModelError(f"unknown features in the model: {', '.join(unknown)}")
        if len(set(names)) != len(names) or not names:
            raise ModelError("the model's features must be distinct and not empty")
        if expected is not None:
            extra = [n for n in names if n not in expected]
            absent = [n for n in expected if n not in names]
            if extra or absent:
                raise ModelError(
                    "the model's features differ from the expected ones: "
                    f"extra {extra or 'none'}, missing {absent or 'none'}"
                )

        def numbers(key: str) -> tuple[float, ...]:
            v = data[key]
            if not isinstance(v, list | tuple) or len(v) != len(names):
                raise ModelError(f"'{key}' must hold {len(names)} numbers, one per feature")
            return tuple(_number(x, key) for x in v)

        mean, scale, coef = numbers("mean"), numbers("scale"), numbers("coef")
        if any(s <= 0 for s in scale):
            raise ModelError("'scale' must be positive")
        l2 = _number(data.get("l2", 1.0), "l2")
        gate = None if data.get("gate") is None else cls.from_dict(data["gate"])
        return cls(names, mean, scale, coef, _number(data["intercept"], "intercept"), l2, gate)


def _number(x: Any, key: str) -> float:
    if isinstance(x, bool) or not isinstance(x, int | float):
        raise ModelError(f"'{key}' holds a non-number {x!r}")
    if not math.isfinite(x):
        raise ModelError(f"'{key}' holds a non-finite number {x!r}")
    return float(x)


def _newton(
    Z: np.ndarray,
    offset: np.ndarray,
    y: np.ndarray,
    sw: np.ndarray,
    penalty: np.ndarray,
    max_iter: int,
    tol: float,
) -> np.ndarray:
    """Coefficients ``w`` minimising the weighted log-loss of ``sigmoid(Z @ w + offset)``
    plus ``penalty * w**2 / 2``: Newton's method (iteratively reweighted least squares)
    from zero."""
    w = np.zeros(Z.shape[1])
    for _ in range(max_iter):
        p = _sigmoid(Z @ w + offset)
        grad = Z.T @ (sw * (p - y)) + penalty * w
        hess = (Z * (sw * p * (1 - p))[:, None]).T @ Z + np.diag(penalty)
        # A tiny ridge keeps the step defined when l2 = 0 and a column is constant.
        step = np.linalg.solve(hess + 1e-12 * np.eye(len(w)), grad)
        w = w - step
        if np.max(np.abs(step)) < tol:
            break
    return w


def _log_sigmoid(t: np.ndarray) -> np.ndarray:
    """``log(1 / (1 + exp(-t)))``, without overflow."""
    return -np.logaddexp(0.0, -t)


def _and_logit(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Log-odds of ``sigmoid(a) * sigmoid(b)`` (two probabilities given as log-odds),
    finite and accurate at both ends."""
    log_p = _log_sigmoid(a) + _log_sigmoid(b)
    # log(1 - p): expm1 keeps it accurate where p is near 0, and p < 1 for finite a, b.
    log_q = np.log(-np.expm1(np.minimum(log_p, -1e-300)))
    return np.asarray(log_p - log_q, dtype=np.float64)


def _sigmoid(t: np.ndarray) -> np.ndarray:
    """Logistic function without overflow."""
    t = np.asarray(t, dtype=np.float64)
    e = np.exp(-np.abs(t))
    return np.where(t >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


# -- thresholds and calibration -----------------------------------------------------------------


def threshold_for_precision(
    p: np.ndarray, correct: np.ndarray, target: float = 0.99, *, floor: float = 0.0
) -> float:
    """The lowest probability, at or above ``floor``, whose accepted answers
    (``p >= threshold``) reach ``target`` precision on the given answers (ties accepted
    together). Unreachable (even the most confident answers fall short, or there are
    none): 1.0, which accepts nothing (:meth:`ConfidenceModel.predict` stays below 1).
    Non-finite ``p`` are left out."""
    p = np.asarray(p, dtype=np.float64)
    c = np.asarray(correct, dtype=bool)
    if p.shape != c.shape:
        raise HmpfError("p and correct must have the same shape")
    keep = np.isfinite(p)
    p, c = p[keep], c[keep]
    order = np.argsort(-p, kind="stable")
    ps, cs = p[order], c[order].astype(np.float64)
    precision = np.cumsum(cs) / np.arange(1, len(cs) + 1)
    last_of_tie = np.append(ps[1:] != ps[:-1], True)  # accepting ps[i] accepts its ties
    ok = np.flatnonzero(last_of_tie & (precision >= target) & (ps >= floor))
    return float(ps[ok[-1]]) if len(ok) else 1.0


@dataclass(frozen=True)
class Reliability:
    """A reliability diagram's bins (equal width over [0, 1]).

    Attributes:
        lower, upper: (bins,) the bin edges.
        predicted: (bins,) mean predicted probability in the bin (NaN: empty).
        observed: (bins,) share of right answers in the bin (NaN: empty).
        count: (bins,) answers in the bin.
    """

    lower: np.ndarray
    upper: np.ndarray
    predicted: np.ndarray
    observed: np.ndarray
    count: np.ndarray


def reliability(p: np.ndarray, correct: np.ndarray, bins: int = 10) -> Reliability:
    """Per bin of predicted probability (``[i/bins, (i+1)/bins)``, the last one closed):
    mean predicted, observed share right and count."""
    p = np.asarray(p, dtype=np.float64).ravel()
    c = np.asarray(correct, dtype=np.float64).ravel()
    if p.shape != c.shape:
        raise HmpfError("p and correct must have the same shape")
    if bins < 1:
        raise HmpfError("bins must be >= 1")
    if p.size and not (np.isfinite(p).all() and p.min() >= 0 and p.max() <= 1):
        raise HmpfError("probabilities must be finite and in [0, 1]")
    idx = np.minimum((p * bins).astype(np.int64), bins - 1)
    count = np.bincount(idx, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted = np.bincount(idx, weights=p, minlength=bins) / count
        observed = np.bincount(idx, weights=c, minlength=bins) / count
    edges = np.arange(bins + 1) / bins
    return Reliability(edges[:-1], edges[1:], predicted, observed, count)


def expected_calibration_error(p: np.ndarray, correct: np.ndarray, bins: int = 10) -> float:
    """Sum over bins of (share of answers in the bin) x |mean predicted - observed|
    (bins as :func:`reliability`); 0.0 without answers."""
    r = reliability(p, correct, bins)
    n = int(r.count.sum())
    if n == 0:
        return 0.0
    used = r.count > 0
    return float(np.sum(r.count[used] / n * np.abs(r.predicted[used] - r.observed[used])))
