"""Method interface: the base class checks input, subclasses compute.

A method turns an RGB image into a *feature* and compares a query's feature with reference
features, giving one raw score per reference. Two kinds exist (CONTRIBUTING.md, "Adding a method"):

* ``global``: one fixed-length vector per image; compared by a distance over stacked matrices,
  so it can rank the whole database (tier 1, later through FAISS).
* ``local``: a variable-size set per image (keypoints, regions); compared pairwise, so it is
  used on candidate lists.

``higher_is_better`` says which direction of the raw score is better; fusion normalises every
score to ``best = 1`` (spec §5.1, docs/spec/fusion.md).

A method also declares how it is extracted, so that :mod:`hmpf.features` needs to know no
method family:

* ``batched``: extracted many images at a time in the calling process (a CNN: torch uses every
  core for one batch of ``batch_size`` images) instead of image by image in worker processes;
* :meth:`Method.group_key`: methods with equal keys share one pass per image (one CNN forward
  pass feeds every method on that backbone and input size); :meth:`Method.extract_group` and
  :meth:`Method.fit_group` run such a group;
* :meth:`Method.requires_fit`: parameters are fitted on the reference set first.

A global method declares the FAISS metric reproducing its scores
(:meth:`GlobalMethod.faiss_metric`), which tier 1 searches with.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
import weakref
from abc import ABC, abstractmethod
from collections.abc import Hashable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any, ClassVar, Literal, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from hmpf.imageio import to_rgb
from hmpf.runtime import compute_threads

__all__ = [
    "GlobalMethod",
    "GroupOutput",
    "LocalMethod",
    "Method",
    "MethodConfig",
    "MetricKind",
    "MetricSpec",
    "DbaConfig",
    "ReferenceFitConfig",
    "apply_whitening",
    "extract_many",
    "fit_many",
    "fit_whitening",
    "method_groups",
    "route_dba",
]

MetricKind = Literal["l2", "l1", "ip"]


class MethodConfig(BaseModel):
    """Base of every method's typed configuration: frozen, unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class DbaConfig(MethodConfig):
    """Database-side augmentation option of a global method (see :class:`ReferenceFitConfig`)."""

    dba: int = Field(0, ge=0, le=50, description="route neighbours averaged into a reference")


class ReferenceFitConfig(DbaConfig):
    """Options of a global method fitted on (or computed over) the reference set.

    * ``whiten``: PCA-whitening of the descriptor to this many dimensions (at most the number
      of fitting references minus one), fitted on the references' descriptors
      (:func:`fit_whitening`), stored with the index; the stored and query descriptors are
      the whitened, L2-normalised ones (Euclidean distance, FAISS ``l2``).
    * ``whiten_power``: each principal axis is scaled by ``(eigenvalue + shrink)^-power``:
      0.5 is full whitening, 0 a plain PCA projection, between them power whitening.
    * ``whiten_shrink``: added to every eigenvalue, as a fraction of the mean retained
      eigenvalue (regularises the noisy small ones).
    * ``dba``: database-side augmentation: a reference's stored descriptor becomes the
      L2-normalised weighted mean of itself and its +-``dba`` route neighbours (triangular
      weights ``1 - |j| / (dba + 1)``; :func:`route_dba`); queries are not augmented.
    """

    whiten: int | None = Field(
        None, ge=1, le=4096, description="PCA-whitening output size (None: off)"
    )
    whiten_power: float = Field(0.5, ge=0.0, le=1.0, description="eigenvalue^-power scaling")
    whiten_shrink: float = Field(
        0.0, ge=0.0, le=100.0, description="eigenvalue shrinkage, fraction of the mean"
    )

    @model_validator(mode="after")
    def _check_whiten(self) -> ReferenceFitConfig:
        if self.whiten is None and (self.whiten_power != 0.5 or self.whiten_shrink != 0.0):
            raise ValueError("whiten_power and whiten_shrink need whiten (the output size)")
        return self


#: Options added after a method's first release (reference fitting, multi-scale and
#: multi-crop pooling), left out of its keys while at their defaults, so that configs without
#: them keep the keys (cached descriptors, index identities) they had.
_KEY_DEFAULTS: dict[str, Any] = {
    "dba": 0,
    "whiten": None,
    "whiten_power": 0.5,
    "whiten_shrink": 0.0,
    "scales": (1.0,),
    "crops": 0,
    "precision": "f32",
}


def fit_whitening(
    x: np.ndarray, dims: int, *, power: float = 0.5, shrink: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """PCA-whitening fitted on the rows of ``x`` (n, D): ``(mean (D,), proj (D, p))``.

    ``p = min(dims, n - 1, D)`` (directions beyond ``n - 1`` carry no variance). Axis ``i``
    (eigenvalue ``l_i`` of the sample covariance) is scaled by
    ``(l_i + shrink * mean(l))^-power`` over the ``p`` retained ``l``; tiny eigenvalues
    are floored at ``1e-9`` of the largest. Apply with :func:`apply_whitening`.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or len(x) < 2:
        raise ValueError(f"whitening needs at least 2 descriptors, got shape {x.shape}")
    n, d = x.shape
    p = min(int(dims), n - 1, d)
    mean = x.mean(axis=0)
    xc = x - mean
    if d <= n:  # covariance eigendecomposition (D x D)
        ev, vec = np.linalg.eigh(xc.T @ xc / (n - 1))
        order = np.argsort(ev)[::-1][:p]
        lam, axes = ev[order], vec[:, order]
    else:  # thin SVD of the centred data (n x D)
        _, s, vt = np.linalg.svd(xc, full_matrices=False)
        lam, axes = s[:p] ** 2 / (n - 1), vt[:p].T
    lam = np.maximum(lam, 1e-9 * max(float(lam.max()), 1e-30))
    lam = lam + shrink * float(lam.mean())
    # Sign convention: the largest-magnitude entry of each axis is positive (deterministic).
    sign = np.sign(axes[np.abs(axes).argmax(axis=0), np.arange(axes.shape[1])])
    axes = axes * np.where(sign == 0, 1.0, sign)
    proj = axes * lam[None, :] ** (-power)
    return mean.astype(np.float32), proj.astype(np.float32)


def apply_whitening(x: np.ndarray, mean: np.ndarray, proj: np.ndarray) -> np.ndarray:
    """Rows of ``x`` (or one vector) whitened by :func:`fit_whitening`'s output, L2-normalised
    (float32)."""
    v = (np.asarray(x, dtype=np.float32) - mean) @ proj
    return (v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)).astype(np.float32)


def route_dba(x: np.ndarray, k: int, *, normalise: bool = True) -> np.ndarray:
    """Database-side augmentation along the route: row ``i`` becomes the weighted mean of
    rows ``i-k .. i+k`` (those that exist), weight ``1 - |j| / (k + 1)``, L2-normalised
    (``normalise``) or divided by the weights' sum (otherwise).

    The rows must be in route order (the reference table's order). ``k = 0`` returns ``x``
    unchanged; otherwise the result is float32.
    """
    x = np.asarray(x)
    if k < 0:
        raise ValueError(f"dba must be >= 0, got {k}")
    if k == 0 or len(x) == 0:
        return x
    xf = x.astype(np.float32)
    n = len(xf)
    out = np.zeros_like(xf)
    total = np.zeros((n, 1), dtype=np.float32)
    for j in range(-k, k + 1):
        w = 1.0 - abs(j) / (k + 1)
        lo, hi = max(0, -j), min(n, n - j)  # rows i with 0 <= i + j < n
        if hi <= lo:  # |j| >= n: no such row
            continue
        out[lo:hi] += w * xf[lo + j : hi + j]
        total[lo:hi] += w
    if normalise:
        return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
    return out / total


@dataclass(frozen=True)
class MetricSpec:
    """How FAISS values map to a global method's raw score: ``raw = scale * value``.

    Attributes:
        kind: FAISS metric: ``l2`` Euclidean (FAISS returns squared distances; the square root
            is taken), ``l1`` sum of absolute differences, ``ip`` inner product.
        scale: factor from the FAISS value (after ``sqrt`` for l2) to the raw score.
        proxy: True when ``kind`` only approximates the method's distance (candidates are
            re-scored exactly).
    """

    kind: MetricKind
    scale: float
    proxy: bool = False

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


class GroupOutput(NamedTuple):
    """What :meth:`Method.extract_group` returns for a group over ``n`` images.

    Attributes:
        features: method id -> ``n`` features.
        own_ms: method id -> ``n`` times (ms) of that method's own work per image.
        shared_ms: ``n`` times (ms) of the group's shared work per image (the forward pass).
    """

    features: dict[str, list[Any]]
    own_ms: dict[str, list[float]]
    shared_ms: list[float]

    def ms(self, mid: str) -> list[float]:
        """Method ``mid``'s time per image: the group's shared time plus its own (ms)."""
        return [s + o for s, o in zip(self.shared_ms, self.own_ms[mid], strict=True)]


class Method(ABC):
    """One image-matching technique.

    Subclasses set the class attributes and implement :meth:`_extract` plus the comparison of
    their kind. ``version`` is part of the cache key: bump it whenever the feature a method
    produces changes, so that stale cached descriptors are never reused.

    ``batched``: True for methods extracted many images at a time in the calling process
    (``batch_size`` images per call of :meth:`extract_group`); False for methods extracted
    image by image, in worker processes when there are many images.
    """

    name: ClassVar[str]
    kind: ClassVar[Literal["global", "local"]]
    higher_is_better: ClassVar[bool] = False
    version: ClassVar[str] = "2"
    Config: ClassVar[type[MethodConfig]] = MethodConfig
    batched: ClassVar[bool] = False

    def __init__(self, config: MethodConfig | None = None) -> None:
        self.config = config if config is not None else self.Config()

    # -- extraction -------------------------------------------------------------------------
    def extract(self, image: np.ndarray) -> Any:
        """Compute this method's feature for one H x W x 3 RGB ``uint8`` image."""
        return self._extract(to_rgb(image))

    @abstractmethod
    def _extract(self, image: np.ndarray) -> Any: ...

    @property
    def batch_size(self) -> int:
        """Images per call of :meth:`extract_group` when a batched method extracts many."""
        return 1

    def group_key(self) -> Hashable | None:
        """Methods with equal keys share one pass per image (None: this method runs alone).

        Grouped methods are extracted together by their class's :meth:`extract_group`; only
        methods whose classes share that implementation are grouped (:func:`method_groups`),
        so two method families cannot collide on a key.
        """
        return None

    @classmethod
    def extract_group(
        cls, methods: Mapping[str, Method], images: Sequence[np.ndarray]
    ) -> GroupOutput:
        """Features of ``methods`` (sharing one :meth:`group_key`, or one alone) per image.

        The default extracts each method on its own (no shared work).
        """
        features: dict[str, list[Any]] = {mid: [] for mid in methods}
        own: dict[str, list[float]] = {mid: [] for mid in methods}
        for image in images:
            for mid, method in methods.items():
                t0 = time.perf_counter()
                features[mid].append(method.extract(image))
                own[mid].append((time.perf_counter() - t0) * 1e3)
        return GroupOutput(features, own, [0.0] * len(images))

    @classmethod
    def fit_group(
        cls, methods: Mapping[str, Method], images: Sequence[np.ndarray]
    ) -> GroupOutput | None:
        """Fit (in place) ``methods`` (id -> method, sharing one :meth:`group_key`, each
        ``requires_fit()``) on reference ``images``; methods that fit parameters override it.

        Returns:
            The fitted methods' features of ``images`` where the fit computes them on the way,
            exactly what :meth:`extract_group` would give after the fit; or None.
        """
        names = ", ".join(repr(m.name) for m in methods.values())
        raise NotImplementedError(f"method {names} requires fitting but implements no fit_group")

    # -- comparison -------------------------------------------------------------------------
    @abstractmethod
    def scores(self, query: Any, references: Any, subset: np.ndarray | None = None) -> np.ndarray:
        """Raw scores of one query feature against ``references`` (a stored feature set).

        Args:
            query: the query's feature as returned by :meth:`extract`.
            references: the stored set as returned by :meth:`stack`.
            subset: optional reference indices (candidates); ``None`` means all.

        Returns:
            float64 array, one raw score per reference (or per entry of ``subset``, in order).
        """

    @abstractmethod
    def stack(self, features: Sequence[Any]) -> Any:
        """Combine per-image features into the stored set used by :meth:`scores`."""

    def stack_references(self, features: Sequence[Any]) -> Any:
        """The searched reference set from the references' features in route order:
        :meth:`stack` plus what is computed over the whole set (a global method's ``dba``,
        :meth:`GlobalMethod.augment_references`)."""
        return self.stack(features)

    # -- persistence ------------------------------------------------------------------------
    def to_arrays(self, feature: Any) -> dict[str, np.ndarray]:
        """Feature -> named numpy arrays (for the descriptor cache and the index)."""
        return {"x": np.asarray(feature)}

    def from_arrays(self, arrays: dict[str, np.ndarray]) -> Any:
        """Inverse of :meth:`to_arrays`."""
        return arrays["x"]

    # -- parameters fitted on the reference set --------------------------------------------
    def requires_fit(self) -> bool:
        """True when :meth:`fit_state` must be set (from the references) before extraction.

        Fitted parameters (VLAD centroids, PCA, a visual vocabulary) belong to the reference
        set: they are fitted once on it, stored with it (the index), and never refitted for a
        query.
        """
        return False

    def state_arrays(self) -> dict[str, np.ndarray]:
        """The fitted parameters as named arrays (empty for methods without any)."""
        return {}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        """Set the fitted parameters from :meth:`state_arrays` output."""
        if arrays:
            raise ValueError(f"method {self.name!r} has no fitted parameters")

    def state_digest(self) -> str:
        """sha256 of the fitted parameters ('' when there are none)."""
        arrays = self.state_arrays()
        if not arrays:
            return ""
        h = hashlib.sha256()
        for k in sorted(arrays):
            a = np.ascontiguousarray(arrays[k])
            h.update(f"{k}:{a.dtype.str}:{a.shape}".encode())
            h.update(a.tobytes())
        return h.hexdigest()

    def key_config(self, *, per_image: bool = False) -> dict[str, Any]:
        """The config as it enters the keys: later options (:data:`_KEY_DEFAULTS`) at their
        defaults are left out (older keys stay valid); ``per_image`` also leaves out ``dba``,
        which changes the stored reference set but no image's own feature."""
        cfg = self.config.model_dump()
        for k, default in _KEY_DEFAULTS.items():
            if k in cfg and (cfg[k] == default or (per_image and k == "dba")):
                del cfg[k]
        return cfg

    def _key(self, config: dict[str, Any]) -> str:
        payload = json.dumps(
            {
                "name": self.name,
                "version": self.version,
                "config": config,
                "state": self.state_digest(),
            },
            sort_keys=True,
        )
        return f"{self.name}-{hashlib.sha256(payload.encode()).hexdigest()[:16]}"

    def cache_key(self) -> str:
        """Stable id of this method's exact output: name, code version, config, fitted state."""
        return self._key(self.key_config())

    def descriptor_key(self) -> str:
        """Key of the descriptor cache: the per-image part of :meth:`cache_key` (no ``dba``)
        plus how the features are computed when that can change them within rounding (the
        CNN runtime): cached descriptors of two runtimes are kept apart, while the method's
        identity (recorded in an index) stays the same."""
        return self._key(self.key_config(per_image=True))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.config!r})"

    def __reduce__(self) -> tuple[Any, ...]:
        # Rebuilt from the config (and fitted state) in worker processes: OpenCV objects and
        # torch modules do not pickle.
        return (_rebuild, (type(self), self.config, self.state_arrays()))


def _rebuild(cls: type[Method], config: MethodConfig, state: dict[str, np.ndarray]) -> Method:
    method = cls(config)
    if state:
        method.load_state(state)
    return method


def method_groups(methods: Mapping[str, Method]) -> list[dict[str, Method]]:
    """``methods`` split into groups sharing one pass per image (:meth:`Method.group_key`).

    Groups keep the order of first appearance; a method whose key is None is a group alone,
    and methods share a group only when their classes also share :meth:`Method.extract_group`.
    """
    groups: dict[Hashable, dict[str, Method]] = {}
    for mid, m in methods.items():
        key = m.group_key()
        family = type(m).extract_group.__func__  # type: ignore[attr-defined]
        groups.setdefault(("alone", mid) if key is None else (family, key), {})[mid] = m
    return list(groups.values())


def extract_many(
    methods: Mapping[str, Method],
    images: Sequence[np.ndarray],
    ms: dict[str, list[float]] | None = None,
) -> dict[str, list[Any]]:
    """Every method's feature for every image: {method id: [feature per image]}.

    One pass per image for each group (:func:`method_groups`). When ``ms`` is given, each
    method's time per image (its group's shared time plus its own, ms) is appended to
    ``ms[method id]``.
    """
    out: dict[str, list[Any]] = {mid: [] for mid in methods}
    for group in method_groups(methods):
        res = type(next(iter(group.values()))).extract_group(group, images)
        out.update(res.features)
        if ms is not None:
            for mid in res.own_ms:
                ms.setdefault(mid, []).extend(res.ms(mid))
    return out


def fit_many(
    methods: Mapping[str, Method], images: Sequence[np.ndarray]
) -> dict[str, tuple[list[Any], list[float]]]:
    """Fit (in place) every method whose ``requires_fit()`` is True on ``images``, one pass
    per image for each group.

    Returns:
        method id -> (its features of ``images``, ms per image), for the fitted methods whose
        fit computes them on the way (:meth:`Method.fit_group`): a reference set fitted on
        is not extracted a second time. Times as :func:`extract_many`'s.
    """
    todo = {mid: m for mid, m in methods.items() if m.requires_fit()}
    out: dict[str, tuple[list[Any], list[float]]] = {}
    for group in method_groups(todo):
        res = type(next(iter(group.values()))).fit_group(group, images)
        if res is not None:
            out.update({mid: (res.features[mid], res.ms(mid)) for mid in group})
    return out


class GlobalMethod(Method):
    """A method with one vector per image; the stored set is an N x D matrix.

    Subclasses declare :meth:`faiss_metric`.
    """

    kind: ClassVar[Literal["global", "local"]] = "global"
    # Descriptor length: a class default, set per instance where the config decides it.
    dim: int

    def faiss_metric(self) -> MetricSpec | None:
        """The FAISS metric reproducing :meth:`pairwise` (``raw = scale * value``), or None
        when no FAISS metric does (tier 1 then scans the stored matrix).

        Every global method declares it; this default raises :class:`NotImplementedError`,
        which the index build reports as an error for a tier-1 method.
        """
        raise NotImplementedError(f"global method {self.name!r} declares no FAISS metric")

    def stack(self, features: Sequence[np.ndarray]) -> np.ndarray:
        if len(features) == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        return np.stack([np.asarray(f) for f in features])

    # -- reference fitting: PCA-whitening, database-side augmentation ---------------------
    def _fit_config(self) -> ReferenceFitConfig | None:
        c = self.config
        return c if isinstance(c, ReferenceFitConfig) else None

    def _whitening(self) -> dict[str, np.ndarray]:
        return self.__dict__.setdefault("_whiten_state", {})

    def requires_fit(self) -> bool:
        c = self._fit_config()
        return c is not None and c.whiten is not None and not self._whitening()

    def state_arrays(self) -> dict[str, np.ndarray]:
        return dict(self._whitening())

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        c = self._fit_config()
        if c is None or c.whiten is None:
            super().load_state(arrays)
            return
        missing = {"whiten_mean", "whiten_proj"} - set(arrays)
        if missing:
            raise ValueError(f"{self.name} whitening state lacks {sorted(missing)}")
        state = {k: np.asarray(arrays[k], dtype=np.float32) for k in ("whiten_mean", "whiten_proj")}
        self.__dict__["_whiten_state"] = state
        self.dim = int(state["whiten_proj"].shape[1])

    def fit_references(self, descriptors: np.ndarray) -> None:
        """Fit the whitening (``whiten`` in the config) on reference ``descriptors`` (n, D),
        the method's own unwhitened ones."""
        c = self._fit_config()
        if c is None or c.whiten is None:
            raise ValueError(f"method {self.name!r} has no whitening to fit")
        mean, proj = fit_whitening(
            descriptors, c.whiten, power=c.whiten_power, shrink=c.whiten_shrink
        )
        self.load_state({"whiten_mean": mean, "whiten_proj": proj})

    def finish(self, descriptor: np.ndarray) -> np.ndarray:
        """The stored descriptor from the method's own one: whitened when configured."""
        c = self._fit_config()
        if c is None or c.whiten is None:
            return descriptor
        state = self._whitening()
        if not state:
            raise RuntimeError(f"{self.name} whitening is not fitted: fit on the references first")
        return apply_whitening(descriptor, state["whiten_mean"], state["whiten_proj"])

    def raw_descriptor(self, image: np.ndarray) -> np.ndarray:
        """The method's own descriptor of an RGB image (before :meth:`finish`); methods that
        support whitening implement it instead of ``_extract``."""
        raise NotImplementedError(f"method {self.name!r} implements no raw_descriptor")

    def _extract(self, image: np.ndarray) -> np.ndarray:
        return self.finish(self.raw_descriptor(image))

    @classmethod
    def fit_group(cls, methods: Mapping[str, Method], images: Sequence[np.ndarray]) -> GroupOutput:
        """Fit each method's whitening on its own descriptors of ``images``; their finished
        descriptors of ``images`` come back (the whitening applied, as :meth:`extract`)."""
        features: dict[str, list[Any]] = {}
        own: dict[str, list[float]] = {}
        for mid, m in methods.items():
            g: GlobalMethod = m  # type: ignore[assignment]
            raw, own[mid] = [], []
            for im in images:
                t0 = time.perf_counter()
                raw.append(g.raw_descriptor(to_rgb(im)))
                own[mid].append((time.perf_counter() - t0) * 1e3)
            g.fit_references(np.stack(raw))
            features[mid] = [g.finish(r) for r in raw]
        return GroupOutput(features, own, [0.0] * len(images))

    def stack_references(self, features: Sequence[np.ndarray]) -> np.ndarray:
        return self.augment_references(self.stack(features))

    def augment_references(self, matrix: np.ndarray) -> np.ndarray:
        """The searched reference matrix from the stored one (rows in route order): with
        ``dba``, :func:`route_dba` (same dtype as stored); else ``matrix`` itself.

        An index stores each reference's own descriptor and applies this when it loads
        (and before it writes a FAISS file), so adding or removing references recomputes
        the neighbours' means."""
        c = self.config
        k = c.dba if isinstance(c, DbaConfig) else 0
        if k == 0:
            return matrix
        out = route_dba(matrix, k)
        # Keep the stored precision (float16 descriptors stay float16).
        return out.astype(matrix.dtype) if matrix.dtype.kind == "f" else out

    def scores(
        self, query: np.ndarray, references: np.ndarray, subset: np.ndarray | None = None
    ) -> np.ndarray:
        refs = references if subset is None else references[np.asarray(subset, dtype=np.int64)]
        return self.pairwise(np.asarray(query)[None, :], refs)[0]

    @abstractmethod
    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        """(nq, D) x (n, D) -> (nq, n) float64 raw scores."""


class LocalMethod(Method):
    """A method with a variable-size feature set per image; the stored set is a list."""

    kind: ClassVar[Literal["global", "local"]] = "local"

    def stack(self, features: Sequence[Any]) -> Any:
        """A list by default; subclasses may return their own indexed set type."""
        return list(features)


_REF_CACHE: dict[int, tuple[Any, np.ndarray, np.ndarray]] = {}
_REF_CACHE_SIZE = 8
#: large arrays scored once so far (a second call with the same array caches its float64
#: copy): by id, with a weak reference that tells a reused id from the same array
_SEEN: dict[int, Any] = {}
_SEEN_SIZE = 64
#: float64 elements converted at a time when a matrix is scored without a float64 copy (256
#: KiB: a block, its products and its sums stay in a core's L2 cache; 1 MiB blocks scored
#: 512 NetVLAD rows about 1 ms slower on an Intel Xeon with 1 MiB of L2)
_BLOCK = 1 << 15
#: held while either table is changed (a service's query threads score at the same time)
_TABLES_LOCK = threading.Lock()


def _remembered(table: dict[int, Any], references: np.ndarray) -> Any:
    """``table``'s entry for ``references`` (None: not there, or its id now names another
    array)."""
    hit = table.get(id(references))
    return hit if hit is not None and hit[0]() is references else None


def _remember(table: dict[int, Any], size: int, references: np.ndarray, *value: Any) -> bool:
    """Put ``(weakref(references), *value)`` in ``table`` (at most ``size`` entries, the
    oldest out first, entries of arrays that are gone before any); False when the array
    cannot be weakly referenced (e.g. a list)."""
    try:
        ref = weakref.ref(references)
    except TypeError:
        return False
    with _TABLES_LOCK:
        # Entries of arrays that are gone first (e.g. the rows a previous query gathered),
        # so that they do not push out the matrices every query scores against.
        for k in [k for k, v in table.items() if v[0]() is None]:
            del table[k]
        if len(table) >= size:
            table.pop(next(iter(table)))
        table[id(references)] = (ref, *value)
    return True


def _as_f64_with_norms(references: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``references`` in float64 and their squared row norms, remembered per array.

    A hierarchy scores one query at a time against the same reference matrix; converting
    it to float64 and summing its squares again for every query dominated the per-query
    cost on large maps. The entry lives as long as the array does (weak reference).
    """
    hit = _remembered(_REF_CACHE, references)
    if hit is not None:
        return hit[1], hit[2]
    r = np.asarray(references, dtype=np.float64)
    norms = np.vecdot(r, r)
    _remember(_REF_CACHE, _REF_CACHE_SIZE, references, r, norms)
    return r, norms


def _scored_before(references: np.ndarray) -> bool:
    """Whether ``references`` (a large array) is worth a remembered float64 copy: it is
    remembered already, or this is the second call with it. The rows a query gathers for
    itself (an approximate tier 1's candidates, a later tier's) are scored once and are
    gone: a float64 copy of them would only cost its allocation and its page faults."""
    if _remembered(_REF_CACHE, references) is not None:
        return True
    with _TABLES_LOCK:
        if _remembered(_SEEN, references) is not None:
            del _SEEN[id(references)]
            return True
    return not _remember(_SEEN, _SEEN_SIZE, references)


def euclidean(queries: np.ndarray, references: np.ndarray) -> np.ndarray:
    """Euclidean distances (nq, D) x (n, D) -> (nq, n) float64, exact to rounding.

    Uses the ``|q|^2 + |r|^2 - 2 q.r`` expansion in float64 (clipped at 0): fast for the
    full-database matrices and accurate enough for descriptors of moderate norm. The
    float64 copy of a large reference matrix and its norms are computed once per matrix
    (from its second call on: a matrix scored once is converted a block of rows at a time).

    One query (a hierarchy's every call) takes one dot product per reference, each on its
    own (:func:`_row_dots`): a reference's distance is then the same number whichever other
    references are scored with it (the whole map, a GPS prior's subset, a region shard), and
    whether or not its matrix has a float64 copy.
    """
    q = np.asarray(queries, dtype=np.float64)
    large = isinstance(references, np.ndarray) and references.size >= 1 << 16
    if q.shape[0] == 1 and large and not _scored_before(references):
        dots, rn = _dots_and_norms(q[0], references)
        dots = dots[None, :]
    else:
        if large:
            r, rn = _as_f64_with_norms(references)
        else:
            r = np.asarray(references, dtype=np.float64)
            rn = np.vecdot(r, r)
        dots = _row_dots(q[0], r)[None, :] if q.shape[0] == 1 else q @ r.T
    d2 = (q * q).sum(1)[:, None] + rn[None, :] - 2.0 * dots
    return np.sqrt(np.maximum(d2, 0.0))


#: Rows x dimensions of one query's scoring above which it is split over the compute threads.
_PARALLEL_DOTS = 1 << 22
_dot_pool: ThreadPoolExecutor | None = None
_dot_pool_lock = threading.Lock()


def _row_parts(n: int, d: int) -> np.ndarray:
    """Bounds of the row ranges a scoring of ``n x d`` is split into over the compute
    threads (one range below :data:`_PARALLEL_DOTS` elements)."""
    parts = max(1, min(compute_threads(), (n * d) // _PARALLEL_DOTS)) if n else 1
    return np.linspace(0, n, parts + 1).round().astype(np.int64)


def _in_parts(bounds: np.ndarray, part: Any) -> None:
    """``part(lo, hi)`` for every range of ``bounds``, on the dot pool when there are several."""
    if len(bounds) <= 2:
        part(int(bounds[0]), int(bounds[-1]))
        return
    list(_pool().map(part, bounds[:-1].tolist(), bounds[1:].tolist()))


def _row_dots(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(n,) ``r[i] . q``, each a dot product of its own (a stack of 1 x D by D x 1
    products). A matrix-vector product (``r @ q``) is as fast on one thread but not the same
    to the last bit for every row: BLAS kernels sum a block of rows in one order and the last
    few rows of a call in another (OpenBLAS's dgemv: blocks of 4), and split the rows between
    their threads, so a row's value would depend on how many rows the call held, where the
    row sat and how many threads ran. A large matrix is split into row ranges scored on up to
    :func:`~hmpf.runtime.compute_threads` threads at once (the same numbers: each row is
    still its own product)."""
    n = len(r)
    out = np.empty(n, dtype=np.result_type(r, q))

    def part(lo: int, hi: int) -> None:
        out[lo:hi] = np.matmul(r[lo:hi, None, :], q[:, None])[:, 0, 0]

    _in_parts(_row_parts(n, r.shape[1] if r.ndim == 2 else 0), part)
    return out


def _dots_and_norms(q: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n,) ``r[i] . q`` and ``r[i] . r[i]`` in float64 for a float64 ``q``, converting a
    block of ``r``'s rows to float64 at a time: the numbers of :func:`_row_dots` and
    :func:`_as_f64_with_norms` (each row is still its own product and its own sum) without
    a float64 copy of ``r``."""
    n, d = len(r), r.shape[1]
    dots, norms = np.empty(n), np.empty(n)
    step = max(1, _BLOCK // max(d, 1))

    def part(lo: int, hi: int) -> None:
        for a in range(lo, hi, step):
            b = np.asarray(r[a : min(a + step, hi)], dtype=np.float64)
            norms[a : a + len(b)] = np.vecdot(b, b)
            dots[a : a + len(b)] = np.matmul(b[:, None, :], q[:, None])[:, 0, 0]

    _in_parts(_row_parts(n, d), part)
    return dots, norms


def _pool() -> ThreadPoolExecutor:
    """The threads large row products are split over (one pool per process, made on first
    use, as many threads as cores)."""
    global _dot_pool
    with _dot_pool_lock:
        if _dot_pool is None:
            _dot_pool = ThreadPoolExecutor(
                max_workers=os.cpu_count() or 1, thread_name_prefix="hmpf-dots"
            )
        return _dot_pool
