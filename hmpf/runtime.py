"""Process-wide settings: compute threads (FFT and BLAS-like work inside one image), the
runtime of the CNN forward passes, the signals of worker processes and the caches' default
places. Light to import (the commands read it before their heavy imports).

Extraction worker processes call :func:`set_compute_threads(1)` so that parallel workers do not
oversubscribe the cores; a single process uses every core for one image. They also call
:func:`ignore_sigint`: Ctrl-C is the parent's to handle (one line, exit 130), not theirs.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import platform
import signal
from pathlib import Path

from hmpf.errors import ConfigError

_threads: int | None = None
_cnn_runtime: str | None = None

#: Runtimes of the CNN backbones' forward passes (:func:`cnn_runtime`).
CNN_RUNTIMES = ("onnx", "openvino", "openvino-bf16", "torch")
#: The runtimes that run a backbone's exported ONNX model (cached, or stored in an index
#: version): every one but ``torch``.
EXPORTED_MODEL_RUNTIMES = ("onnx", "openvino", "openvino-bf16")
#: What ``HMPF_CNN_RUNTIME`` may say: a runtime, or ``auto`` (the default:
#: :func:`auto_cnn_runtime`).
CNN_RUNTIME_SETTINGS = ("auto", *CNN_RUNTIMES)


def compute_threads() -> int:
    """Threads one image's computation may use (``HMPF_THREADS`` or the CPU count)."""
    if _threads is not None:
        return _threads
    env = os.environ.get("HMPF_THREADS")
    if env:
        return max(1, int(env))
    return os.cpu_count() or 1


def cnn_runtime() -> str:
    """Runtime of the CNN forward passes on the CPU. Set by :func:`set_cnn_runtime` or
    ``HMPF_CNN_RUNTIME``:

    * ``auto`` (the default): ``openvino`` where it is installed and the CPU has AVX-512,
      else ``onnx`` (:func:`auto_cnn_runtime`);
    * ``onnx``: the torch model exported once to ONNX and run by ONNX Runtime, about
      1.7-1.9x faster than torch on one thread;
    * ``openvino``: the same exported model compiled by OpenVINO for the CPU, in float32
      (the ``openvino`` extra): about 1.15-1.26x faster than ONNX Runtime on CPUs with
      AVX-512, no faster with AVX2 only (docs/experiments/cpu_levers/openvino.md);
    * ``openvino-bf16``: the same, computing in bfloat16 where the CPU has it (AVX-512 BF16 or
      AMX; elsewhere OpenVINO computes in float32);
    * ``torch``: the reference implementation.

    Returns the runtime itself, never ``auto``. ``onnx``, ``openvino`` and ``torch`` give the
    same maps within float32 rounding (tests/hmpf/methods/test_cnn_runtime.py): the runtime is
    how descriptors are computed, not what they are, so it is not part of a config's digest
    nor of a method's :meth:`~hmpf.methods.base.Method.cache_key` (an index built with one
    runtime serves queries with another). ``openvino-bf16`` is not within float32 rounding:
    its recall against the float32 runtimes is measured by ``python -m bench.int8_recall``
    (docs/experiments/cpu_levers/openvino.md). The descriptor
    cache keeps every runtime apart (:meth:`~hmpf.methods.base.Method.descriptor_key`).
    """
    if _cnn_runtime is not None:
        return _cnn_runtime
    return _resolve(os.environ.get("HMPF_CNN_RUNTIME") or "auto", "HMPF_CNN_RUNTIME")


def set_cnn_runtime(name: str) -> None:
    """Choose the CNN runtime of this process and of the processes it starts (also sets
    ``HMPF_CNN_RUNTIME``, to the runtime ``auto`` chose when given ``auto``)."""
    global _cnn_runtime
    _cnn_runtime = _resolve(name, "CNN runtime")
    os.environ["HMPF_CNN_RUNTIME"] = _cnn_runtime


def choose_cnn_runtime(cpu_flags: set[str], openvino_installed: bool) -> str:
    """What ``auto`` runs on a CPU with ``cpu_flags`` (``/proc/cpuinfo``'s): ``openvino``
    (float32: the same answers as ONNX Runtime) where it is installed and the CPU has AVX-512
    (``avx512f``; AMX CPUs have it too), else ``onnx``.

    Measured, the default preset, one run each: AMD EPYC with AVX-512 BF16 1.18x one query,
    1.18x HTTP p50 and answers/s with 8 clients, 1.08x build (docs/experiments/speed/
    speed_table_avx512.json); Intel Xeon with AMX 1.26x one query (cpu_levers/openvino_amx.json);
    AMD EPYC with AVX2 only 1.00x one query and 0.97x answers/s with 8 clients
    (cpu_levers/openvino.md): there ONNX Runtime stays."""
    return "openvino" if openvino_installed and "avx512f" in cpu_flags else "onnx"


@functools.cache
def auto_cnn_runtime() -> str:
    """:func:`choose_cnn_runtime` for this machine (read once per process; the CPU flags from
    ``/proc/cpuinfo``: Linux on x86, elsewhere ``onnx``). Where the CPU has AVX-512, openvino
    is imported to see that it works: an installed package that fails to import leaves
    ``onnx``."""
    flags = cpu_flags()
    if choose_cnn_runtime(flags, openvino_installed=True) == "onnx":
        return "onnx"  # openvino would not be chosen: not imported
    try:
        installed = importlib.util.find_spec("openvino") is not None
        if installed:
            import openvino  # noqa: F401  (the openvino extra)
    except Exception:  # a broken install: ONNX Runtime, as without the package
        installed = False
    return choose_cnn_runtime(flags, installed)


def _resolve(name: str, what: str) -> str:
    value = name.strip().lower()
    if value not in CNN_RUNTIME_SETTINGS:
        raise ConfigError(f"{what} must be one of {', '.join(CNN_RUNTIME_SETTINGS)}, got {name!r}")
    return auto_cnn_runtime() if value == "auto" else value


def onnx_cache_dir() -> Path:
    """Where exported ONNX models are cached: ``$HMPF_CACHE_DIR/onnx`` or
    ``~/.cache/hmpf/onnx``."""
    env = os.environ.get("HMPF_CACHE_DIR")
    return Path(env) / "onnx" if env else Path.home() / ".cache" / "hmpf" / "onnx"


def default_cache_dir() -> Path:
    """Where extracted descriptors are cached: ``$HMPF_CACHE_DIR`` or ``~/.cache/hmpf/features``."""
    env = os.environ.get("HMPF_CACHE_DIR")
    return Path(env) if env else Path.home() / ".cache" / "hmpf" / "features"


def vector_extensions(flags: set[str]) -> str | None:
    """The widest vector instructions among a CPU's ``/proc/cpuinfo`` flags, as a short name
    (``AMX``, ``AVX-512 BF16``, ``AVX-512``, ``AVX2``), or None: CNN passes run up to twice as
    fast with AVX-512 as with AVX2, so two machines that both say "AMD EPYC" are told apart."""
    for flag, name in (
        ("amx_bf16", "AMX"),
        ("avx512_bf16", "AVX-512 BF16"),
        ("avx512f", "AVX-512"),
        ("avx2", "AVX2"),
    ):
        if flag in flags:
            return name
    return None


def _cpuinfo() -> dict[str, str]:
    """The first CPU's ``/proc/cpuinfo`` fields (empty where there is none)."""
    fields: dict[str, str] = {}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())  # the first CPU's
    except OSError:
        pass
    return fields


def cpu_flags() -> set[str]:
    """The CPU's ``/proc/cpuinfo`` flags (empty where it does not say)."""
    return set(_cpuinfo().get("flags", "").split())


def machine_description() -> str:
    """``<CPU model> (<vector extensions>), <n> cores, Python <version>``: the machine a
    measurement ran on (:func:`vector_extensions`; left out where ``/proc/cpuinfo`` does not
    say)."""
    fields = _cpuinfo()
    cpu = fields.get("model name") or platform.processor() or platform.machine()
    isa = vector_extensions(set(fields.get("flags", "").split()))
    if isa:
        cpu = f"{cpu} ({isa})"
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def set_compute_threads(n: int) -> None:
    """Limit this process's per-image threads (also OpenCV's pool)."""
    global _threads
    _threads = max(1, int(n))
    import cv2  # OpenCV takes ~0.3 s to import: loaded on first use

    cv2.setNumThreads(_threads)


def ignore_sigint() -> None:
    """Pool-worker initializer: leave Ctrl-C to the parent, so workers print no tracebacks."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
