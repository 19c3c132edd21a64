"""Request parameters and response bodies of the API (they also document /docs).

The multipart form models, which hold uploaded files, live with their routes in
:mod:`service.routes.localize`; everything here is plain pydantic.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = [
    "BatchItem",
    "BatchResponse",
    "Candidate",
    "ErrorBody",
    "ErrorDetail",
    "IndexInfo",
    "LocalizeFields",
    "LocalizeParams",
    "LocalizeResponse",
    "Match",
    "PriorReport",
    "TierReport",
]


class LocalizeFields(BaseModel):
    """Optional fields of a localisation request as one source gives them: the query string
    or the multipart form fields (a field may come from either, not from both)."""

    model_config = ConfigDict(extra="forbid")

    lat: float | None = Field(None, ge=-90, le=90, description="GPS prior: latitude")
    lon: float | None = Field(None, ge=-180, le=180, description="GPS prior: longitude")
    radius_m: float | None = Field(None, gt=0, le=20_000_000, description="GPS prior radius")
    top_k: int = Field(5, ge=1, description="ranked candidates returned")
    vehicle_id: str | None = Field(None, min_length=1, max_length=128, pattern=r"^[\w.:@-]+$")


class LocalizeParams(LocalizeFields):
    """A request's fields from the query string and the form together, checked as a whole."""

    @model_validator(mode="after")
    def _prior(self) -> LocalizeParams:
        given = [v is not None for v in (self.lat, self.lon, self.radius_m)]
        if any(given) and not all(given):
            raise ValueError("a GPS prior needs lat, lon and radius_m together")
        return self


class Match(BaseModel):
    reference_id: int = Field(description="row of the reference in the index version")
    name: str
    lat: float | None = None
    lon: float | None = None
    score: float | None = Field(
        description="Combined score: z-score over the final candidates (None: not a number, "
        "e.g. a method scored NaN; such a match is never accepted)"
    )
    confidence: float = Field(ge=0, le=1, description="score / largest possible z-score")
    accepted: bool = Field(description="score >= the acceptance threshold")


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


class LocalizeResponse(BaseModel):
    match: Match | None = Field(description="None when the GPS prior leaves no reference")
    candidates: list[Candidate] = Field(description="final ranking by Combined score, top_k")
    tiers: list[TierReport]
    prior: PriorReport | None = None
    timing_ms: dict[str, float | dict[str, float] | list[float]]
    index_version: str
    vehicle_id: str | None = None
    threshold: float


class BatchItem(BaseModel):
    index: int
    result: LocalizeResponse | None = None
    error: ErrorDetail | None = None


class BatchResponse(BaseModel):
    results: list[BatchItem]
    index_version: str


class IndexInfo(BaseModel):
    root: str
    version: str
    versions: list[str]
    references: int
    methods: dict[str, dict[str, object]]
    config: dict[str, object]
    built: dict[str, object]
    has_positions: bool
    threshold: float
    loaded_at: float


class ErrorDetail(BaseModel):
    code: str
    message: str


class ErrorBody(BaseModel):
    error: ErrorDetail
