"""Request parameters and response bodies of the API (they also document /docs).

The models are defined in the core, :mod:`hmpf.api` (the client uses them too), and
re-exported here under their historical names. The multipart form models, which hold
uploaded files, live with their routes in :mod:`service.routes.localize`.
"""

from __future__ import annotations

from hmpf.api import (
    MAX_TIMESTAMP_S,
    TRACK_HEADER,
    VEHICLE_ID_HEADER,
    VEHICLE_ID_PATTERN,
    AcceptanceInfo,
    AcceptedBy,
    BatchItem,
    BatchResponse,
    BuildInfo,
    Candidate,
    ErrorBody,
    ErrorDetail,
    Experience,
    Health,
    IndexInfo,
    LocalizeFields,
    LocalizeParams,
    LocalizeResponse,
    Match,
    ModelInfo,
    PriorReport,
    Ready,
    ReferenceList,
    ReloadResponse,
    SequenceReport,
    TierReport,
    VehicleFields,
)

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
    "VEHICLE_ID_PATTERN",
]
