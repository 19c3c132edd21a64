"""Hierarchy configuration: YAML presets validated by pydantic (unknown keys are errors).

The presets ship inside the package (``hmpf/presets/``, browsable as ``configs/`` in the
repository) and are loaded by name: ``load_config("handcrafted")``,
``load_config("calibrated/gp_dr_nr")``; a path to a YAML file works too.

Example (preset ``handcrafted``)::

    name: handcrafted
    mode: default            # or "faithful": the original's duplicate-keeping fusion
    tier_score: max          # or "mean": a non-final tier's Combined term (see HierarchyConfig)
    methods:                 # optional: parameters per method id (id = method name by default)
      kaze: {max_keypoints: 500}
    tiers:                   # tier 1 first; k = candidates passed on (final tier: list length)
      - {methods: [hog, gist], k: 50}
      - {methods: [sad], k: 10}
      - {methods: [kaze], k: 1}
    weights: [0.5, 0.75, 1.0]   # optional, tier 1 first
    index:                      # optional, for hmpf-index (flags override)
      faiss: {"*": Flat, gem: "IVF4096,Flat"}
      faiss_params: {gem: nprobe=32}
    experiences:                # optional, for hmpf-index add --experiences (flags override)
      min_p_correct: 0.99
      max_per_place: 4

A method id may name a registered method directly, or be declared under ``methods`` with
``type: <registered name>`` plus parameters, so one method can appear with two settings.
"""

from __future__ import annotations

import hashlib
import json
from importlib.resources import files
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hmpf.confidence import MAP_FEATURES, PROFILE_FEATURES, ConfidenceModel
from hmpf.errors import ConfigError, HmpfError
from hmpf.fusion import default_weights
from hmpf.methods import Method, create_method, get_method_class
from hmpf.methods.registry import format_validation_error
from hmpf.sequence import FilterParams

__all__ = [
    "AcceptanceSettings",
    "ExperienceSettings",
    "HierarchyConfig",
    "IndexSettings",
    "TierConfig",
    "build_methods",
    "load_config",
    "preset_names",
]


class TierConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    methods: list[str] = Field(min_length=1)
    k: int = Field(ge=1, description="candidates each method passes on (final tier: list size)")


class IndexSettings(BaseModel):
    """How ``hmpf-index`` stores tier-1 methods (command-line flags override these).

    Attributes:
        faiss: method id (or ``"*"`` for every tier-1 global method) -> FAISS factory string,
            e.g. ``Flat`` (exact, the default), ``IVF4096,Flat``, ``HNSW32``, ``IVF4096,PQ64``.
        faiss_params: method id (or ``"*"``) -> search parameters, e.g. ``nprobe=32``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    faiss: dict[str, str] = Field(default_factory=dict)
    faiss_params: dict[str, str] = Field(default_factory=dict)


class ExperienceSettings(BaseModel):
    """How ``hmpf-index add --experiences`` merges the fleet's recorded frames into a version
    (:mod:`indexer.experiences`); command-line flags override these, and the values a merge used
    are recorded in its manifest. Not part of the index's identity
    (:meth:`HierarchyConfig.digest` ignores the section): they decide which frames become
    experiences, never how any stored feature is computed.

    Attributes:
        min_p_correct: a frame is merged only when its recorded answer had at least this
            ``p_correct`` (0.99: the service's default recording threshold, so a lower value
            matters only for logs recorded with a lower one).
        agreement_window: the frame, localised on its own (one frame, the version's whole
            hierarchy, over places) against the version it is merged into, must land within
            this many places of its recorded place along that place's route (the
            ``sequence`` column, else index order); None turns the check off. It keeps
            wrong frames out (a poisoned log, a wrong sequence-mode lock) at the price of the
            frames a single frame cannot localise.
        duplicate_similarity: a frame whose tier-1 descriptor (the first global method of
            tier 1) has at least this cosine similarity to a stored image of its place, or to
            a frame of the same place kept before it in this merge, adds nothing and is
            skipped (a vehicle standing still records the same picture again and again);
            None turns the check off.
        max_per_place: images a place may hold after a merge, its original reference
            included; the frames kept are those that differ most (greedy farthest point on
            the tier-1 descriptor) from the images already there. A merge never drops a stored
            experience (``hmpf-index remove --experiences-from`` does). None: no cap.
        interpolate_places: a frame is first placed between its time neighbours (the frames
            just before and after it of the same log and vehicle, equally spaced in time, at
            most :data:`indexer.experiences.MAX_NEIGHBOUR_GAP_S` apart) where they advanced an
            even number of places along one route and the frame's recorded place is one place
            off the place midway between them: the vehicle's constant pace is better evidence
            of where it was than the frame's own answer, whose place jitters by one (two frames
            answered at one place, the place after them left without an experience). Not a
            gate: it moves no frame more than one place and is on with the gates open too.
        place_leads: a ``lead`` frame (a lock's lead-in: the service recorded it just before
            a recorded frame of the same vehicle, setting ``experience_lead_frames``) is
            placed back along the route from the frames kept after it, at its vehicle's pace,
            where its own answer agrees within a place (:func:`indexer.experiences.
            place_leads`; else it is left out), then meets the gates after
            ``below_p_correct`` like any frame; False leaves every lead frame out. On with
            the gates open too (without it a lead frame has no place).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    min_p_correct: float = Field(default=0.99, ge=0, le=1)
    agreement_window: int | None = Field(default=3, ge=0)
    duplicate_similarity: float | None = Field(default=0.99, gt=0, le=1)
    max_per_place: int | None = Field(default=4, ge=1)
    interpolate_places: bool = True
    place_leads: bool = True

    @classmethod
    def open(cls) -> ExperienceSettings:
        """Every gate open: each readable frame of a known place is merged (what a
        measurement of the gates compares with); ``interpolate_places`` and ``place_leads``
        as by default."""
        return cls(
            min_p_correct=0.0, agreement_window=None, duplicate_similarity=None, max_per_place=None
        )


class AcceptanceSettings(BaseModel):
    """When an answer is trusted.

    Without a model: its Combined quality (z-score) must reach ``threshold`` (the paper's
    score). With ``model`` (a :class:`hmpf.confidence.ConfidenceModel` as
    :meth:`~hmpf.confidence.ConfidenceModel.to_dict`), an answer gets ``p_correct``, the
    calibrated probability that it is right, and is accepted when ``p_correct >=
    model_threshold``; ``sequence_model`` / ``sequence_threshold`` do the same for the
    sequence filter's estimates (sequence features), and ``sequence_stay_threshold`` the
    lower bar of an estimate accepted on the previous frame that moved on consistently
    (hysteresis, :mod:`hmpf.acceptance`), applied only while the frame's score at the
    estimate's reference is at least ``sequence_stay_ref_z`` standard deviations from what
    unrelated references get (None: always). ``map_prior_fallback``: the ``map_prior`` a model
    that reads it uses for an index version that stores none (the shipped models: the lowest
    prior of the maps they were fitted on, so such a version is accepted conservatively;
    None: such a version is refused). Written by ``hmpf-calibrate`` (the
    thresholds that gave ``precision`` on its training split); not part of the index's
    identity (:meth:`HierarchyConfig.digest` ignores it). A model that does not load
    (another format version, missing or extra features, non-finite numbers) makes the
    config invalid: a clear error, never a silent wrong probability.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    threshold: float
    precision: float | None = Field(None, gt=0, le=1)
    note: str = ""
    model: dict[str, Any] | None = None
    model_threshold: float | None = Field(default=None, ge=0, le=1)
    sequence_model: dict[str, Any] | None = None
    sequence_threshold: float | None = Field(default=None, ge=0, le=1)
    sequence_stay_threshold: float | None = Field(default=None, ge=0, le=1)
    map_prior_fallback: float | None = Field(default=None, allow_inf_nan=False)
    sequence_stay_ref_z: float | None = Field(default=None, allow_inf_nan=False)

    @model_validator(mode="after")
    def _models(self) -> AcceptanceSettings:
        stay = self.sequence_stay_threshold
        if self.sequence_stay_ref_z is not None and stay is None:
            raise ValueError("acceptance.sequence_stay_ref_z needs a sequence_stay_threshold")
        if stay is not None:
            if self.sequence_model is None or self.sequence_threshold is None:
                raise ValueError("acceptance.sequence_stay_threshold needs a sequence_model")
            if stay > self.sequence_threshold:
                raise ValueError(
                    "acceptance.sequence_stay_threshold must not exceed sequence_threshold"
                )

        for name, model, threshold in (
            ("model", self.model, self.model_threshold),
            ("sequence_model", self.sequence_model, self.sequence_threshold),
        ):
            if model is None:
                continue
            if threshold is None:
                raise ValueError(f"acceptance.{name} needs its threshold")
            try:
                ConfidenceModel.from_dict(model)
            except HmpfError as exc:
                raise ValueError(f"acceptance.{name}: {exc}") from None
        return self

    @property
    def needs_profile(self) -> bool:
        """Whether a model reads absolute evidence (:data:`hmpf.confidence.PROFILE_FEATURES`)
        or the map's prior (:data:`~hmpf.confidence.MAP_FEATURES`), so whoever applies it
        must build the references' profile."""
        floor = self.sequence_stay_ref_z is not None
        return floor or any(f in PROFILE_FEATURES or f in MAP_FEATURES for f in self._features())

    @property
    def reads_map_prior(self) -> bool:
        """Whether a model reads the map's prior (:data:`~hmpf.confidence.MAP_FEATURES`)."""
        return any(f in MAP_FEATURES for f in self._features())

    def _features(self) -> list[str]:
        return [f for m in (self.model, self.sequence_model) if m for f in m.get("features", ())]

    def confidence_model(self, sequence: bool = False) -> Any:
        """The :class:`~hmpf.confidence.ConfidenceModel` (single frame, or ``sequence``), or
        None when the config has none."""
        model = self.sequence_model if sequence else self.model
        return None if model is None else ConfidenceModel.from_dict(model)


class HierarchyConfig(BaseModel):
    """A hierarchy: ordered tiers of methods, candidate counts, weights and fusion mode.

    ``tier_score`` says how a non-final tier's methods make its term of the Combined score:
    ``max``, the element-wise maximum (the original's, spec §5.3 in docs/spec/fusion.md), or
    ``mean``, their average, as the final tier and the per-tier recall already use (an extension: on
    the Gardens Point protocols it raises the mean recall@1 of 600 random hierarchies by 1.2 to
    3.4 points on every protocol and split part, ``bench/tier_score.py``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = "unnamed"
    description: str = ""
    mode: Literal["default", "faithful"] = "default"
    tier_score: Literal["max", "mean"] = "max"
    methods: dict[str, dict[str, Any]] = Field(default_factory=dict)
    tiers: list[TierConfig] = Field(min_length=1)
    weights: list[float] | None = None
    index: IndexSettings = Field(default_factory=IndexSettings)
    acceptance: AcceptanceSettings | None = None
    sequence: dict[str, Any] | None = None
    experiences: ExperienceSettings | None = None

    @model_validator(mode="after")
    def _check(self) -> HierarchyConfig:
        if self.sequence is not None:
            try:
                FilterParams.from_mapping(self.sequence)
            except (HmpfError, TypeError) as exc:
                raise ValueError(f"sequence: {exc}") from None
        for i, tier in enumerate(self.tiers):
            if len(set(tier.methods)) != len(tier.methods):
                raise ValueError(f"tiers.{i}.methods lists a method twice")
        if self.weights is not None and len(self.weights) != len(self.tiers):
            raise ValueError(f"weights has {len(self.weights)} entries for {len(self.tiers)} tiers")
        if self.weights is None and len(self.tiers) > 3:
            raise ValueError("more than 3 tiers need explicit weights")
        return self

    @property
    def faithful(self) -> bool:
        return self.mode == "faithful"

    @property
    def tier_weights(self) -> tuple[float, ...]:
        return tuple(self.weights) if self.weights is not None else default_weights(len(self.tiers))

    @property
    def method_ids(self) -> list[str]:
        """Every method id the tiers use, in first-use order."""
        seen: dict[str, None] = {}
        for tier in self.tiers:
            for m in tier.methods:
                seen.setdefault(m, None)
        return list(seen)

    def method_spec(self, method_id: str) -> tuple[str, dict[str, Any]]:
        """(registered type, parameters) of a method id."""
        spec = dict(self.methods.get(method_id, {}))
        return str(spec.pop("type", method_id)), spec

    def sequence_params(self) -> Any:
        """The sequence filter's :class:`~hmpf.sequence.FilterParams` (``sequence:``
        settings over the defaults)."""
        return FilterParams.from_mapping(self.sequence)

    @property
    def experience_settings(self) -> ExperienceSettings:
        """The ``experiences:`` section, or its defaults where the config has none."""
        return self.experiences or ExperienceSettings()

    def digest(self) -> str:
        """sha256 of the canonical JSON of this config (the acceptance threshold, the
        sequence filter's and the experience merge's settings excluded: they change no stored
        feature, and indexes built before they existed keep their identity; likewise
        ``tier_score`` when it is the original's ``max``)."""
        data = self.model_dump(exclude={"acceptance", "sequence", "experiences"})
        if data["tier_score"] == "max":  # the original's: configs (and indexes) from before
            del data["tier_score"]  # the option existed keep their digest
        return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def build_methods(config: HierarchyConfig) -> dict[str, Method]:
    """Instantiate every method the hierarchy uses, keyed by method id."""
    unused = set(config.methods) - set(config.method_ids)
    if unused:
        raise ConfigError(f"methods declared but used by no tier: {', '.join(sorted(unused))}")
    out: dict[str, Method] = {}
    for mid in config.method_ids:
        kind, params = config.method_spec(mid)
        get_method_class(kind)  # UnknownMethodError lists the valid names
        try:
            out[mid] = create_method(kind, params)
        except ConfigError as exc:
            raise ConfigError(f"methods.{mid}: {exc}") from None
    return out


def parse_config(data: Any, source: str = "<config>") -> HierarchyConfig:
    """Validate a mapping; errors name the offending key."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a mapping at the top level")
    try:
        config = HierarchyConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source)) from None
    build_methods(config)  # method names and parameters are checked now, not at first use
    return config


def _presets_dir() -> Traversable:
    return files("hmpf").joinpath("presets")


def _preset_files(folder: Traversable, prefix: str = "") -> dict[str, Traversable]:
    out: dict[str, Traversable] = {}
    for entry in folder.iterdir():
        if entry.is_dir():
            out.update(_preset_files(entry, f"{prefix}{entry.name}/"))
        elif entry.name.endswith(".yaml"):
            out[prefix + entry.name.removesuffix(".yaml")] = entry
    return out


def preset_names() -> list[str]:
    """Names of the shipped presets, sorted: ``handcrafted``, ``calibrated/gp_dr_nr``, ...

    A preset's name is its path under ``hmpf/presets/`` (``configs/`` in the repository)
    without ``.yaml``.
    """
    return sorted(_preset_files(_presets_dir()))


def load_config(path_or_name: str | Path) -> HierarchyConfig:
    """Read and validate a hierarchy: a YAML file, or a shipped preset's name.

    An existing file wins; otherwise ``path_or_name`` (with or without ``.yaml``) names a
    preset (see :func:`preset_names`). Anything else is a :class:`ConfigError` that lists the
    presets.
    """
    p = Path(path_or_name)
    source: Traversable = p
    label = str(p)
    if not p.is_file():
        name = str(path_or_name).removesuffix(".yaml")
        preset = _preset_files(_presets_dir()).get(name)
        if preset is None:
            if p.suffix or p.is_absolute() or p.exists():  # meant as a path
                why = "not a file" if p.exists() else "no such file"
                what = f"cannot read config {str(p)!r}: {why}"
            else:
                what = f"unknown config {str(path_or_name)!r}: neither a file nor a preset"
            raise ConfigError(f"{what}; presets: {', '.join(preset_names())}")
        source, label = preset, f"preset {name!r}"
    try:
        text = source.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read config {label}: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{label}: invalid YAML: {exc}") from None
    return with_shipped_acceptance(parse_config(data, label))


#: Folder (under ``hmpf/presets/``) of the confidence models the bundled presets ship.
SHIPPED_ACCEPTANCE = "acceptance"


def _shipped_files() -> list[tuple[str, str, dict[str, Any]]]:
    """Each ``hmpf/presets/acceptance/<preset>.json`` as ``(file name, digest, content)``,
    read once by :func:`shipped_acceptance` and :func:`with_shipped_acceptance`."""
    folder = _presets_dir().joinpath(SHIPPED_ACCEPTANCE)
    out: list[tuple[str, str, dict[str, Any]]] = []
    if not folder.is_dir():
        return out
    for entry in sorted(folder.iterdir(), key=lambda e: e.name):
        if not entry.name.endswith(".json"):
            continue
        try:
            data = json.loads(entry.read_text())
            out.append((entry.name, str(data["digest"]), data))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"shipped acceptance {entry.name}: {exc}") from None
    return out


def _settings_of(name: str, data: dict[str, Any]) -> AcceptanceSettings:
    """A shipped file's ``acceptance`` section, validated."""
    try:
        return AcceptanceSettings.model_validate(data["acceptance"])
    except (ValueError, KeyError, TypeError, ValidationError) as exc:
        raise ConfigError(f"shipped acceptance {name}: {exc}") from None


def _filter_of(name: str, data: dict[str, Any]) -> dict[str, Any]:
    """The filter settings a shipped file's sequence model was fitted under: its own
    ``sequence`` (``bench/shipped_acceptance.py --write`` records it), else the ``sequence:``
    of the preset it names (``{}``: none set)."""
    try:
        if "sequence" in data:
            return dict(data["sequence"] or {})
        preset = _preset_files(_presets_dir()).get(str(data.get("preset")))
        raw = yaml.safe_load(preset.read_text()) if preset is not None else None
        return dict((raw or {}).get("sequence") or {})
    except (OSError, ValueError, TypeError, AttributeError, yaml.YAMLError) as exc:
        raise ConfigError(f"shipped acceptance {name}: {exc}") from None


def shipped_acceptance() -> dict[str, AcceptanceSettings]:
    """The shipped acceptance settings by hierarchy digest: each
    ``hmpf/presets/acceptance/<preset>.json`` (written by ``bench/shipped_acceptance.py``)
    holds the ``digest`` of the hierarchy its models were fitted for and the ``acceptance``
    section. Keyed by digest, not name: a preset edited since its model was fitted gets no
    stale model, and a YAML file equal to a preset gets the preset's."""
    return {digest: _settings_of(name, data) for name, digest, data in _shipped_files()}


def with_shipped_acceptance(config: HierarchyConfig) -> HierarchyConfig:
    """``config`` with the shipped acceptance of its hierarchy (:func:`shipped_acceptance`)
    when it has no ``acceptance`` section of its own (``hmpf-calibrate``'s models override
    the shipped ones); else ``config`` itself.

    With the shipped models come the filter settings their sequence model was fitted under
    (:func:`_filter_of`) for every setting the config's ``sequence:`` leaves unset: an
    index built before its preset's filter changed keeps its hierarchy (the digest) and gets
    the filter its shipped model reads, not a model fitted for another filter."""
    if config.acceptance is not None:
        return config
    digest = config.digest()
    mine = None
    for name, d, data in _shipped_files():
        settings = _settings_of(name, data)  # every file checked, as shipped_acceptance does
        if d == digest:
            mine = name, data, settings
    if mine is None:
        return config
    name, data, settings = mine
    update: dict[str, Any] = {"acceptance": settings}
    filt = _filter_of(name, data)
    if filt:
        update["sequence"] = {**filt, **(config.sequence or {})}
    return config.model_copy(update=update)
