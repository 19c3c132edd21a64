"""The one acceptance policy: whether an answer is accepted, with what probability, and why.

A vehicle acts on one field, ``accepted``. This module is the only place that decides it; the
service (:mod:`service.answer`) and every evaluation path (:mod:`hmpf.evaluation.acceptance`,
``hmpf-eval``, ``hmpf-calibrate``, the benches) call :class:`Policy`, so what is evaluated is
what the service runs.

The rules, in order:

* **Single frame.** With a confidence model (the config's ``acceptance.model``: fitted by
  ``hmpf-calibrate``, or the model a bundled preset ships, :mod:`hmpf.presets`), the answer
  gets ``p_correct`` (:meth:`~hmpf.confidence.ConfidenceModel.predict` of
  :func:`~hmpf.confidence.answer_features`) and is accepted when ``p_correct >=
  model_threshold`` (``accepted_by = "p_correct"``). Without one, the *quality* rule: the
  Combined z of the answer must reach ``threshold`` (``"quality"``; ``p_correct`` None,
  never a made-up number). An answer without a finite score is never accepted.
* **Sequence mode.** The filter's estimate is the answer. With a sequence model,
  ``p_correct`` is the model's probability of the frame's features with the estimate's,
  times the filter's probability that the vehicle is on the map at all (``1 -``
  :attr:`~hmpf.sequence.Estimate.off_map`), accepted when ``p_correct >=
  sequence_threshold``; without one, the *lock* rule: the estimate's posterior mass must
  reach ``lock_mass`` (``"lock"``). Either way with **hysteresis**: an estimate that was
  accepted on the previous frame (:attr:`~hmpf.sequence.Estimate.held`) and moved on
  consistently with the motion model (:attr:`~hmpf.sequence.Estimate.continuous`) stays
  accepted while its value is at or above the lower *stay* threshold
  (``sequence_stay_threshold``; the lock rule: ``unlock_mass``), so an estimate that stays
  right does not flicker. With ``sequence_stay_ref_z`` the stay threshold also needs the
  frame itself to support the estimate: its score at the estimate's reference must be at
  least that many standard deviations from what unrelated references get
  (``sequence_ref_z``), so the first frame after the vehicle leaves the map, which the
  filter still carries forward, must pass the entry threshold. A frame held back by that
  floor alone (its value reached the stay threshold) is not accepted but does not end the
  lock (:attr:`Decision.kept`): the next frame is still held, so one dark frame costs one
  frame, not the climb back to the entry threshold. And an estimate the filter
  believes is **off the map** (:attr:`~hmpf.sequence.Estimate.off_map` >= 0.5) is never
  accepted, and says so
  (:attr:`Decision.off_map`).

The caller hands the decision back to the filter (:meth:`hmpf.sequence.SequenceFilter.hold`
of :attr:`Decision.holds`) so the next frame knows whether it was held.

Pure and deterministic (numpy only).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from hmpf.confidence import (
    FEATURES,
    MAP_FEATURES,
    PROFILE_FEATURES,
    SEQUENCE_FEATURES,
    ConfidenceModel,
    ModelError,
    ReferenceProfile,
    answer_features,
)
from hmpf.config import AcceptanceSettings
from hmpf.hierarchy import HierarchyResult
from hmpf.sequence import Estimate, RouteMap

__all__ = [
    "DEFAULT_ACCEPT_THRESHOLD",
    "DEFAULT_UNLOCK_MASS",
    "OFF_MAP",
    "SINGLE_MODEL_FEATURES",
    "STAY_P",
    "STAY_REF_Z",
    "AcceptedBy",
    "Decision",
    "Policy",
]

#: The rule that decided an answer.
AcceptedBy = Literal["p_correct", "quality", "lock"]

#: The features a single-frame answer has, so all a single-frame model may read.
SINGLE_MODEL_FEATURES = (*FEATURES, "ref_z", "ref_z_low", "cand_z", "cand_z_low", *MAP_FEATURES)

#: Combined quality (z-score over the final candidates) an answer needs when neither the
#: settings nor the config give a threshold and there is no model. Measured with
#: ``default-lite0`` (the default until 2026-11-26) on the three Gardens Point protocols
#: pooled (600 queries, +-2 frames): every answer at or above 2.9 was right, but only 1.3 %
#: reach it. Only a config without a model meets it: every bundled preset ships one.
DEFAULT_ACCEPT_THRESHOLD = 2.9
#: The lock rule's stay threshold (posterior mass) for an estimate held since the last frame.
DEFAULT_UNLOCK_MASS = 0.9
#: Off-map probability from which an estimate is reported off the map (never accepted).
OFF_MAP = 0.5
#: The stay threshold of the acceptance benches' default recipe (``sequence_stay_threshold``):
#: an estimate accepted on the previous frame that moved on consistently stays accepted while
#: it is more likely right than wrong. Searching it on the training drives (the lowest value
#: keeping 99 % precision) left it next to the entry threshold, so the lock still flickered
#: (16 flips per 100 frames on a held-out Gardens Point night route); 0.5 gave 2 at the same
#: precision (bench/shipped_acceptance.py). The ``default`` preset's shipped models carry 0.9
#: since 2026-11-29: with the map's prior, 0.5 carried a look-alike stretch of wrong answers,
#: and the filter's motion cue keeps 0.9 from flickering
#: (docs/experiments/acceptance/README.md).
STAY_P = 0.5
#: The stay rule's evidence floor of the ``default`` preset's shipped models
#: (``sequence_stay_ref_z``): a held estimate keeps the lower stay threshold only while the
#: frame scores the estimate's reference at least this far (in standard deviations) from
#: what unrelated references get. Chosen on the training parts' drives that leave the map
#: and come back (``python -m bench.stay_rule``): the least strict value of its grid at which
#: no frame off the map was accepted through the stay
#: (docs/experiments/acceptance/stay_rule.json).
STAY_REF_Z = -0.5


@dataclass(frozen=True)
class Decision:
    """What the policy says of one answer.

    Attributes:
        accepted: whether the vehicle may act on it.
        accepted_by: the rule that decided (``p_correct``, ``quality`` or ``lock``).
        p_correct: the model's probability that the answer is right (None without a model,
            or without a finite score).
        off_map: sequence mode: the filter believes the vehicle is not on a mapped route.
        value: the number the rule compared (``p_correct``, the quality or the mass).
        kept: sequence mode: not accepted, but held back only by the stay threshold's
            evidence floor (a held estimate whose ``p_correct`` reached the stay threshold
            on a frame that does not support it): the lock survives the frame, so the next
            frame is still held (:attr:`holds`).
    """

    accepted: bool
    accepted_by: AcceptedBy
    p_correct: float | None = None
    off_map: bool = False
    value: float = float("nan")
    kept: bool = False

    @property
    def holds(self) -> bool:
        """What the filter carries to the next frame as *held*
        (:meth:`hmpf.sequence.SequenceFilter.hold`): accepted, or :attr:`kept`."""
        return self.accepted or self.kept


def _probability(p: float | np.ndarray) -> float | None:
    """A model's prediction as ``p_correct`` (None unless finite and in [0, 1])."""
    v = float(p)
    return v if math.isfinite(v) and 0.0 <= v <= 1.0 else None


@dataclass(frozen=True)
class Policy:
    """A version's acceptance rules (see the module's docstring).

    Attributes:
        threshold: the quality rule's Combined z.
        model, model_threshold: the single-frame confidence model and its threshold.
        sequence_model, sequence_threshold: the sequence model and its threshold.
        sequence_stay_threshold: the sequence model's threshold for an estimate held and
            continuous since the last frame (None: no hysteresis, ``sequence_threshold``).
        sequence_stay_ref_z: the stay threshold applies only to a frame whose
            ``sequence_ref_z`` is at least this (None: to every held, continuous estimate).
        lock_mass, unlock_mass: the lock rule's thresholds (no sequence model).
        map_prior_fallback: the ``map_prior`` the models read for a map that stores none
            (None: such a map is refused, :meth:`with_map_prior`).
    """

    threshold: float = DEFAULT_ACCEPT_THRESHOLD
    model: ConfidenceModel | None = None
    model_threshold: float | None = None
    sequence_model: ConfidenceModel | None = None
    sequence_threshold: float | None = None
    sequence_stay_threshold: float | None = None
    lock_mass: float = 0.99
    unlock_mass: float = DEFAULT_UNLOCK_MASS
    map_prior_fallback: float | None = None
    sequence_stay_ref_z: float | None = None

    @classmethod
    def of(
        cls,
        settings: AcceptanceSettings | None,
        *,
        threshold: float | None = None,
        lock_mass: float = 0.99,
        label: str = "the config",
    ) -> Policy:
        """The rules of a config's ``acceptance`` section; ``threshold`` (e.g. the service's
        setting) overrides its z threshold, ``lock_mass`` is the filter's
        (:attr:`hmpf.sequence.FilterParams.lock_mass`).

        Raises:
            ModelError: a model over features an answer of its kind does not have.
        """
        chosen = threshold if threshold is not None else (settings.threshold if settings else None)
        z = DEFAULT_ACCEPT_THRESHOLD if chosen is None else float(chosen)
        unlock = min(DEFAULT_UNLOCK_MASS, lock_mass)
        if settings is None:
            return cls(z, lock_mass=lock_mass, unlock_mass=unlock)
        model = settings.confidence_model()
        seq = settings.confidence_model(sequence=True)
        for name, m, known in (
            ("model", model, SINGLE_MODEL_FEATURES),
            ("sequence_model", seq, FEATURES + SEQUENCE_FEATURES + PROFILE_FEATURES + MAP_FEATURES),
        ):
            extra = [] if m is None else [f for f in m.features if f not in known]
            if extra:
                raise ModelError(
                    f"{label}: acceptance.{name} needs features an answer of its kind does "
                    f"not have ({', '.join(extra)}); recalibrate"
                )
        return cls(
            z,
            model,
            settings.model_threshold,
            seq,
            settings.sequence_threshold,
            settings.sequence_stay_threshold,
            lock_mass,
            unlock,
            settings.map_prior_fallback,
            settings.sequence_stay_ref_z,
        )

    @property
    def needs_profile(self) -> bool:
        """Whether a model (or the stay rule's evidence floor) reads absolute evidence or the
        map's prior (both come with the references' profile)."""
        floor = self.sequence_stay_ref_z is not None and self.sequence_model is not None
        return floor or self._reads(PROFILE_FEATURES + MAP_FEATURES)

    @property
    def needs_map_prior(self) -> bool:
        """Whether a model reads the map's prior (``map_prior``)."""
        return self._reads(MAP_FEATURES)

    def _reads(self, names: tuple[str, ...]) -> bool:
        """Whether either model reads one of the features ``names``."""
        models = [m for m in (self.model, self.sequence_model) if m is not None]
        return any(f in names for m in models for f in m.features)

    def with_map_prior(
        self, profile: ReferenceProfile | None, label: str = "the map"
    ) -> ReferenceProfile | None:
        """``profile`` as the models read it: when a model reads the map's prior and the map
        stores none, with :attr:`map_prior_fallback` in its place (a conservative prior: fewer
        answers accepted until the version is built with ``hmpf-index build --map-prior``).

        Raises:
            ModelError: a model reads ``map_prior``, the map does not store it and the
                models carry no fallback (or there is no profile at all).
        """
        if not self.needs_map_prior or (profile is not None and profile.map_prior is not None):
            return profile
        if profile is None or self.map_prior_fallback is None:
            raise ModelError(
                f"{label}: the acceptance models read the map's prior (map_prior), which this "
                "version does not store; build it with hmpf-index build --map-prior"
            )
        return replace(profile, map_prior=float(self.map_prior_fallback))

    @property
    def single_rule(self) -> AcceptedBy:
        return "quality" if self.model is None else "p_correct"

    @property
    def sequence_rule(self) -> AcceptedBy:
        return "lock" if self.sequence_model is None else "p_correct"

    # -- single frame ---------------------------------------------------------------------------

    def single(
        self,
        result: HierarchyResult,
        routes: RouteMap,
        profile: ReferenceProfile | None = None,
    ) -> Decision:
        """The decision on a single-frame answer (``result`` on reference ids of ``routes``;
        ``profile`` when the model reads absolute evidence)."""
        feats = None
        if self.model is not None and result.match >= 0 and math.isfinite(result.quality):
            feats = answer_features(result, routes, profile=profile)
        return self.single_from(feats, result.quality, answered=result.match >= 0)

    def single_from(
        self, features: Mapping[str, float] | None, quality: float, *, answered: bool = True
    ) -> Decision:
        """:meth:`single` from the answer's features (:func:`answer_features`; may be None
        without a model) and its Combined quality."""
        q = float(quality)
        if not answered or not math.isfinite(q):
            return Decision(False, self.single_rule, None, value=q)
        if self.model is None or self.model_threshold is None:
            return Decision(q >= self.threshold, "quality", None, value=q)
        if features is None:
            raise ModelError("the single-frame model needs the answer's features")
        p = _probability(self.model.predict(features))
        ok = p is not None and p >= self.model_threshold
        return Decision(ok, "p_correct", p, value=float("nan") if p is None else p)

    # -- sequence mode --------------------------------------------------------------------------

    def sequence(
        self,
        result: HierarchyResult | None,
        estimate: Estimate,
        routes: RouteMap,
        profile: ReferenceProfile | None = None,
    ) -> Decision:
        """The decision on a sequence estimate, with the frame's ``result`` (on reference
        ids; None: the frame had no result)."""
        feats = None
        if self.sequence_model is not None and estimate.ref >= 0:
            feats = answer_features(
                _NO_RESULT if result is None else result,
                routes,
                estimate=estimate,
                profile=profile,
            )
        return self.sequence_from(feats, estimate)

    def sequence_from(
        self,
        features: Mapping[str, float] | None,
        estimate: Estimate,
        *,
        held: bool | None = None,
    ) -> Decision:
        """:meth:`sequence` from the answer's features (with the estimate's; may be None
        without a sequence model). ``held``: whether the previous frame's estimate was
        accepted (None: as the filter carried it, :attr:`~hmpf.sequence.Estimate.held`);
        the stay threshold applies when it was and the estimate moved on consistently."""
        off = float(estimate.off_map)
        off_map = math.isfinite(off) and off >= OFF_MAP
        was = estimate.held if held is None else held
        held = was and estimate.continuous
        if estimate.ref < 0:
            return Decision(False, self.sequence_rule, None, off_map)
        if self.sequence_model is None or self.sequence_threshold is None:
            mass = float(estimate.mass)
            bar = self.unlock_mass if held else self.lock_mass
            ok = math.isfinite(mass) and mass >= bar and not off_map
            return Decision(ok, "lock", None, off_map, mass)
        if features is None:
            raise ModelError("the sequence model needs the answer's features")
        # P(right) = P(on the map) x P(right | on the map): the model speaks for an estimate
        # on the map; the filter's off-map state says how likely that is.
        on = 1.0 - min(1.0, max(0.0, off)) if math.isfinite(off) else 1.0
        p = _probability(on * float(self.sequence_model.predict(features)))
        stay = self.sequence_stay_threshold
        supported = True
        if held and stay is not None and self.sequence_stay_ref_z is not None:
            supported = _supports(features, self.sequence_stay_ref_z)
        bar = stay if held and supported and stay is not None else self.sequence_threshold
        ok = p is not None and p >= bar and not off_map
        # Held back by the floor alone: the frame is not accepted, the lock is not lost.
        kept = not (ok or supported or off_map) and p is not None and stay is not None and p >= stay
        return Decision(ok, "p_correct", p, off_map, float("nan") if p is None else p, kept)

    def describe(self) -> dict[str, Any]:
        """The rules as plain JSON (for ``/v1/index`` and reports)."""

        def model(m: ConfidenceModel | None, threshold: float | None) -> dict[str, Any] | None:
            if m is None or threshold is None:
                return None
            return {"features": list(m.features), "threshold": threshold}

        seq = model(self.sequence_model, self.sequence_threshold)
        if seq is not None:
            seq["stay_threshold"] = self.sequence_stay_threshold
            seq["stay_ref_z"] = self.sequence_stay_ref_z
        return {
            "rule": self.single_rule,
            "sequence_rule": self.sequence_rule,
            "threshold": self.threshold,
            "model": model(self.model, self.model_threshold),
            "sequence_model": seq,
            "lock_mass": self.lock_mass,
            "unlock_mass": self.unlock_mass,
            "map_prior_fallback": self.map_prior_fallback if self.needs_map_prior else None,
        }


def _supports(features: Mapping[str, float], floor: float) -> bool:
    """Whether the frame scores the estimate's reference at least ``floor`` (its
    ``sequence_ref_z``; not finite: no support)."""
    if "sequence_ref_z" not in features:
        raise ModelError(
            "the stay rule's evidence floor needs sequence_ref_z (the references' profile)"
        )
    z = float(features["sequence_ref_z"])
    return math.isfinite(z) and z >= floor


#: A frame without a result (a GPS prior that left no reference): no evidence.
_NO_RESULT = HierarchyResult(-1, float("nan"), np.zeros(0, np.int64), np.zeros(0))
