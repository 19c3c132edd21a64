"""Process-wide settings: compute threads (FFT and BLAS-like work inside one image), the
signals of worker processes and the descriptor cache's default place. Light to import (the
commands read it before their heavy imports).

Extraction worker processes call :func:`set_compute_threads(1)` so that parallel workers do not
oversubscribe the cores; a single process uses every core for one image. They also call
:func:`ignore_sigint`: Ctrl-C is the parent's to handle (one line, exit 130), not theirs.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

_threads: int | None = None


def compute_threads() -> int:
    """Threads one image's computation may use (``HMPF_THREADS`` or the CPU count)."""
    if _threads is not None:
        return _threads
    env = os.environ.get("HMPF_THREADS")
    if env:
        return max(1, int(env))
    return os.cpu_count() or 1


def default_cache_dir() -> Path:
    """Where extracted descriptors are cached: ``$HMPF_CACHE_DIR`` or ``~/.cache/hmpf/features``."""
    env = os.environ.get("HMPF_CACHE_DIR")
    return Path(env) if env else Path.home() / ".cache" / "hmpf" / "features"


def machine_description() -> str:
    """``<CPU model>, <n> cores, Python <version>``: the machine a measurement ran on."""
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def set_compute_threads(n: int) -> None:
    """Limit this process's per-image threads (also OpenCV's pool)."""
    global _threads
    _threads = max(1, int(n))
    import cv2

    cv2.setNumThreads(_threads)


def ignore_sigint() -> None:
    """Pool-worker initializer: leave Ctrl-C to the parent, so workers print no tracebacks."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
