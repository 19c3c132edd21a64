"""The wire models of the HTTP API: request parameters and response bodies.

Plain pydantic, in the core so that both sides use one definition: the service
(:mod:`service.schemas` re-exports them; they also document ``/docs``) and the client
(:mod:`hmpf.client` parses answers with them). The multipart form models, which hold
uploaded files, live with their routes in :mod:`service.routes.localize`.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

#: The longest sequence token accepted: the header, 64 hypotheses, the motion sketch (a
#: filter that weighs motion) and the MAC in base64, with room (see :mod:`service.track`).
MAX_TOKEN_CHARS = 1024

#: Characters of a ``vehicle_id``, spelled out: JSON Schema's regex dialect (ECMA-262) reads
#: ``\w`` as ASCII, Python's and pydantic's as any Unicode letter.
VEHICLE_ID_PATTERN = r"^[A-Za-z0-9_.:@-]+$"
#: The largest ``timestamp`` either way, seconds (about 31,700 years from its epoch): any
#: epoch a camera uses fits, and differences of two stay exact to 0.2 ms.
MAX_TIMESTAMP_S = 1e12

__all__ = [
    "AcceptanceInfo",
    "AcceptedBy",
    "BatchItem",
    "BatchResponse",
    "BuildInfo",
    "Candidate",
    "ErrorBody",
    "ErrorDetail",
    "Experience",
    "Health",
    "IndexInfo",
    "LocalizeFields",
    "LocalizeParams",
    "LocalizeResponse",
    "MAX_TOKEN_CHARS",
    "TRACK_HEADER",
    "VEHICLE_ID_HEADER",
    "VehicleFields",
    "MAX_TIMESTAMP_S",
    "Match",
    "ModelInfo",
    "PriorReport",
    "Ready",
    "ReferenceList",
    "ReloadResponse",
    "SequenceReport",
    "TierReport",
    "VerificationInfo",
    "VEHICLE_ID_PATTERN",
]


class LocalizeFields(BaseModel):
    """Optional fields of a localisation request as one source gives them: the query string
    or the multipart form fields (a field may come from either, not from both). The vehicle's
    id and track are :class:`VehicleFields` (headers or form, not the query string)."""

    model_config = ConfigDict(extra="forbid")

    lat: float | None = Field(
        None, ge=-90, le=90, allow_inf_nan=False, description="GPS prior: latitude"
    )
    lon: float | None = Field(
        None, ge=-180, le=180, allow_inf_nan=False, description="GPS prior: longitude"
    )
    radius_m: float | None = Field(
        None, gt=0, le=20_000_000, allow_inf_nan=False, description="GPS prior radius (metres)"
    )
    top_k: int = Field(
        5, ge=1, description="ranked candidates returned (at most the service's max_top_k)"
    )
    timestamp: float | None = Field(
        None,
        allow_inf_nan=False,
        ge=-MAX_TIMESTAMP_S,
        le=MAX_TIMESTAMP_S,
        description="sequence mode: the frame's capture time in seconds (any epoch, the same "
        "for every frame of the vehicle; at most 1e12 either way, so not milliseconds); "
        "tells the filter how many frames were dropped",
    )


#: Headers of sequence mode: a vehicle's id and its track token never travel in the URL
#: (servers, proxies and browsers log URLs; the token is a bearer token for the track).
VEHICLE_ID_HEADER = "X-Vehicle-Id"
TRACK_HEADER = "X-Track"


class VehicleFields(BaseModel):
    """Sequence mode's identity and state: in the headers :data:`VEHICLE_ID_HEADER` and
    :data:`TRACK_HEADER`, or as multipart form fields; never in the query string."""

    model_config = ConfigDict(extra="forbid")

    vehicle_id: str | None = Field(
        None,
        min_length=1,
        max_length=128,
        pattern=VEHICLE_ID_PATTERN,
        description="the vehicle sending the frame (1-128 ASCII letters, digits and "
        "`_ . : @ -`): turns on sequence mode (the answer follows the vehicle's frames; see "
        "`sequence` in the response). Header `X-Vehicle-Id` or a form field, not the URL",
    )
    track: str | None = Field(
        None,
        min_length=1,
        max_length=MAX_TOKEN_CHARS,
        description="sequence mode: `sequence.track` of this vehicle's previous answer "
        "(omit on the first frame); a token of another vehicle, or altered, is refused (422 "
        "invalid_track). Header `X-Track` or a form field, never the URL (URLs are logged)",
    )


class LocalizeParams(LocalizeFields, VehicleFields):
    """A request's fields from the query string and the form together, checked as a whole."""

    @model_validator(mode="after")
    def _prior(self) -> LocalizeParams:
        given = [v is not None for v in (self.lat, self.lon, self.radius_m)]
        if any(given) and not all(given):
            raise ValueError("a GPS prior needs lat, lon and radius_m together")
        if self.vehicle_id is None and (self.track is not None or self.timestamp is not None):
            raise ValueError("track and timestamp belong to sequence mode: give vehicle_id too")
        return self


#: The rule that decided a match's ``accepted``.
AcceptedBy = Literal["p_correct", "quality", "lock"]


class Experience(BaseModel):
    """Which stored image of the matched place the query matched.

    A place of the map holds its original reference and, once fleet frames have been merged
    into the index (``hmpf-index add --experiences``), further *experiences* of it: frames
    of the same place taken by the vehicles, in other light, weather or seasons. The answer
    names the place (``reference_id``, ``name``, ``lat``/``lon`` are its original
    reference's); this says which of its images looked most like the query.
    """

    row: int = Field(
        description="row of the image in the index version (the place's `reference_id` "
        "when it is the original reference); usable wherever a reference row id is taken "
        "(`/v1/references/{row}/thumbnail`, `/v1/evidence`)"
    )
    name: str = Field(description="the image's name in the index")
    original: bool = Field(
        description="the place's original reference (true) or an experience added from "
        "the fleet (false)"
    )
    vehicle: str | None = Field(
        None, description="a fleet experience: the vehicle that sent the frame (else null)"
    )
    time: float | None = Field(
        None,
        description="a fleet experience: when the frame was taken, seconds since the Unix "
        "epoch (else null)",
    )
    p_correct: float | None = Field(
        None,
        description="a fleet experience: the p_correct its answer had when it was recorded "
        "(else null)",
    )
    log: str | None = Field(
        None, description="a fleet experience: the id of the experience log it came from"
    )
    version: str | None = Field(
        None,
        description="a fleet experience: the index version that answered the frame when it "
        "was recorded",
    )


class Match(BaseModel):
    reference_id: int = Field(
        description="the place: row of its original reference in the index version"
    )
    name: str = Field(description="the place's name (its original reference's)")
    lat: float | None = None
    lon: float | None = None
    score: float | None = Field(
        description="Combined score: z-score over the final candidates (None: not a number, "
        "e.g. a method scored NaN, such a match is never accepted; or a sequence estimate)"
    )
    confidence: float = Field(
        ge=0,
        le=1,
        description="score / largest possible z-score (a sequence estimate: its posterior mass)",
    )
    p_correct: float | None = Field(
        None,
        ge=0,
        le=1,
        description="calibrated probability that this match is right (the place is within "
        "a couple of references of the true one), from the confidence model that "
        "hmpf-calibrate stored in the index's config (`acceptance.model`; a sequence "
        "estimate: `acceptance.sequence_model`). null when the index has no such model "
        "(never a made-up number) or the match has no finite score",
    )
    accepted: bool = Field(
        description="whether to act on this match, decided by the rule in `accepted_by`"
    )
    accepted_by: AcceptedBy = Field(
        description="the rule that decided `accepted`: `p_correct`: p_correct >= the "
        "model's threshold (null p_correct: not accepted); `quality`: no model, score >= the "
        "z threshold (`threshold` of the response); `lock`: a sequence estimate without a "
        "sequence model, accepted when the filter is locked"
    )
    experience: Experience | None = Field(
        None,
        description="which stored image of the place matched: its original reference or an "
        "experience the fleet added (with where it came from). A place scores by its best "
        "image; this is the one that decided the final tier. null where the frame did not "
        "score the place (a sequence estimate elsewhere than the frame's candidates, e.g. "
        "outside its GPS prior)",
    )


class Candidate(BaseModel):
    reference_id: int
    name: str
    score: float | None = Field(default=None, description="Combined score (final ranking)")
    scores: dict[str, float | None] | None = Field(
        default=None, description="per method: score normalised over the tier's inputs (1 = best)"
    )


class TierReport(BaseModel):
    tier: int
    methods: list[str]
    k: int
    inputs: int = Field(description="references the tier scored")
    candidates: list[Candidate] = Field(description="the tier's output list")
    time_ms: float


class PriorReport(BaseModel):
    lat: float
    lon: float
    radius_m: float
    applied: bool
    references: int | None = Field(None, description="references within the radius")
    reason: str | None = None


class SequenceReport(BaseModel):
    """Sequence mode's part of an answer (requests with a ``vehicle_id``)."""

    status: Literal["started", "tracking", "reset", "out_of_order"] = Field(
        description="started: no track given; tracking: the track continued; reset: the "
        "track was not trusted (see reset_reason) and restarted from this frame; "
        "out_of_order: the frame is older than the track: answered single-frame, the "
        "track is returned unchanged"
    )
    reset_reason: Literal["expired", "index_changed"] | None = Field(
        None,
        description="expired: the track is older than the service's track_max_age_s; "
        "index_changed: it was made on another index version",
    )
    match: Match | None = Field(
        description="the filter's estimate (score null, confidence = posterior mass; "
        "accepted by the one acceptance policy: p_correct >= the sequence model's threshold, "
        "or the lower stay threshold while an accepted estimate moves on consistently; "
        "never while off the map); None when out of order"
    )
    mass: float = Field(ge=0, le=1, description="posterior probability near the estimate")
    locked: bool = Field(
        description="the same as `match.accepted` (kept for older clients; act on `match.accepted`)"
    )
    off_map: bool = Field(
        False,
        description="the filter believes the vehicle is not on a mapped route "
        "(off_map_probability >= 0.5): the estimate is not accepted",
    )
    off_map_probability: float = Field(
        0.0, ge=0, le=1, description="posterior probability of the 'not in the map' state"
    )
    frames: int = Field(
        description="frames the track has seen since it (re)started (0 when out of order: "
        "the filter did not run)"
    )
    speed: float | None = Field(
        None, description="most probable speed, references per frame (1: the mapping run's)"
    )
    steps: int | None = Field(
        None, description="frames moved since the previous one (more than 1: frames dropped)"
    )
    track: str = Field(description="send this as `track` with the vehicle's next frame")


class LocalizeResponse(BaseModel):
    match: Match | None = Field(
        description="THE answer: in sequence mode the sequence estimate (accepted by its "
        "p_correct with a sequence model, else when locked), else the single-frame match; "
        "None when the GPS prior leaves no reference. Act on it only when `match.accepted` "
        "(see `match.accepted_by`)"
    )
    match_source: Literal["single", "sequence"] = Field(
        default="single", description="where `match` comes from"
    )
    single: Match | None = Field(None, description="the single-frame match, on its own")
    sequence: SequenceReport | None = Field(
        default=None, description="sequence mode (requests with a vehicle_id), else None"
    )
    candidates: list[Candidate] = Field(description="final ranking by Combined score, top_k")
    tiers: list[TierReport]
    prior: PriorReport | None = None
    timing_ms: dict[str, float | dict[str, float] | list[float]]
    index_version: str
    vehicle_id: str | None = None
    threshold: float = Field(
        description="the z threshold of the `quality` rule (used where no model decides)"
    )


class BatchItem(BaseModel):
    index: int
    result: LocalizeResponse | None = None
    error: ErrorDetail | None = None


class BatchResponse(BaseModel):
    results: list[BatchItem]
    index_version: str
    track: str | None = Field(
        None,
        description="sequence mode: the track after the batch's last answered frame, for "
        "the vehicle's next request",
    )


class ModelInfo(BaseModel):
    """A confidence model the loaded version applies."""

    features: list[str] = Field(description="the answer features it reads, in order")
    threshold: float = Field(ge=0, le=1, description="accepted when p_correct >= this")
    stay_threshold: float | None = Field(
        None,
        ge=0,
        le=1,
        description="sequence model: an estimate accepted on the previous frame that moved "
        "on consistently stays accepted while p_correct >= this (hysteresis)",
    )
    stay_ref_z: float | None = Field(
        None,
        description="sequence model: the stay threshold applies only while the frame's score "
        "at the estimate's reference is at least this many standard deviations from what "
        "unrelated references get (`sequence_ref_z`); below it the entry threshold decides "
        "(null: no such floor)",
    )


class AcceptanceInfo(BaseModel):
    """How the loaded version decides `accepted`."""

    rule: Literal["p_correct", "quality"] = Field(
        description="the single-frame rule: `p_correct` with a model, else `quality`"
    )
    threshold: float = Field(description="the z threshold of the `quality` rule")
    model: ModelInfo | None = Field(
        None, description="single-frame confidence model (null: none, the quality rule)"
    )
    sequence_model: ModelInfo | None = Field(
        None,
        description="sequence-mode confidence model (null: none, the `lock` rule: posterior "
        "mass >= lock_mass, or >= unlock_mass while held)",
    )
    sequence_rule: Literal["p_correct", "lock"] = Field(
        "lock", description="the sequence-mode rule"
    )
    lock_mass: float | None = Field(None, description="the lock rule's threshold")
    unlock_mass: float | None = Field(None, description="the lock rule's stay threshold")
    map_prior: float | None = Field(
        None,
        description="the map's prior the models read (log-odds of the map's pseudo-query "
        "recall@1; null: no model reads it)",
    )
    map_prior_stored: bool | None = Field(
        None,
        description="whether the version stores its prior (`hmpf-index build --map-prior`); "
        "false: the models' conservative `map_prior_fallback` stands in, so fewer answers are "
        "accepted",
    )
    map_prior_fallback: float | None = Field(
        None, description="the prior used for a version that stores none"
    )


class BuildInfo(BaseModel):
    """How the loaded version was made."""

    created: str | None = Field(None, description="when (ISO 8601)")
    operation: str | None = Field(None, description="the indexer operation that wrote it")
    seconds: float | None = None
    images_per_s: float | None = None
    packages: dict[str, Any] | None = Field(
        None,
        description="package versions of the build (admin keys only; null for other keys)",
    )


class VerificationInfo(BaseModel):
    """How the loaded version's files were checked against their manifest's sha256."""

    state: Literal["full", "checking", "passed", "corrupt"] = Field(
        description="full: every file hashed before the version answered; checking: opened "
        "by its verification stamp (its files unchanged since a full check at publish or by "
        "`hmpf-index verify`), the full check running in the background; passed: that check "
        "found every file sound; corrupt: it did not, and the version answers no query (503)"
    )
    seconds: float | None = Field(
        None, description="the hashing before the version answered (null: none, by stamp)"
    )
    check_seconds: float | None = Field(
        None, description="the background check (null: not run, or not finished)"
    )
    problems: list[str] = Field(
        default_factory=list, description="what the background check found, file by file"
    )


class IndexInfo(BaseModel):
    root: str | None = Field(
        None,
        description="the index's folder on the server (admin keys only; null for other keys)",
    )
    version: str = Field(description="the version this server has loaded and answers with")
    current: str | None = Field(
        None,
        description="the version the index's CURRENT names now: another one than `version` "
        "until this server reloads (POST /v1/index/reload, or the watch_current_s setting); "
        "null when CURRENT cannot be read",
    )
    versions: list[str]
    references: int
    methods: dict[str, dict[str, object]]
    config: dict[str, object]
    built: BuildInfo
    has_positions: bool
    threshold: float
    acceptance: AcceptanceInfo
    loaded_at: float
    verification: VerificationInfo | None = Field(
        None, description="how the loaded version's files were verified"
    )


class ReferenceList(BaseModel):
    """Every reference of the loaded version, in row order (``reference_id`` = position)."""

    index_version: str
    names: list[str]
    lat: list[float | None] | None = Field(
        description="latitude per reference (null: the index has no positions)"
    )
    lon: list[float | None] | None = Field(description="longitude per reference")
    thumbnails: bool = Field(description="whether the version stores reference thumbnails")


class ReloadResponse(BaseModel):
    previous: str = Field(description="the version loaded before")
    version: str = Field(description="the version loaded now")
    changed: bool = Field(description="whether the version changed")


class Health(BaseModel):
    status: Literal["ok"]


class Ready(BaseModel):
    status: Literal["ready"]
    index_version: str


class ErrorDetail(BaseModel):
    code: str
    message: str


class ErrorBody(BaseModel):
    error: ErrorDetail
