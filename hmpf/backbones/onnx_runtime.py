"""Backbone forward passes in ONNX Runtime: the torch model exported once, cached on disk.

The ``onnx`` CNN runtime (:func:`hmpf.runtime.cnn_runtime`; the default's choice where the
CPU has no AVX-512 or openvino is not installed) runs a backbone's
:meth:`~hmpf.backbones.base.Backbone.forward_maps` for one set of layers at one input size
through an ONNX Runtime session instead of torch: on one CPU thread EfficientNet-Lite0 runs
about 1.7-1.9x faster than the (already BN-folded, channels-last) torch model
(``bench/cnn_runtime.py``) and the maps equal torch's within float32 rounding (6e-5 on maps
up to 33; ``tests/hmpf/methods/test_cnn_runtime.py``).

* Export: at first use, with torch's TorchScript-based exporter (``torch.onnx.export``,
  ``dynamo=False``; torch is pinned, so is the exporter), at the fixed input size, with a
  dynamic batch dimension and one output per layer. Padding depends on the input size
  (EfficientNet's "same" padding is made constant for it, :meth:`Backbone.for_export`),
  which is why a model is exported per size. The session runs one image at a time
  (:class:`OnnxMaps`).
* Cache: ``<onnx_cache_dir()>/<backbone>-<key>.onnx`` where the key is a sha256 of the
  weights (the loaded module's tensors, so folded BatchNorm and any weight file count), the
  layers, the input size, the export settings (opset, :data:`EXPORT_VERSION`) and the torch
  and onnx versions. A second process loads the file instead of exporting; a changed key
  exports anew. Each file has a ``.sha256`` beside it: a file that does not match it (a
  partial write, a corrupt disk) or that ONNX Runtime cannot load is exported again, never
  an error. Files are written to a temporary name and renamed, so concurrent processes never
  read half a file. When the cache folder is not writable the model goes to a temporary
  folder for this process (a warning says so).
* Index versions: a build copies the exported models into the version
  (:func:`export_model`, :mod:`hmpf.index.models`), and a reader runs them from there
  (:class:`StoredModel`) with onnxruntime alone: no torch, no onnx, no export, no cache.
* OpenVINO (``HMPF_CNN_RUNTIME=openvino`` or ``openvino-bf16``): the same exported files,
  cached or stored, compiled by OpenVINO for the CPU (:class:`OpenVinoSession`) instead of
  loaded by ONNX Runtime; exporting still uses torch and onnx.
* Sessions: one per (model, compute threads, runtime) per process, with ``intra_op_num_threads`` =
  :func:`hmpf.runtime.compute_threads` (1 in extraction workers, the service's per-worker
  threads), sequential execution, and no spinning of idle pool threads (a waiting worker
  burns no CPU). ``InferenceSession.run`` may be called from several threads at once.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
import threading
import warnings
import weakref
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hmpf.backbones.base import Backbone
from hmpf.errors import MissingDependencyError
from hmpf.runtime import EXPORTED_MODEL_RUNTIMES, cnn_runtime, compute_threads, onnx_cache_dir

if TYPE_CHECKING:
    import onnxruntime

__all__ = [
    "EXPORT_VERSION",
    "OPSET",
    "OnnxMaps",
    "OpenVinoSession",
    "StoredModel",
    "clear_sessions",
    "export_key",
    "export_model",
    "model_path",
    "onnx_maps",
    "require_onnxruntime",
]

log = logging.getLogger(__name__)

#: Bump when the export procedure changes (the wrapper, names, settings): new cache keys.
EXPORT_VERSION = "2"  # 2: constant "same" padding (Backbone.for_export)
#: ONNX opset of the exported models.
OPSET = 17
INPUT = "input"

_LOCK = threading.Lock()
_SESSIONS: dict[tuple[str, int, str], OnnxMaps] = {}
_WEIGHTS: weakref.WeakKeyDictionary[Backbone, str] = weakref.WeakKeyDictionary()
_FALLBACK_DIR: Path | None = None


def require_onnxruntime(export: bool = True, runtime: str = "onnx") -> None:
    """Raise :class:`MissingDependencyError` with an install hint when what ``runtime`` runs
    an exported model with (onnxruntime, or openvino) is missing, or, to ``export``, onnx
    (and onnxruntime, which checks an export)."""
    if runtime.startswith("openvino"):
        try:
            import openvino  # noqa: F401  (the openvino extra: checked only when asked for)
        except ImportError:
            raise MissingDependencyError(
                f"HMPF_CNN_RUNTIME={runtime} runs the exported models with OpenVINO: pip "
                "install 'hmpf[openvino]' (or make install), or set HMPF_CNN_RUNTIME=onnx"
            ) from None
        if not export:
            return
    try:
        if export:
            import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
    except ImportError:
        if not export:
            raise MissingDependencyError(
                "the CNN methods run their exported models with onnxruntime: pip install "
                "'hmpf[onnx]' (or 'hmpf[serve]', or make install)"
            ) from None
        raise MissingDependencyError(
            "the onnx CNN runtime needs onnxruntime and onnx: pip install 'hmpf[cnn]' (or "
            "make install), or set HMPF_CNN_RUNTIME=torch"
        ) from None


class OnnxMaps:
    """One exported backbone (layers, input size) in an ONNX Runtime session (or an
    :class:`OpenVinoSession`: the openvino runtimes).

    Calling it on a (B, 3, rows, cols) float32 batch returns {layer: (B, C, h, w) float32}.
    The session runs ``run_batch`` images at a time (the model takes any batch size): one
    image per run is the fastest per image on the CPU, measured 25-40 % faster than runs of
    16 at every default input size (the maps of one image stay in cache).
    """

    def __init__(
        self,
        session: onnxruntime.InferenceSession | OpenVinoSession,
        layers: Sequence[str],
        path: Path,
        run_batch: int = 1,
    ) -> None:
        self.session = session
        self.layers = list(layers)
        self.path = path
        self.run_batch = max(1, run_batch)

    def __call__(self, batch: np.ndarray) -> dict[str, np.ndarray]:
        x = np.ascontiguousarray(batch, dtype=np.float32)
        runs = [
            self.session.run(self.layers, {INPUT: x[s : s + self.run_batch]})
            for s in range(0, max(1, len(x)), self.run_batch)
        ]
        if len(runs) == 1:
            return {k: np.asarray(v) for k, v in zip(self.layers, runs[0], strict=True)}
        return {k: np.concatenate([r[i] for r in runs]) for i, k in enumerate(self.layers)}


def weights_digest(net: Backbone) -> str:
    """sha256 of the backbone module's tensors (names, dtypes, shapes, bytes); once per net."""
    with _LOCK:
        cached = _WEIGHTS.get(net)
    if cached is not None:
        return cached
    h = hashlib.sha256()
    for name, t in sorted(net.module.state_dict().items()):
        a = np.ascontiguousarray(t.detach().cpu().numpy())
        h.update(f"{name}:{a.dtype.str}:{a.shape}\n".encode())
        h.update(a.tobytes())
    digest = h.hexdigest()
    with _LOCK:
        _WEIGHTS[net] = digest
    return digest


def export_key(net: Backbone, layers: Sequence[str], size: tuple[int, int]) -> str:
    """Content key of the exported model of ``net`` for ``layers`` at input ``size``."""
    import onnx  # exporting only (needs the cnn extra; a server need not have it)
    import torch  # the cnn extra; a server running stored ONNX models has no torch

    payload = {
        "backbone": net.name,
        "class": f"{type(net).__module__}.{type(net).__qualname__}",
        "weights": weights_digest(net),
        "layers": list(layers),
        "input_size": [int(v) for v in size],
        "opset": OPSET,
        "export": EXPORT_VERSION,
        "exporter": "torchscript",
        "torch": torch.__version__,
        "onnx": onnx.__version__,
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:32]


def model_path(net: Backbone, layers: Sequence[str], size: tuple[int, int]) -> Path:
    """Where the exported model of ``net`` for ``layers`` at ``size`` is cached."""
    return _cache_dir() / f"{net.name}-{export_key(net, layers, size)}.onnx"


def _cache_dir() -> Path:
    return _FALLBACK_DIR if _FALLBACK_DIR is not None else onnx_cache_dir()


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _sidecar(path: Path) -> Path:
    return path.with_name(path.name + ".sha256")


def _intact(path: Path) -> bool:
    """The cached file exists and matches the sha256 written beside it at export."""
    try:
        return _sidecar(path).read_text().strip() == _file_sha256(path)
    except OSError:
        return False


def _maps_module(net: Backbone, layers: Sequence[str]) -> Any:
    """The exported module: a batch in, the requested maps out (in ``layers`` order)."""
    import torch  # the cnn extra; a server running stored ONNX models has no torch

    names = list(layers)

    class MapsModule(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.inner = net.module

        def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
            maps = net.forward_maps(x, names)
            return tuple(maps[k].float() for k in names)

    return MapsModule().eval()


def _export(net: Backbone, layers: Sequence[str], size: tuple[int, int], path: Path) -> None:
    """Export ``net``'s maps at ``size`` to ``path`` (atomically, with its sha256 beside)."""
    import torch  # the cnn extra; a server running stored ONNX models has no torch

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    module = _maps_module(net.for_export(size), layers)
    example = torch.zeros((2, 3, *size), dtype=torch.float32)
    dynamic = {name: {0: "batch"} for name in [INPUT, *layers]}
    try:
        with warnings.catch_warnings(), torch.no_grad():
            # The tracer warns about the padding computed from the input size (a constant at
            # one size, as intended) and the legacy exporter about itself.
            warnings.simplefilter("ignore")
            torch.onnx.export(
                module,
                (example,),
                str(tmp),
                dynamo=False,
                input_names=[INPUT],
                output_names=list(layers),
                dynamic_axes=dynamic,
                opset_version=OPSET,
                do_constant_folding=True,
            )
        digest = _file_sha256(tmp)
        side_tmp = tmp.with_name(tmp.name + ".sha256")
        side_tmp.write_text(digest + "\n")
        os.replace(tmp, path)
        os.replace(side_tmp, _sidecar(path))
    finally:
        for p in (tmp, tmp.with_name(tmp.name + ".sha256")):
            p.unlink(missing_ok=True)
    log.info("exported %s %s at %s to %s", net.name, list(layers), size, path)


def _check_exported(runtime: str) -> str:
    if runtime not in EXPORTED_MODEL_RUNTIMES:
        raise ValueError(f"runtime must be one of {EXPORTED_MODEL_RUNTIMES}, got {runtime!r}")
    return runtime


def _runtime() -> str:
    """The process's CNN runtime when it runs exported models (``onnx`` otherwise: a torch
    process exports and checks its models with ONNX Runtime)."""
    runtime = cnn_runtime()
    return runtime if runtime in EXPORTED_MODEL_RUNTIMES else "onnx"


class OpenVinoSession:
    """An exported model compiled by OpenVINO for the CPU, run like an ONNX Runtime session
    (:meth:`run`), one image at a time (the input's batch dimension is fixed at 1).

    ``threads`` inference threads, one stream, threads not pinned to cores (replicas and
    workers share the cores); ``precision`` ``f32`` or ``bf16`` (OpenVINO's inference
    precision hint: computed in bfloat16 where the CPU has it, else in float32). An infer
    request per calling thread, so :meth:`run` may be called from several threads at once,
    as an ONNX Runtime session may.
    """

    def __init__(self, path: Path, threads: int, precision: str = "f32") -> None:
        import openvino as ov  # the openvino extra: only the openvino runtimes need it

        core = ov.Core()
        model = core.read_model(str(path))
        shape = model.input(INPUT).get_partial_shape()
        model.reshape({INPUT: [1, *(int(shape[i].get_length()) for i in (1, 2, 3))]})
        self.compiled = core.compile_model(
            model,
            "CPU",
            {
                "INFERENCE_NUM_THREADS": int(threads),
                "NUM_STREAMS": 1,
                "PERFORMANCE_HINT": "LATENCY",
                "ENABLE_CPU_PINNING": False,
                "INFERENCE_PRECISION_HINT": precision,
            },
        )
        # every name of an output (the model's own, e.g. "head", and OpenVINO's node names)
        self._outputs = {n: o for o in self.compiled.outputs for n in o.get_names()}
        self._local = threading.local()

    def run(self, names: Sequence[str], feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        """The outputs ``names`` for ``feeds[INPUT]`` (B, 3, rows, cols), image by image."""
        request = getattr(self._local, "request", None)
        if request is None:
            request = self._local.request = self.compiled.create_infer_request()
        x = feeds[INPUT]
        per_image: list[list[np.ndarray]] = []
        for i in range(len(x)):
            request.infer({INPUT: x[i : i + 1]})
            per_image.append([request.get_tensor(self._outputs[n]).data.copy() for n in names])
        return [np.concatenate([p[k] for p in per_image]) for k in range(len(names))]


def _session(path: Path, threads: int, runtime: str = "onnx") -> Any:
    """A session running ``path`` on ``threads`` threads in ``runtime`` (an
    ONNX Runtime session or an :class:`OpenVinoSession`)."""
    if runtime == "openvino":
        return OpenVinoSession(path, threads, "f32")
    if runtime == "openvino-bf16":
        return OpenVinoSession(path, threads, "bf16")
    import onnxruntime as ort  # the onnx extra: CNN methods only

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # Idle intra-op threads sleep instead of spinning: a worker waiting for its next image
    # uses no CPU (the default spins, which shows as busy cores between queries).
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3  # errors only
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def onnx_maps(
    net: Backbone, layers: Sequence[str], size: tuple[int, int], runtime: str | None = None
) -> OnnxMaps:
    """The session computing ``net``'s ``layers`` at input ``size`` in ``runtime`` (None:
    the process's, :func:`~hmpf.runtime.cnn_runtime`; ``onnx`` in a torch process).

    Loads the cached export (exporting it first when it is missing, corrupt or unloadable);
    one session per model, :func:`~hmpf.runtime.compute_threads` value and runtime per
    process.
    """
    global _FALLBACK_DIR
    runtime = _check_exported(runtime) if runtime else _runtime()
    require_onnxruntime(runtime=runtime)
    threads = compute_threads()
    size = (int(size[0]), int(size[1]))
    path = model_path(net, layers, size)
    key = (str(path), threads, runtime)
    with _LOCK:
        hit = _SESSIONS.get(key)
        if hit is not None:
            return hit
        session = None
        if _intact(path):
            try:
                session = _session(path, threads, runtime)
            except Exception as exc:  # the runtime's own error types (InvalidProtobuf, Fail...)
                log.warning(
                    "cached ONNX model %s does not load (%s): exporting it again", path, exc
                )
        if session is None:
            try:
                _export(net, layers, size, path)
            except OSError as exc:
                if _FALLBACK_DIR is not None:
                    raise
                _FALLBACK_DIR = Path(tempfile.mkdtemp(prefix="hmpf-onnx-"))
                log.warning(
                    "cannot write the ONNX cache %s (%s): exporting to %s for this process",
                    path.parent,
                    exc,
                    _FALLBACK_DIR,
                )
                path = _FALLBACK_DIR / path.name
                _export(net, layers, size, path)
            session = _session(path, threads, runtime)
        maps = OnnxMaps(session, layers, path)
        _SESSIONS[key] = maps
        return maps


def export_model(net: Backbone, layers: Sequence[str], size: tuple[int, int], dest: Path) -> str:
    """Write ``net``'s exported model for ``layers`` at ``size`` to ``dest`` (a copy of the
    cached export, exported first when needed: the model the extraction of this process
    runs). Returns its :func:`export_key`."""
    maps = onnx_maps(net, layers, size)
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(maps.path, dest)
    return export_key(net, layers, (int(size[0]), int(size[1])))


class StoredModel:
    """An exported model kept outside the cache (in an index version, where the manifest's
    sha256 vouches for it): ``path`` computes ``layers`` at input ``size``.

    Running it needs onnxruntime (or openvino) only: no torch, no onnx. Sessions are made on
    first use, one per :func:`~hmpf.runtime.compute_threads` value and runtime, and live as
    long as this object (the reader that holds it). ``runtime`` runs it in that runtime
    (``onnx``, ``openvino``, ``openvino-bf16``) whatever the process's; None (the default):
    the process's (:func:`~hmpf.runtime.cnn_runtime`).
    """

    def __init__(
        self,
        path: Path,
        layers: Sequence[str],
        size: tuple[int, int],
        info: dict[str, Any] | None = None,
        runtime: str | None = None,
    ) -> None:
        self.runtime = _check_exported(runtime) if runtime is not None else None
        self.path = Path(path)
        self.layers = list(layers)
        self.size = (int(size[0]), int(size[1]))
        #: what else is known of it (an index manifest's entry: export key, exporter...)
        self.info: dict[str, Any] = dict(info or {})
        self._lock = threading.Lock()
        #: by (compute threads, runtime)
        self._sessions: dict[tuple[int, str], Any] = {}

    def __repr__(self) -> str:
        return f"StoredModel({str(self.path)!r}, {self.layers}, {self.size})"

    def covers(self, layers: Sequence[str]) -> bool:
        return set(layers) <= set(self.layers)

    def maps(self, layers: Sequence[str], runtime: str | None = None) -> OnnxMaps:
        """The session computing ``layers`` (a subset of this model's outputs) in
        ``runtime`` (None: this model's own, else the process's)."""
        if not self.covers(layers):
            raise ValueError(f"{self.path} computes {self.layers}, not {sorted(layers)}")
        runtime = _check_exported(runtime) if runtime else self.runtime or _runtime()
        require_onnxruntime(export=False, runtime=runtime)
        key = (compute_threads(), runtime)
        with self._lock:
            session = self._sessions.get(key)
            if session is None:
                session = self._sessions[key] = _session(self.path, *key)
        return OnnxMaps(session, list(layers), self.path)


def clear_sessions() -> None:
    """Forget this process's sessions (the next call loads the cached files again)."""
    with _LOCK:
        _SESSIONS.clear()
