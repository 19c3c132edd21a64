"""What every bench shares: arguments, protocols, timing and the JSON record.

A bench is a module of this package, run from the repository root::

    python -m bench.accuracy --protocols gp_dr_nr --out results/accuracy.json

and its ``main()`` is short: :func:`parser` (with the ``add_*`` helpers below) parses the
arguments, small functions compute, :func:`write_record` writes the JSON.

* **Arguments**: :func:`parser` (description from the module's docstring; ``--smoke``
  sizes with :meth:`Parser.smoke`), :func:`add_datasets`, :func:`add_cache_dir` (both:
  :func:`add_data`), :func:`add_config`, :func:`add_protocols`, :func:`add_json`.
* **Protocols**: :data:`PROTOCOLS` (Gardens Point's from :mod:`hmpf.datasets`, and
  Nordland summer -> winter), :func:`protocol_data` (an :class:`EvalData` of one of them),
  :func:`split_parts` (its training and test parts).
* **Timing**: :func:`samples_ms` (wall times of repeated calls after a warm-up),
  :func:`median_ms`, :func:`timed`, :func:`percentiles`, :func:`summary`; the machine:
  :func:`machine` (``<CPU>, <n> cores, Python <v>``) and :func:`machine_details` (the same
  split into fields, with the versions of the packages the figures depend on).
* **JSON out**: :func:`provenance` (date, machine, preset and config digest, git commit, the
  command and its arguments), :func:`record` (that beside the bench's own keys) and
  :func:`write_json` / :func:`write_record` (written atomically: a temporary file, then
  :func:`os.replace`).
"""

from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hmpf.config import HierarchyConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root
from hmpf.evaluation.evaluate import EvalData
from hmpf.evaluation.study import split_data
from hmpf.runtime import auto_cnn_runtime, default_cache_dir, machine_description

__all__ = [
    "NORDLAND",
    "PROTOCOLS",
    "RESULTS",
    "ROOT",
    "Parser",
    "add_cache_dir",
    "add_config",
    "add_data",
    "add_datasets",
    "add_json",
    "add_protocols",
    "git_commit",
    "machine",
    "machine_details",
    "median_ms",
    "parser",
    "percentiles",
    "protocol_data",
    "protocol_dirs",
    "provenance",
    "record",
    "samples_ms",
    "split_parts",
    "summary",
    "timed",
    "write_json",
    "write_record",
]

#: The repository root (the benches' default outputs and configs are named from it).
ROOT = Path(__file__).resolve().parent.parent
#: Where a bench writes its JSON unless told otherwise (git ignores it).
RESULTS = ROOT / "results"
#: Nordland summer -> winter (64 x 32 thumbnails, frame-aligned), relative to the datasets.
NORDLAND = ("nordland_64x32/summer", "nordland_64x32/winter")
#: Every frame-aligned protocol the benches use: name -> (reference folder, query folder),
#: relative to :func:`hmpf.datasets.dataset_root`.
PROTOCOLS = {**GARDENS_POINT_PROTOCOLS, "nordland_s_w": NORDLAND}
#: The packages whose versions :func:`machine_details` reports.
PACKAGES = (
    "numpy",
    "scipy",
    "opencv-contrib-python-headless",
    "torch",
    "onnxruntime",
    "openvino",
    "faiss-cpu",
)


# -- arguments ---------------------------------------------------------------------------------


class Parser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` with ``--smoke``: small sizes for a quick run
    (:meth:`smoke`); an option given another value than its default keeps it."""

    def smoke(self, **sizes: Any) -> Parser:
        """Add ``--smoke``: each ``dest=value`` replaces that option's default when set."""
        self._smoke = sizes
        self.add_argument(
            "--smoke",
            action="store_true",
            help="small sizes for a quick check: "
            + ", ".join(f"--{k.replace('_', '-')} {v}" for k, v in sizes.items()),
        )
        return self

    def parse_args(self, args: Sequence[str] | None = None, namespace: Any = None) -> Any:  # type: ignore[override]
        ns = super().parse_args(args, namespace)
        sizes = getattr(self, "_smoke", None)
        if sizes and ns.smoke:
            for dest, value in sizes.items():
                if getattr(ns, dest) == self.get_default(dest):  # not given: the small size
                    setattr(ns, dest, value)
        return ns


def parser(doc: str | None, **kwargs: Any) -> Parser:
    """A :class:`Parser` described by the first line of the bench's docstring, its usage
    line naming ``python -m bench.NAME``."""
    script = Path(sys.argv[0])
    if script.parent.name == "bench" and script.suffix == ".py":
        kwargs.setdefault("prog", f"python -m bench.{script.stem}")
    first = (doc or "").strip().splitlines()[:1]
    return Parser(description=first[0] if first else None, **kwargs)


def add_datasets(ap: argparse.ArgumentParser) -> None:
    """``--datasets``: the shared datasets' folder (``$HMPF_DATASETS``)."""
    ap.add_argument("--datasets", default=str(dataset_root()))


def add_cache_dir(ap: argparse.ArgumentParser) -> None:
    """``--cache-dir``: the feature cache (``$HMPF_CACHE_DIR`` or ``~/.cache/hmpf``)."""
    ap.add_argument("--cache-dir", default=str(default_cache_dir()))


def add_data(ap: argparse.ArgumentParser) -> None:
    """``--datasets`` and ``--cache-dir``: where the images are and their features cached."""
    add_datasets(ap)
    add_cache_dir(ap)


def add_config(ap: argparse.ArgumentParser, default: str = "default", **kwargs: Any) -> None:
    """``--config``: a preset name or a YAML file."""
    ap.add_argument("--config", default=default, **kwargs)


def add_protocols(
    ap: argparse.ArgumentParser,
    default: Iterable[str] | None = None,
    choices: Iterable[str] = tuple(PROTOCOLS),
) -> None:
    """``--protocols``: some of :data:`PROTOCOLS` (default: all of ``choices``)."""
    choices = list(choices)
    ap.add_argument(
        "--protocols",
        nargs="*",
        default=list(choices if default is None else default),
        choices=choices,
    )


def add_json(
    ap: argparse.ArgumentParser,
    flag: str = "--json",
    default: Any = None,
    help: str = "write the figures here too",
    **kwargs: Any,
) -> None:
    """The JSON output's option (``--json`` or ``--out``)."""
    ap.add_argument(flag, default=default, help=help, **kwargs)


# -- protocols ---------------------------------------------------------------------------------


def protocol_dirs(name: str, datasets: str | Path | None = None) -> tuple[Path, Path]:
    """Protocol ``name``'s (reference, query) folders under ``datasets``."""
    root = Path(datasets) if datasets is not None else dataset_root()
    ref, query = PROTOCOLS[name]
    return root / ref, root / query


def protocol_data(name: str, datasets: str | Path | None = None, tolerance: int = 2) -> EvalData:
    """Protocol ``name`` with ground truth +-``tolerance`` frames."""
    return EvalData.frames(*protocol_dirs(name, datasets), tolerance)


def split_parts(
    name: str, datasets: str | Path | None = None, tolerance: int = 2
) -> list[tuple[str, EvalData]]:
    """Protocol ``name``'s training and test parts (``hmpf-calibrate``'s ``blocks`` split),
    as ``[("train", part), ("test", part)]``."""
    data = protocol_data(name, datasets, tolerance)
    return list(zip(("train", "test"), split_data(data), strict=True))


# -- timing ------------------------------------------------------------------------------------


def samples_ms(
    fn: Callable[..., Any], items: Sequence[Any] | None = None, repeats: int = 1
) -> list[float]:
    """Wall times (ms) of ``fn(item)`` for each of ``items`` after a warm-up ``fn(items[0])``;
    without ``items``, of ``repeats`` calls ``fn()`` after a warm-up ``fn()``."""
    calls: list[tuple[Any, ...]] = [()] * repeats if items is None else [(x,) for x in items]
    fn(*calls[0]) if calls else fn()
    runs = []
    for call in calls:
        t = time.perf_counter()
        fn(*call)
        runs.append((time.perf_counter() - t) * 1e3)
    return runs


def median_ms(fn: Callable[[Any], Any], items: Sequence[Any]) -> float:
    """Median wall time (ms) of ``fn(item)`` over ``items``, after one warm-up call."""
    return statistics.median(samples_ms(fn, items))


def timed(fn: Callable[[], Any], repeats: int) -> float:
    """Median wall time (ms) of ``repeats`` calls ``fn()``, after one warm-up call."""
    return statistics.median(samples_ms(fn, repeats=repeats))


def percentiles(ms: Sequence[float], qs: Sequence[float] = (50, 95)) -> tuple[float, ...]:
    """The ``qs`` percentiles of ``ms`` (default: median and 95th)."""
    a = np.asarray(ms, dtype=float)
    return tuple(float(np.percentile(a, q)) for q in qs)


def summary(ms: Sequence[float]) -> dict[str, float | int]:
    """n, median, p95, min and max of a set of timings."""
    p50, p95 = percentiles(ms)
    return {"n": len(ms), "median": p50, "p95": p95, "min": min(ms), "max": max(ms)}


def machine() -> str:
    """``<CPU model>, <n> cores, Python <version>``
    (:func:`hmpf.runtime.machine_description`)."""
    return machine_description()


def _version(package: str) -> str | None:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def machine_details() -> dict[str, Any]:
    """The machine as fields: CPU model, cores, load, Python, OS, package versions, and the
    CNN runtime ``auto`` (the default) chooses on it (a bench that sets runtimes per row
    records each row's own)."""
    cpu = machine_description().rsplit(", ", 2)[0]
    return {
        "cpu": cpu,
        "cnn_runtime_auto": auto_cnn_runtime(),
        "cores": os.cpu_count(),
        "load_1min": os.getloadavg()[0],
        "python": platform.python_version(),
        "platform": platform.platform(),
        "packages": {p: v for p in PACKAGES if (v := _version(p)) is not None},
    }


# -- JSON out ----------------------------------------------------------------------------------


def git_commit() -> dict[str, Any]:
    """The commit the tree was at, and whether the benches' or hmpf's code differed from it."""

    def git(*args: str) -> str:
        try:
            return subprocess.run(
                ["git", *args], cwd=ROOT, capture_output=True, text=True, check=True
            ).stdout.rstrip("\n")  # not strip(): porcelain lines start with a space
        except (OSError, subprocess.CalledProcessError):
            return ""

    changed = git("status", "--porcelain", "--", "bench", "hmpf")
    return {
        "commit": git("rev-parse", "HEAD") or None,
        "code_changed_since_commit": [line[3:] for line in changed.splitlines()],
    }


def _arguments(args: Any) -> dict[str, Any] | None:
    if args is None:
        return None
    items = vars(args) if isinstance(args, argparse.Namespace) else dict(args)
    return json.loads(json.dumps(items, default=str))


def provenance(
    preset: str | None = None,
    config: HierarchyConfig | str | Path | None = None,
    args: Any = None,
) -> dict[str, Any]:
    """What every figure of a report belongs to: the preset and its config digest (``config``
    a loaded config, or a preset name / YAML to load; else ``preset`` is loaded when given),
    the machine, the date (UTC), the git commit, the command line and its parsed arguments."""
    if config is not None and not isinstance(config, HierarchyConfig):
        config = load_config(config)
    elif config is None and preset is not None:
        config = load_config(preset)
    out: dict[str, Any] = {
        "preset": preset,
        "digest": config.digest() if config is not None else None,
        "machine": machine_description(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        **git_commit(),
        "command": " ".join(["python", *sys.argv]),
    }
    if args is not None:
        out["arguments"] = _arguments(args)
    out["machine_details"] = machine_details()
    return out


def record(
    results: dict[str, Any],
    args: Any = None,
    preset: str | None = None,
    config: HierarchyConfig | str | Path | None = None,
    prov: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A bench's JSON record: :func:`provenance` (or ``prov``, taken earlier), then the
    bench's own keys (which win where they share a name)."""
    head = prov if prov is not None else provenance(preset, config, args)
    return {**head, **results}


def write_json(path: str | Path, data: Any, default: Callable[[Any], Any] = str) -> Path:
    """Write ``data`` as JSON (indent 1, a final newline; values JSON lacks written with
    ``default``) to ``path`` atomically: a temporary file beside it, then :func:`os.replace`.
    Its folder is made. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w") as fh:
            fh.write(json.dumps(data, indent=1, default=default) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_record(
    path: str | Path,
    results: dict[str, Any],
    args: Any = None,
    preset: str | None = None,
    config: HierarchyConfig | str | Path | None = None,
    prov: dict[str, Any] | None = None,
    default: Callable[[Any], Any] = str,
) -> Path:
    """:func:`record` written by :func:`write_json`."""
    return write_json(path, record(results, args, preset, config, prov), default)
