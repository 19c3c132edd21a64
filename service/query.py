"""One uploaded image's localisation: the work a request hands to :meth:`Engine.run`.

An :class:`ImageQuery` is built on the event loop when the request has been read and called
on a query thread with the request's lease on an index version: it decodes the image, runs
the hierarchy (restricted to the GPS prior, if any), times each stage and returns the answer.
In sequence mode it also keeps the frame's evidence for the filter (:attr:`ImageQuery.evidence`,
with the version it ran on), which the request runs once its frames are answered, in order;
its absolute evidence (:func:`hmpf.confidence.absolute_evidence`, what the filter's
"not in the map" hypothesis weighs) is read from the version's reference profile at the
single-frame answer (NaN when the version has none).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any

from hmpf.confidence import absolute_evidence
from hmpf.errors import HmpfError
from hmpf.hierarchy import HierarchyResult
from hmpf.index.layout import HmpfIndexError
from hmpf.methods import Method
from hmpf.sequence import Evidence
from service.answer import localize_response, on_references
from service.engine import Loaded, Prior, run_query
from service.errors import ApiError
from service.images import decode_upload
from service.schemas import LocalizeParams, LocalizeResponse
from service.track import NO_EVIDENCE

log = logging.getLogger("hmpf.service")

__all__ = ["ImageQuery"]


@dataclass
class ImageQuery:
    """One image of a request, with what its answer needs.

    Attributes:
        data: the uploaded bytes.
        content_type: the declared content type (checked again against the bytes).
        params: the request's fields (one set for every image of a batch).
        source: how messages name the image (``image``, ``images[3]``).
        max_pixels: the pixel limit, read from the header before decoding.
        compute: the engine's pool for the extraction tasks.
        submitted: when the request handed it over (``perf_counter``), for the queue time.
        sequence: keep the frame's evidence for the sequence filter.
        decode_side: the working size the image is decoded at (0: full size).
        keep_features: keep the image's features (for the experience log).
        evidence, loaded: after the call, in sequence mode: the evidence and the version it
            was computed on.
        result: after the call, in sequence mode: the frame's result on reference ids
            (:func:`~service.answer.on_references`; None when the prior left no reference),
            for the estimate's features (a sequence confidence model) and experience.
        features, methods: after the call, with ``keep_features``: the image's features by
            method id and the methods of the version that extracted them.
    """

    data: bytes
    content_type: str | None
    params: LocalizeParams
    source: str
    max_pixels: int
    compute: Executor
    submitted: float = field(default_factory=time.perf_counter)
    sequence: bool = False
    decode_side: int = 0
    keep_features: bool = False
    evidence: Evidence | None = field(default=None, init=False)
    loaded: Loaded | None = field(default=None, init=False, repr=False)
    result: HierarchyResult | None = field(default=None, init=False, repr=False)
    features: dict[str, Any] | None = field(default=None, init=False, repr=False)
    methods: Mapping[str, Method] | None = field(default=None, init=False, repr=False)

    def __call__(self, loaded: Loaded) -> LocalizeResponse:
        """Localise the image against ``loaded`` (on a query thread).

        Raises:
            ApiError: 413 / 415 / 422 for an image that cannot be used.
        """
        timing: dict[str, Any] = {"queue": _ms_since(self.submitted)}
        t = time.perf_counter()
        image = decode_upload(
            self.data,
            max_pixels=self.max_pixels,
            content_type=self.content_type,
            source=self.source,
            decode_side=self.decode_side,
        )
        timing["decode"] = _ms_since(t)
        # The motion cue of a sequence filter that weighs it needs the frame's descriptor.
        motion = loaded.motion if self.sequence else None
        features: dict[str, Any] | None = {} if self.keep_features or motion else None
        try:
            result, allowed = run_query(
                loaded, image, _prior(self.params), timing, self.compute, features
            )
        except HmpfIndexError as exc:  # the index, not the image (a row that cannot be read)
            log.error("index version %s: %s", loaded.version, exc)
            raise ApiError(
                503,
                "index_corrupt",
                f"index version {loaded.version} could not be read while answering (a file "
                "is damaged or truncated); operators: run `hmpf-index verify` on the index and "
                "switch to a sound version (`hmpf-index use`) or rebuild, then reload",
            ) from None
        except HmpfError as exc:
            raise ApiError(422, "invalid_image", f"{self.source}: {exc}") from None
        if features is not None and self.keep_features:
            self.features, self.methods = features, loaded.reader.methods
        if result is None:
            timing["hierarchy"] = 0.0
        else:
            timing["tiers"] = [t.time_ms for t in result.tiers]
            timing["fusion"] = result.fusion_ms
        if self.sequence:
            self.loaded = loaded
            self.evidence = NO_EVIDENCE
            if result is not None:
                on_refs = on_references(result, allowed, loaded.reader.n)
                self.evidence = Evidence.from_result(
                    result,
                    loaded.reader.n,
                    proposals=loaded.sequence.params.proposals,
                    allowed=allowed,
                    absolute=absolute_evidence(on_refs, loaded.profile),
                    sketch=None
                    if motion is None or features is None
                    else motion[1](features[motion[0]]),
                )
                # Kept for the estimate's features (a sequence model) and its experience
                # (which image of the estimate's place matched this frame).
                self.result = on_refs
        answer = localize_response(loaded, result, allowed, self.params, timing)
        answer.timing_ms["total"] = _ms_since(self.submitted)
        return answer


def _prior(params: LocalizeParams) -> Prior | None:
    if params.lat is None or params.lon is None or params.radius_m is None:
        return None  # LocalizeParams has checked that they come together
    return Prior(params.lat, params.lon, params.radius_m)


def _ms_since(start: float) -> float:
    return (time.perf_counter() - start) * 1e3
