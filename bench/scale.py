"""Scale bench: real index versions of 1k / 100k / 1M references, served by the real hmpf-serve.

    .venv/bin/python -m bench.scale write --refs 100000 --out /work/scale/v100k
    .venv/bin/python -m bench.scale measure --index /work/scale/v100k
    .venv/bin/python -m bench.scale report docs/experiments/scale/measure-*.json

``write`` publishes a real index version (the layout, manifest, checksums, ONNX models,
FAISS files, profile and verification stamp of ``hmpf-index build``: it goes through
:class:`indexer.build.VersionTransaction`) of ``--refs`` references, generated and written
block by block (:class:`hmpf.index.storage.RowBlocks`; nothing holds ``N x D`` floats):

* **planted**: Gardens Point day_left's 200 real references (every stored array: GeM,
  NetVLAD, Gist, OLO blocks, thumbnails) as one route at a known place (``--planted-at``,
  default the middle), so that the real night_right frames have a ground truth;
* **distractors**: the rest, in routes of ``--route-len`` (1000): each global descriptor
  drawn from a Gaussian fitted to the real descriptors of Nordland summer (3576 frames of
  another country, camera and season, so none shows a planted place or the query
  traverse): the mean, the top ``--components`` principal components with their variances,
  and an isotropic residual with the rest of the variance; consecutive rows of a route
  follow a first-order autoregression fitted to Nordland's consecutive frames (per
  component, and one coefficient for the residual), so a route looks like a route. Each
  row is then normalised as its method normalises its output (GeM: positive, L2, float16
  precision; NetVLAD: intra-normalised per cluster, L2, float16 precision; Gist: positive),
  and OLO's blocks and the thumbnail are copied from a random real Nordland reference.

The real descriptors come from a real version (``--source``, built once with the real CLI
if missing: ``hmpf-index build`` on day_left with the bench's config, then ``hmpf-index add``
of Nordland summer, so every method has day_left's fitted state, as the planted rows).
``write`` prints how the synthetic statistics compare with the real ones (distances to
the nearest reference of the night_right queries and of each reference, and between
consecutive rows of a route, real Nordland against as many synthetic rows).

``measure`` opens the version with :class:`hmpf.index.reader.IndexReader` and measures
tier-1 recall@100 and @10 of the reader's approximate tier 1 (FAISS's ``approx_k``
candidates and the fixed sample re-scored exactly) against exact search (chunked float32
products over the stored float16 matrices, then re-scored by the method), on the real
night_right queries, per ``--nprobe``; then starts the real ``hmpf-serve`` (one worker, one
thread; :func:`bench.service_load._start`) and measures the time from the process's start
to its first answer, resident memory (:func:`bench.capacity.rss_mib`) after the warm-up and
after the queries, latency p50 / p99 of the 200 night_right frames sent one at a time in
single-frame mode after 5 warm-up frames, and recall@1 of the answers against the planted
ground truth (+-2 frames).

The config is a parameter; the default, ``bench/scale/default-olo25.yaml``, is the default
preset with OLO at 25 regions (about 30 KiB per reference on disk instead of 59, so that
a million references fit this machine's disk): every printout names it and its digest.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import ROOT, machine, provenance, write_json
from hmpf.config import HierarchyConfig, load_config
from hmpf.datasets import dataset_root, list_images
from hmpf.imageio import load_image
from hmpf.index import layout
from hmpf.index.ann import (
    FRONT_FACTOR,
    build_faiss,
    projected_spec,
    search_faiss,
    set_search_params,
)
from hmpf.index.reader import IndexReader
from hmpf.index.storage import RowBlocks, open_h5
from hmpf.index.tables import Ragged, RefTable
from hmpf.methods.base import MetricSpec, euclidean

#: The bench's default hierarchy (the default preset with OLO at 25 regions).
CONFIG = ROOT / "bench" / "scale" / "default-olo25.yaml"
#: Where the JSON records go.
OUT = ROOT / "docs" / "experiments" / "scale"
#: Where the real source version and the query features are kept (git ignores results/).
WORK = ROOT / "results" / "scale"
GP = "gardens_point"
PLANTED_FOLDER = f"{GP}/day_left"
QUERY_FOLDER = f"{GP}/night_right"
NORDLAND_FOLDER = "nordland_64x32/summer"
#: ``sequence`` of the planted rows; distractor routes are ``synthetic:NNNNN``.
PLANTED_ROUTE = f"planted:{PLANTED_FOLDER}"
TOLERANCE = 2
#: Rows generated and written at once (a NetVLAD block is 8192 x 6144 x 4 B = 192 MiB).
BLOCK_ROWS = 8192


def size_label(n: int) -> str:
    """1000 -> 1k, 100000 -> 100k, 1000000 -> 1M."""
    if n >= 1_000_000 and n % 1_000_000 == 0:
        return f"{n // 1_000_000}M"
    if n >= 1000 and n % 1000 == 0:
        return f"{n // 1000}k"
    return str(n)


def config_line(config: HierarchyConfig) -> str:
    return f"config {config.name} ({config.digest()[:12]})"


# -- the real source version -------------------------------------------------------------------
def ensure_source(source: Path, config: Path, datasets: Path, nordland: int | None) -> None:
    """Build the source version with the real CLI unless ``source`` has one: day_left, then
    Nordland summer (its first ``nordland`` frames when given) added as new places."""
    if source.is_dir() and layout.current_version(source) is not None:
        return
    cli = str(ROOT / ".venv" / "bin" / "hmpf-index")
    nl = datasets / NORDLAND_FOLDER
    if nordland:
        subset = source.parent / f"{source.name}-nordland{nordland}"
        subset.mkdir(parents=True, exist_ok=True)
        for p in list_images(nl)[:nordland]:
            if not (subset / p.name).exists():
                os.symlink(p, subset / p.name)
        nl = subset
    steps = [
        [cli, "build", "--config", str(config), "--images", str(datasets / PLANTED_FOLDER)],
        [cli, "add", "--images", str(nl)],
    ]
    for cmd in steps:
        cmd += ["--index", str(source), "--quiet"]
        print("$", " ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)


class Source:
    """The real arrays the bench plants and fits: rows of the source version that came from
    Gardens Point day_left (planted) and from Nordland summer (fitting, donors)."""

    def __init__(self, root: Path) -> None:
        self.reader = IndexReader(root)
        r = self.reader
        self.config = r.config
        self.methods = r.methods
        src = np.array(r.refs.sources, dtype=object)
        self.planted = np.flatnonzero([s.endswith(PLANTED_FOLDER) for s in src])
        self.nordland = np.flatnonzero([not s.endswith(PLANTED_FOLDER) for s in src])
        if len(self.planted) == 0 or len(self.nordland) < 2:
            raise SystemExit(f"{root}: expected day_left and Nordland rows in the source version")
        self.refs = r.refs
        self.globals = {
            mid: np.asarray(r.global_matrix(mid), dtype=np.float32)
            for mid, m in r.methods.items()
            if m.kind == "global"
        }
        self.locals = {mid: r.columns(mid) for mid, m in r.methods.items() if m.kind == "local"}
        self.thumbs = r.thumbnail_column()

    def blocks(self, mid: str) -> dict[str, np.ndarray]:
        """A local method's arrays as ``(rows, n, ...)`` blocks (equal counts only)."""
        out = {}
        for key, rag in self.locals[mid].items():
            counts = rag.counts
            if not (counts == counts[0]).all() or rag.scalar:
                raise SystemExit(f"{mid}/{key}: not an equal-count array; the bench copies blocks")
            out[key] = rag.data.reshape(len(counts), int(counts[0]), *rag.data.shape[1:])
        return out


# -- the distractors' statistics -------------------------------------------------------------------
def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


def _half(x: np.ndarray) -> np.ndarray:
    return x.astype(np.float16).astype(np.float32)


def normaliser(method: Any) -> Callable[[np.ndarray], np.ndarray]:
    """How ``method`` finishes its descriptors, applied to Gaussian samples."""
    name = type(method).name
    if name == "gem":  # GeM of ReLU6 maps: positive; L2; float16 precision
        return lambda x: _half(_unit(np.maximum(x, 0.0)))
    if name == "netvlad":  # per-cluster intra-normalisation (k fastest), L2, float16
        k = int(method.config.clusters)

        def vlad(x: np.ndarray) -> np.ndarray:
            v = x.reshape(len(x), -1, k)  # (n, D, K): index k + K d
            sq = np.einsum("ndk,ndk->nk", v, v)
            v = v * (1.0 / np.sqrt(np.maximum(sq, 1e-24)))[:, None, :]
            flat = v.reshape(len(x), -1)
            norm = np.sqrt(np.einsum("nd,nd->n", flat, flat))[:, None]
            return _half(flat / np.maximum(norm, 1e-12))

        return vlad
    if name == "gist":  # block means of Gabor magnitudes: positive, not normalised
        return lambda x: np.maximum(x, 0.0).astype(np.float32)
    raise SystemExit(f"no synthetic normalisation for method type {name!r}")


class Gaussian:
    """A Gaussian fitted to real descriptors in route order, sampled as routes.

    The mean, the top ``k`` principal components with their variances and an isotropic
    residual holding the remaining variance; along a route each component's score follows
    an AR(1) process with the lag-1 autocorrelation of the real consecutive rows (the
    residual with one coefficient), so the marginal distribution is the fitted Gaussian and
    neighbouring rows are as alike as neighbouring real frames.
    """

    def __init__(self, x: np.ndarray, k: int, finish: Callable[[np.ndarray], np.ndarray]):
        from scipy.linalg import eigh

        x = np.asarray(x, dtype=np.float64)
        n, d = x.shape
        self.dim = d
        self.mean = x.mean(axis=0)
        xc = x - self.mean
        self.k = k = int(min(k, n - 1, d - 1))
        # the top k principal components, from the smaller of the d x d covariance and the
        # n x n Gram matrix
        xc32 = xc.astype(np.float32)
        top = [min(n, d) - k, min(n, d) - 1]
        if d <= n:
            w, v = eigh((xc32.T @ xc32).astype(np.float64), subset_by_index=top)
            w, v = np.maximum(w[::-1], 1e-30), v[:, ::-1]
            self.comps = v.T  # (k, d), orthonormal rows
            u = xc @ v / np.sqrt(w)
        else:
            w, u = eigh((xc32 @ xc32.T).astype(np.float64), subset_by_index=top)
            w, u = np.maximum(w[::-1], 1e-30), u[:, ::-1]
            self.comps = (xc.T @ u / np.sqrt(w)).T
        var = w / (n - 1)
        self.total_var = float((xc * xc).sum() / (n - 1))
        self.explained = float(var.sum() / self.total_var)
        self.sd = np.sqrt(var)
        self.res_sd = math.sqrt(max(self.total_var - float(var.sum()), 0.0) / (d - k))
        z = u * math.sqrt(n - 1)  # unit-variance scores
        self.rho = np.clip((z[1:] * z[:-1]).sum(0) / (z[:-1] ** 2).sum(0), 0.0, 0.995)
        res = xc - (z * self.sd) @ self.comps
        self.res_rho = float(
            np.clip((res[1:] * res[:-1]).sum() / (res[:-1] ** 2).sum(), 0.0, 0.995)
        )
        self.finish = finish
        # float32 copies for sampling
        self._w = (self.sd[:, None] * self.comps).astype(np.float32)
        self._mean = self.mean.astype(np.float32)

    def route(self, rng: np.random.Generator, length: int) -> np.ndarray:
        """One route of ``length`` rows, normalised (float32)."""
        e = rng.standard_normal((length, self.k), dtype=np.float32)
        z = np.empty_like(e)
        z[0] = e[0]
        a = self.rho.astype(np.float32)
        b = np.sqrt(1.0 - a * a)
        for t in range(1, length):
            z[t] = a * z[t - 1] + b * e[t]
        r = rng.standard_normal((length, self.dim), dtype=np.float32)
        c = np.float32(self.res_rho)
        if c > 0:
            r[1:] *= np.sqrt(np.float32(1.0) - c * c)
            for t in range(1, length):  # r[0] ~ N(0, 1): stationary from the start
                r[t] += c * r[t - 1]
        x = z @ self._w
        x += self._mean
        x += np.float32(self.res_sd) * r
        return self.finish(x)

    def describe(self) -> dict[str, Any]:
        return {
            "components": self.k,
            "explained_variance": self.explained,
            "total_variance": self.total_var,
            "residual_sd": self.res_sd,
            "ar1_components_median": float(np.median(self.rho)),
            "ar1_components_top10": [round(float(v), 3) for v in self.rho[:10]],
            "ar1_residual": self.res_rho,
        }


class Distractors:
    """Distractor rows ``j`` of one method: route ``j // route_len``, generated whole from
    its own seed (so any range, in any order, gives the same rows); the last routes are
    kept for the next call."""

    def __init__(self, gauss: Gaussian, n: int, route_len: int, seed: int, tag: int) -> None:
        self.gauss, self.n, self.route_len = gauss, n, route_len
        self.seed, self.tag = seed, tag
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()

    def _route(self, r: int) -> np.ndarray:
        hit = self._cache.get(r)
        if hit is None:
            length = min(self.route_len, self.n - r * self.route_len)
            rng = np.random.default_rng([self.seed, self.tag, r])
            hit = self._cache[r] = self.gauss.route(rng, length)
            while len(self._cache) > 2:
                self._cache.popitem(last=False)
        return hit

    def rows(self, j0: int, j1: int) -> np.ndarray:
        parts = []
        for r in range(j0 // self.route_len, (j1 - 1) // self.route_len + 1):
            base = r * self.route_len
            block = self._route(r)
            parts.append(block[max(j0, base) - base : min(j1, base + len(block)) - base])
        return np.concatenate(parts) if parts else np.zeros((0, self.gauss.dim), np.float32)


class Layout:
    """Where each row of the version comes from: rows ``offset .. offset + P - 1`` are the
    planted references (source rows ``planted``), the others distractor ``j`` (row ``r``
    below the planted block, ``r - P`` above it), whose copied arrays come from the source
    row ``donors[j]``."""

    def __init__(self, n: int, planted: np.ndarray, offset: int, donors: np.ndarray) -> None:
        self.n, self.planted, self.offset = n, planted, offset
        self.p = len(planted)
        self.donors = donors

    def segments(self, a: int, b: int) -> list[tuple[str, int, int]]:
        """``(kind, lo, hi)`` pieces of rows ``a .. b - 1``: ``("d", j0, j1)`` distractors,
        ``("p", i0, i1)`` planted indices."""
        o, p = self.offset, self.p
        out = []
        if a < min(b, o):
            out.append(("d", a, min(b, o)))
        if max(a, o) < min(b, o + p):
            out.append(("p", max(a, o) - o, min(b, o + p) - o))
        if max(a, o + p) < b:
            out.append(("d", max(a, o + p) - p, b - p))
        return out

    def source_rows(self, a: int, b: int) -> np.ndarray:
        """The source row each of rows ``a .. b - 1`` copies its local arrays from."""
        parts = [
            self.planted[lo:hi] if kind == "p" else self.donors[lo:hi]
            for kind, lo, hi in self.segments(a, b)
        ]
        return np.concatenate(parts).astype(np.int64)


class Progress:
    """Prints how far the writer has read a method's rows (every tenth, each pass)."""

    def __init__(self, name: str, n: int) -> None:
        self.name, self.n, self.done, self.t0 = name, n, 0, time.perf_counter()

    def add(self, rows: int) -> None:
        before = self.done * 10 // self.n
        self.done += rows
        if self.n >= 50_000 and self.done * 10 // self.n != before:
            print(
                f"  {self.name}: pass {self.done // self.n + (self.done % self.n > 0)}, "
                f"{self.done % self.n or self.n}/{self.n} rows, "
                f"{time.perf_counter() - self.t0:.0f} s",
                flush=True,
            )


def global_rows(
    lay: Layout, real: np.ndarray, gen: Distractors, progress: Progress
) -> Callable[[int, int], np.ndarray]:
    def rows(a: int, b: int) -> np.ndarray:
        parts = [
            real[lo:hi] if kind == "p" else gen.rows(lo, hi) for kind, lo, hi in lay.segments(a, b)
        ]
        progress.add(b - a)
        return np.concatenate(parts)

    return rows


def select_items(items: Ragged, rows: np.ndarray, chunk: int = 8192) -> Ragged:
    """``items.select(rows)`` a chunk at a time (select indexes every byte it copies with
    an int64: 8 GB for a million thumbnails at once)."""
    return Ragged.concat([items.select(rows[i : i + chunk]) for i in range(0, len(rows), chunk)])


def copied_rows(lay: Layout, blocks: np.ndarray) -> Callable[[int, int], np.ndarray]:
    return lambda a, b: blocks[lay.source_rows(a, b)]


# -- the statistics check ----------------------------------------------------------------------
def _nn(q: np.ndarray, db: np.ndarray, exclude: int | None = None) -> np.ndarray:
    """Distance of each row of ``q`` to its nearest row of ``db`` (with ``exclude``: ``q``
    is ``db`` and rows within ``exclude`` of a row's own position are skipped)."""
    d = euclidean(q, db)
    if exclude is not None:
        i = np.arange(len(q))
        d[np.abs(i[:, None] - i[None, :]) <= exclude] = np.inf
    return d.min(axis=1)


def _quantiles(v: np.ndarray) -> dict[str, float]:
    v = np.asarray(v, dtype=np.float64)
    v = v[np.isfinite(v)]
    return {f"p{q}": round(float(np.percentile(v, q)), 4) for q in (5, 50, 95)}


def statistics_check(
    real: np.ndarray, synth: np.ndarray, queries: np.ndarray, rng: np.random.Generator
) -> dict[str, Any]:
    """Real Nordland rows against as many synthetic rows (routes): distance from each query
    to its nearest row; from each row to its nearest row more than 5 rows away on its
    route; between consecutive rows; between random pairs."""
    n = len(real)
    pairs = rng.integers(0, n, size=(4000, 2))
    out: dict[str, Any] = {}
    for name, x in (("real", real), ("synthetic", synth)):
        sub = x[: min(n, 2000)]
        out[name] = {
            "query_nearest": _quantiles(_nn(queries, x)),
            "query_mean": round(float(euclidean(queries, x).mean()), 4),
            "nearest_beyond_5": _quantiles(_nn(sub, sub, exclude=5)),
            "consecutive": _quantiles(np.linalg.norm(x[1:] - x[:-1], axis=1)),
            "random_pairs": _quantiles(np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)),
        }
    return out


def print_check(check: Mapping[str, Any]) -> None:
    print(
        "synthetic statistics check (Euclidean distances, the methods' metric; p5 / p50 / p95; "
        "real = Nordland summer, synthetic = as many generated rows):"
    )
    rows = ["query_nearest", "nearest_beyond_5", "consecutive", "random_pairs"]
    for mid, c in check.items():
        for what in rows:
            r, s = c["real"][what], c["synthetic"][what]
            print(
                f"  {mid:8s} {what:17s} real {r['p5']:.3f} / {r['p50']:.3f} / {r['p95']:.3f}"
                f"   synthetic {s['p5']:.3f} / {s['p50']:.3f} / {s['p95']:.3f}"
            )


# -- query features ----------------------------------------------------------------------------
def query_features(
    reader: IndexReader, folder: Path, cache_dir: Path, mids: Sequence[str], every: int = 1
) -> dict[str, np.ndarray]:
    """(Q, D) features of every ``every``-th frame of ``folder`` for the global methods
    ``mids``, extracted once by ``reader`` (the version's fitted methods) and cached in a .npz
    named by the methods' cache keys."""
    what = [str(folder.resolve())] + ([every] if every != 1 else [])
    key = hashlib.sha256(
        json.dumps(what + [[m, reader.methods[m].cache_key()] for m in sorted(mids)]).encode()
    ).hexdigest()[:16]
    path = cache_dir / f"queries-{folder.name}-{key}.npz"
    if path.exists():
        with np.load(path) as z:
            return {m: z[m] for m in mids}
    feats: dict[str, list[np.ndarray]] = {m: [] for m in mids}
    t = time.perf_counter()
    for p in list_images(folder)[::every]:
        f = reader.extract_query(load_image(p))
        for m in mids:
            feats[m].append(np.asarray(f[m], dtype=np.float32))
    out = {m: np.stack(v) for m, v in feats.items()}
    cache_dir.mkdir(parents=True, exist_ok=True)
    np.savez(path, **out)  # type: ignore[arg-type]
    print(f"query features of {folder}: extracted in {time.perf_counter() - t:.0f} s -> {path}")
    return out


#: the metric the tier-1 FAISS types of ``factories`` are built for (GeM, NetVLAD)
L2 = MetricSpec("l2", 1.0)


# -- write -------------------------------------------------------------------------------------
def _expand(spec: str, nlist: int) -> str:
    return spec.replace("{nlist}", str(nlist))


def cmd_write(a: argparse.Namespace) -> None:
    from indexer import build as ib
    from indexer.cli import _PARAMS_FOR_METHOD, _pairs

    t_start = time.perf_counter()
    config = load_config(a.config)
    datasets = Path(a.datasets)
    ensure_source(a.source, a.config, datasets, a.nordland)
    src = Source(a.source)
    if src.config.digest() != config.digest():
        raise SystemExit(
            f"{a.source}: built for {config_line(src.config)}, not {config_line(config)}; "
            "use another --source"
        )
    n, p = a.refs, len(src.planted)
    if n <= p:
        raise SystemExit(f"--refs must exceed the {p} planted references")
    nd = n - p
    offset = (n - p) // 2 if a.planted_at is None else a.planted_at
    if not 0 <= offset <= nd:
        raise SystemExit(f"--planted-at {offset}: outside 0 .. {nd}")
    rng = np.random.default_rng([a.seed, 1])
    donors = src.nordland[rng.integers(0, len(src.nordland), size=nd)]
    lay = Layout(n, src.planted, offset, donors)
    print(machine(), f"(load {os.getloadavg()[0]:.2f})")
    print(
        f"writing {n} references ({p} planted from {PLANTED_FOLDER} at rows {offset}.."
        f"{offset + p - 1}, {nd} distractors in routes of {a.route_len}) to {a.out}; "
        f"{config_line(config)}"
    )

    # the Gaussians and their check
    glob_ids = [m for m, meth in src.methods.items() if meth.kind == "global"]
    queries = query_features(src.reader, datasets / QUERY_FOLDER, a.cache_dir, glob_ids)
    gens, fits, check = {}, {}, {}
    for tag, mid in enumerate(glob_ids):
        t = time.perf_counter()
        real = src.globals[mid][src.nordland]
        g = Gaussian(real, a.components, normaliser(src.methods[mid]))
        fits[mid] = {**g.describe(), "fit_s": round(time.perf_counter() - t, 1)}
        gens[mid] = Distractors(g, nd, a.route_len, a.seed, tag + 10)
        probe = Distractors(g, len(real), a.route_len, a.seed + 1_000_003, tag + 10)
        check[mid] = statistics_check(
            real, probe.rows(0, len(real)), queries[mid], np.random.default_rng(a.seed)
        )
        print(
            f"  {mid}: {g.k} components ({g.explained:.1%} of the variance), residual sd "
            f"{g.res_sd:.4f}, AR(1) median {np.median(g.rho):.2f} (residual {g.res_rho:.2f})"
        )
    print_check(check)

    # the version's contents
    refs = _ref_table(src, lay, a.seed, a.route_len)
    progress = {mid: Progress(mid, n) for mid in glob_ids}
    cols: dict[str, Any] = {}
    for mid in glob_ids:
        real = src.globals[mid][src.planted]
        cols[mid] = RowBlocks(
            (n, real.shape[1]),
            np.float32,
            global_rows(lay, real, gens[mid], progress[mid]),
            BLOCK_ROWS,
        )
    for mid in src.locals:
        cols[mid] = {
            key: RowBlocks((n, *b.shape[1:]), b.dtype, copied_rows(lay, b), BLOCK_ROWS)
            for key, b in src.blocks(mid).items()
        }
    thumbs = select_items(src.thumbs, lay.source_rows(0, n))
    nlist = a.nlist or max(1, round(4 * math.sqrt(n)))
    faiss = {mid: _expand(spec, nlist) for mid, spec in _pairs(a.faiss).items()}
    params = _pairs(a.faiss_params, _PARAMS_FOR_METHOD)  # as hmpf-index build parses them
    train = a.train_rows or max(65_536, 40 * nlist)
    ib.FAISS_TRAIN_ROWS = train  # the build's sample for FAISS training on RowBlocks
    opt = ib.BuildOptions(faiss=faiss, faiss_params=params, precision=a.precision, progress=False)
    opt = opt.with_config(config)
    ib._check_options(config, src.methods, opt)
    print(f"FAISS {dict(opt.faiss)} params {dict(opt.faiss_params)}, trained on {train} rows")

    if a.out.exists() and layout.list_versions(a.out):
        if not a.replace:
            raise SystemExit(f"{a.out} holds versions; --replace deletes it first")
        shutil.rmtree(a.out)
    _check_disk(a.out, n)
    t_publish = time.perf_counter()
    tx = ib.VersionTransaction(a.out, "build")
    with tx:
        job = {"operation": "build", "bench": "scale", "config": config.digest(), "refs": n}
        tx.begin({**job, "seed": a.seed, "options": opt.identity()})
        new = ib.NewVersion(config, src.methods, refs, cols, opt, thumbnails=thumbs)
        summary = tx.publish(new, extracted=0)
    publish_s = time.perf_counter() - t_publish
    for line in summary.lines():
        print(line)
    vdir = a.out / summary.version
    manifest = layout.read_manifest(vdir)
    files = {k: v["bytes"] for k, v in manifest["files"].items()}
    models = sum(v for k, v in files.items() if k.startswith("onnx/"))
    per_ref = (sum(files.values()) - models) / n
    print(
        f"written in {publish_s:.0f} s (publish: generation, HDF5, FAISS, profile, sha256, "
        f"fsync), {time.perf_counter() - t_start:.0f} s in all; "
        f"{per_ref / 1024:.2f} KiB per reference on disk without the ONNX models "
        f"({models / 1e6:.1f} MB once); {config_line(config)}"
    )
    checks = _cli_checks(a.out) if a.check else {}
    results = {
        "references": n,
        "planted": {"folder": PLANTED_FOLDER, "rows": [offset, offset + p], "route": PLANTED_ROUTE},
        "distractors": {"count": nd, "route_len": a.route_len, "fit_on": NORDLAND_FOLDER},
        "source": str(a.source),
        "index": str(a.out),
        "version": summary.version,
        "config": {"name": config.name, "digest": config.digest(), "file": str(a.config)},
        "faiss": {"factories": dict(opt.faiss), "params": dict(opt.faiss_params)},
        "faiss_train_rows": train,
        "nlist": nlist,
        "gaussians": fits,
        "statistics_check": check,
        "write_s": publish_s,
        "total_s": time.perf_counter() - t_start,
        "profile": manifest.get("profile"),
        "bytes": files,
        "bytes_per_reference": per_ref,
        "bytes_models": models,
        "summary": manifest["summary"],
        "checks": checks,
    }
    path = a.json or OUT / f"write-{size_label(n)}.json"
    write_json(path, {**provenance(config.name, config, a), **results})
    print(f"wrote {path}")


def _ref_table(src: Source, lay: Layout, seed: int, route_len: int) -> RefTable:
    n, p, o = lay.n, lay.p, lay.offset
    planted = src.refs.select(src.planted)
    names, sha, seq, sources = [], [], [], []
    gp_folder = planted.sources[0]
    syn_folder = f"synthetic:{NORDLAND_FOLDER}"
    for r in range(n):
        if o <= r < o + p:
            i = r - o
            names.append(planted.names[i])
            sha.append(planted.sha256[i])
            seq.append(PLANTED_ROUTE)
            sources.append(gp_folder)
        else:
            j = r if r < o else r - p
            name = f"synthetic-{j:07d}.png"
            names.append(name)
            sha.append(hashlib.sha256(f"hmpf bench.scale {seed} {name}".encode()).hexdigest())
            seq.append(f"synthetic:{j // route_len:05d}")
            sources.append(syn_folder)
    return RefTable(names, sha, {"sequence": np.array(seq, dtype=object)}, sources)


def _reserve(need: float) -> float:
    """Bytes that must stay free beside a version of ``need`` bytes: as much as the version
    itself, between 1 GB (a test's small version on a small disk) and 8 GB (a million)."""
    return min(8e9, max(1e9, need))


def _check_disk(out: Path, n: int) -> None:
    """Refuse to start when the version (about 31 KiB per reference) would leave less free
    than :func:`_reserve` asks."""
    out.parent.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(out.parent).free
    need = n * 31 * 1024 + 100e6
    keep = _reserve(need)
    if free - need < keep:
        raise SystemExit(
            f"{free / 1e9:.1f} GB free, the version needs about {need / 1e9:.1f} GB and "
            f"{keep / 1e9:.1f} GB must stay free"
        )


def _cli_checks(index: Path) -> dict[str, Any]:
    """``hmpf-index verify`` and ``info`` on the new version: exit codes, times, output."""
    out = {}
    cli = str(ROOT / ".venv" / "bin" / "hmpf-index")
    for cmd in ("verify", "info"):
        t = time.perf_counter()
        r = subprocess.run([cli, cmd, "--index", str(index)], capture_output=True, text=True)
        out[cmd] = {
            "rc": r.returncode,
            "seconds": round(time.perf_counter() - t, 1),
            "output": (r.stdout + r.stderr)[-2000:],
        }
        print(f"$ hmpf-index {cmd} --index {index}: exit {r.returncode} in {out[cmd]['seconds']} s")
        print("\n".join("  " + s for s in (r.stdout + r.stderr).strip().splitlines()[-12:]))
    return out


# -- measure -----------------------------------------------------------------------------------
def planted_rows(reader: IndexReader) -> np.ndarray:
    seq = reader.refs.meta.get("sequence")
    if seq is None:
        raise SystemExit(f"{reader.path}: no sequence column: not a bench.scale version")
    rows = np.flatnonzero(np.asarray(seq, dtype=object) == PLANTED_ROUTE)
    if not len(rows):
        raise SystemExit(f"{reader.path}: no planted rows ({PLANTED_ROUTE})")
    return rows


def exact_top(
    reader: IndexReader, mid: str, q: np.ndarray, k: int, margin: int = 50, chunk: int = 32768
) -> np.ndarray:
    """(Q, k) rows of the exact top ``k`` of each query: float32 products over the stored
    matrix in chunks keep the ``k + margin`` nearest, which the method then re-scores
    (float64, as the reader scores) to order them."""
    method = reader.methods[mid]
    if method.higher_is_better:
        raise SystemExit(f"{mid}: exact search assumes a distance")
    with open_h5(reader.path / layout.REFERENCES_H5) as f:
        return _exact_top(method, f["global"][mid], q, k, margin, chunk)


def _exact_top(method: Any, ds: Any, q: np.ndarray, k: int, margin: int, chunk: int) -> np.ndarray:
    n = ds.shape[0]
    keep = min(n, k + margin)
    qf = np.ascontiguousarray(q, dtype=np.float32)
    qq = (qf * qf).sum(1)[:, None]
    best_d = np.full((len(q), 0), np.inf, dtype=np.float32)
    best_i = np.zeros((len(q), 0), dtype=np.int64)
    for lo in range(0, n, chunk):
        x = np.asarray(ds[lo : lo + chunk], dtype=np.float32)
        d = qq + (x * x).sum(1)[None, :] - 2.0 * (qf @ x.T)
        d = np.concatenate([best_d, d], axis=1)
        ids = np.broadcast_to(np.arange(lo, lo + len(x)), (len(q), len(x)))
        i = np.concatenate([best_i, ids], axis=1)
        part = np.argpartition(d, keep - 1, axis=1)[:, :keep] if d.shape[1] > keep else None
        if part is not None:
            best_d = np.take_along_axis(d, part, axis=1)
            best_i = np.take_along_axis(i, part, axis=1)
        else:
            best_d, best_i = d, i
    out = np.empty((len(q), k), dtype=np.int64)
    for j in range(len(q)):
        cand = np.sort(best_i[j])
        rows = np.asarray(ds[cand], dtype=np.float32)  # h5py reads sorted rows
        s = method.scores(q[j], rows, None)
        out[j] = cand[np.argsort(s, kind="stable")[:k]]
    return out


def approx_top(reader: IndexReader, mid: str, q: np.ndarray, k: int) -> tuple[np.ndarray, list]:
    """(Q, k) rows of the reader's approximate tier 1 (its ``approx_k`` FAISS candidates and
    sample, re-scored exactly) and each query's wall time (ms)."""
    out = np.empty((len(q), k), dtype=np.int64)
    sign = -1.0 if reader.methods[mid].higher_is_better else 1.0
    ms = []
    for j in range(len(q)):
        t = time.perf_counter()
        s = np.asarray(reader.row_scorer({mid: q[j]})(mid, None))
        ms.append((time.perf_counter() - t) * 1e3)
        out[j] = np.argsort(sign * s, kind="stable")[:k]
    return out, ms


def faiss_ms(reader: IndexReader, mid: str, q: np.ndarray) -> float:
    index = reader.faiss_index(mid)
    runs = []
    for j in range(len(q)):
        t = time.perf_counter()
        search_faiss(index, np.ascontiguousarray(q[j : j + 1], dtype=np.float32), reader.approx_k)
        runs.append((time.perf_counter() - t) * 1e3)
    return statistics.median(runs)


def _overlap(a: np.ndarray, b: np.ndarray, k: int) -> float:
    return float(
        np.mean([len(np.intersect1d(x[:k], y[:k])) / k for x, y in zip(a, b, strict=True)])
    )


def _right(top: np.ndarray, gt: Sequence[np.ndarray], k: int) -> float:
    return float(np.mean([np.isin(top[j, :k], gt[j]).any() for j in range(len(gt))]))


def stored_settings(info: Mapping[str, Any]) -> str:
    """A version's FAISS search settings as written (``faiss_info``): a projected scan's
    ``F`` and ``G`` as its factory string says (a setting tried may change them, and the
    stored parameters need not name them), then the stored parameters, which win."""
    spec = projected_spec(str(info.get("factory") or ""))
    parts = []
    if spec is not None:
        parts.append(f"k_factor_rf={spec.k_factor}")
        front = spec.pre_factor or spec.bit_factor or spec.fast_factor
        if front:
            parts.append(f"{FRONT_FACTOR}={front}")
    parts.append(str(info.get("params") or ""))
    return ",".join(p for p in parts if p)


def measure_recall(
    reader: IndexReader, queries: Mapping[str, np.ndarray], gt: Sequence[np.ndarray], a: Any
) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for mid in reader.config.tiers[0].methods:
        if reader.methods[mid].kind != "global" or reader.is_exact(mid):
            continue
        q = queries[mid]
        t = time.perf_counter()
        exact = exact_top(reader, mid, q, 100)
        exact_s = time.perf_counter() - t
        info = reader.faiss_info(mid) or {}
        rows = []
        stored_k = reader.approx_k
        half = len(q) // 2
        for depth, setting in itertools.product(a.approx_k or [stored_k], search_settings(a)):
            reader.approx_k = depth
            if setting is not None:  # each setting on top of the version's own, not the last
                set_search_params(reader.faiss_index(mid), f"{stored_settings(info)},{setting}")
            approx, ms = approx_top(reader, mid, q, 100)
            row = {
                "approx_k": depth,
                "params": setting or info.get("params"),
                "recall_at_100": _overlap(approx, exact, 100),
                # each half of the queries apart: a depth chosen on one, read on the other
                "recall_at_100_halves": [
                    _overlap(approx[:half], exact[:half], 100),
                    _overlap(approx[half:], exact[half:], 100),
                ],
                "recall_at_10": _overlap(approx, exact, 10),
                "right_in_exact_top10": _right(exact, gt, 10),
                "right_in_approx_top10": _right(approx, gt, 10),
                "tier1_ms_p50": statistics.median(ms),
                "faiss_ms_p50": faiss_ms(reader, mid, q),
            }
            rows.append(row)
            print(
                f"  {mid:8s} {info.get('factory')} {row['params']}, {depth} re-scored: "
                f"recall@100 {row['recall_at_100']:.4f} (halves "
                f"{row['recall_at_100_halves'][0]:.4f} / {row['recall_at_100_halves'][1]:.4f}), "
                f"@10 {row['recall_at_10']:.4f}; right place in "
                f"top 10: exact {row['right_in_exact_top10']:.3f}, approximate "
                f"{row['right_in_approx_top10']:.3f}; tier-1 {row['tier1_ms_p50']:.1f} ms "
                f"(FAISS {row['faiss_ms_p50']:.2f} ms) p50",
                flush=True,
            )
        if search_settings(a) != [None]:  # back to the stored settings
            set_search_params(reader.faiss_index(mid), stored_settings(info))
        reader.approx_k = stored_k
        out[mid] = {
            "factory": info.get("factory"),
            "stored_params": info.get("params"),
            "approx_k": stored_k,
            "exact_search_s": exact_s,
            "settings": rows,
        }
    return out


def measure_serve(index: Path, frames: list[bytes], gt: Sequence[np.ndarray], a: Any) -> dict:
    from bench.capacity import cpu_seconds, rss_mib
    from bench.service_load import _free_port, _start
    from hmpf.client import Client

    # the server re-scores as many rows as the recall's first depth (its default without)
    depth = a.approx_k[0] if a.approx_k else None
    serve_params = getattr(a, "serve_params", None)
    args = argparse.Namespace(
        workers=1, threads=1, queue=None, approx_k=depth, faiss_params=serve_params
    )
    port = _free_port()
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "serve.log"
        t0 = time.monotonic()
        proc = _start(index, port, args, log)
        out["ready_s"] = time.monotonic() - t0
        out["approx_k"] = depth  # None: hmpf-serve's default
        out["faiss_params"] = serve_params  # None: the version's stored ones
        out["rss_ready_mib"] = rss_mib(proc.pid)
        try:
            with Client(f"http://127.0.0.1:{port}", timeout=600) as client:
                client.localize(frames[0])
                out["first_answer_s"] = time.monotonic() - t0
                verification = client.index().model_dump().get("verification") or {}
                out["verification_at_first_answer"] = dict(verification)
                while verification.get("state") == "checking":
                    time.sleep(1.0)
                    verification = client.index().model_dump().get("verification") or {}
                out["verification"] = dict(verification)
                out["verification_done_s"] = time.monotonic() - t0
                for f in frames[1 : a.warmup]:
                    client.localize(f)
                out["rss_after_warmup_mib"] = rss_mib(proc.pid)
                cpu0 = cpu_seconds(proc.pid)
                walls, matches, timings = [], [], []
                for f in frames:
                    t = time.perf_counter()
                    ans = client.localize(f)
                    walls.append((time.perf_counter() - t) * 1e3)
                    matches.append(-1 if ans.match is None else ans.match.reference_id)
                    timings.append(ans.timing_ms)
                out["cpu_ms_per_query"] = (cpu_seconds(proc.pid) - cpu0) / len(frames) * 1e3
                out["rss_after_queries_mib"] = rss_mib(proc.pid)
            if not a.no_reload:
                out["reload"] = reload_under_queries(f"http://127.0.0.1:{port}", frames)
                out["rss_after_reload_mib"] = rss_mib(proc.pid)
        finally:
            proc.terminate()
            proc.wait(60)
            out["log_tail"] = log.read_text()[-1500:]
    out["queries"] = len(walls)
    out["p50_ms"] = float(np.percentile(walls, 50))
    out["p99_ms"] = float(np.percentile(walls, 99))
    out["recall_at_1"] = float(np.mean([m in g for m, g in zip(matches, gt, strict=True)]))
    planted = np.concatenate(gt)
    out["answers_on_distractors"] = int(sum(m not in planted for m in matches))
    out["server_timing_ms_p50"] = _timing_p50(timings)
    out["load_1min_after"] = os.getloadavg()[0]
    return out


def reload_under_queries(url: str, frames: Sequence[bytes]) -> dict[str, Any]:
    """``POST /v1/index/reload`` while one client keeps querying, without retries (a
    failed request is counted, not tried again): how long the reload took, how many
    queries were answered meanwhile and how many failed."""
    import threading

    import httpx

    from hmpf.client import Client

    stop = threading.Event()
    answered: list[float] = []
    failures: list[str] = []

    def drive() -> None:
        with Client(url, timeout=600, retries=0) as client:
            i = 0
            while not stop.is_set():
                try:
                    client.localize(frames[i % len(frames)])
                    answered.append(time.monotonic())
                except Exception as exc:  # what a vehicle would see
                    failures.append(repr(exc)[:300])
                i += 1

    thread = threading.Thread(target=drive, daemon=True)
    thread.start()
    time.sleep(2.0)
    t0 = time.monotonic()
    r = httpx.post(f"{url}/v1/index/reload", timeout=1800)
    t1 = time.monotonic()
    time.sleep(2.0)
    stop.set()
    thread.join(600)
    out = {
        "status": r.status_code,
        "body": r.json(),
        "reload_s": t1 - t0,
        "answered_during_reload": sum(t0 <= t <= t1 for t in answered),
        "answered": len(answered),
        "failed": len(failures),
        "failures": failures[:5],
    }
    print(
        f"  reload under queries: {r.status_code} in {out['reload_s']:.1f} s, "
        f"{out['answered_during_reload']} queries answered meanwhile, {out['failed']} failed",
        flush=True,
    )
    return out


def _timing_p50(timings: list[Mapping[str, Any]]) -> dict[str, float]:
    keys = [k for k, v in timings[0].items() if isinstance(v, int | float)]
    return {k: float(np.median([t[k] for t in timings if k in t])) for k in keys}


def cmd_factories(a: argparse.Namespace) -> None:
    """Other FAISS types for one tier-1 method of a written version, without writing it
    again: each trained on the build's sample and filled from the stored matrix in blocks,
    then searched as the reader searches (top ``approx_k``, united with the reader's fixed
    sample, re-scored exactly) against exact search, per ``--nprobe``."""
    import faiss

    from hmpf.index.reader import SAMPLE_SIZE

    reader = IndexReader(a.index, verify=False)
    mid, n = a.method, reader.n_rows
    method = reader.methods[mid]
    qdir = a.queries or Path(a.datasets) / QUERY_FOLDER
    glob = [m for m, meth in reader.methods.items() if meth.kind == "global"]
    q = query_features(reader, qdir, a.cache_dir, glob, a.every)[mid]
    depths = a.approx_k or [reader.approx_k]
    sample = np.unique(np.linspace(0, n - 1, min(n, SAMPLE_SIZE)).round().astype(np.int64))
    planted = planted_rows(reader)
    gt = [planted[max(0, i - TOLERANCE) : i + TOLERANCE + 1] for i in range(len(q))]
    if len(q) != len(planted):  # other queries than the planted route's: no ground truth
        gt = [np.zeros(0, np.int64)] * len(q)
    print(machine(), f"(load {os.getloadavg()[0]:.2f})")
    print(
        f"{a.index}: {n} references, {mid}; {len(q)} queries (every {a.every}. of {qdir}); "
        f"{config_line(reader.config)}"
    )
    t = time.perf_counter()
    exact = exact_top(reader, mid, q, 100)
    print(f"exact top 100 of {len(q)} queries in {time.perf_counter() - t:.0f} s")
    rows_out = []
    rows = reader.global_matrix(mid)  # what the reader re-scores (on demand where it reads so)
    with open_h5(reader.path / layout.REFERENCES_H5) as f:
        ds = f["global"][mid]
        for spec in a.factory:
            nlist = a.nlist or max(1, round(4 * math.sqrt(n)))
            factory = _expand(spec, nlist)
            train_n = min(n, a.train_rows or max(65_536, 40 * nlist))
            pick = np.unique(np.linspace(0, n - 1, train_n).round().astype(np.int64))
            t = time.perf_counter()
            # trained and filled as a build does (indexer.build._faiss_from_blocks)
            index, _ = build_faiss(np.asarray(ds[pick], dtype=np.float32), L2, factory)
            index.reset()
            train_s = time.perf_counter() - t
            t = time.perf_counter()
            for lo in range(0, n, 32768):
                index.add(np.asarray(ds[lo : lo + 32768], dtype=np.float32))
            add_s = time.perf_counter() - t
            nbytes = faiss.serialize_index(index).size
            threads = faiss.omp_get_max_threads()
            faiss.omp_set_num_threads(1)  # searched as hmpf-serve searches
            for setting, approx_k in itertools.product(search_settings(a), depths):
                if setting is not None:  # on top of the type's own, as measure_recall does
                    built = stored_settings({"factory": factory})
                    set_search_params(index, f"{built},{setting}")
                top = np.empty((len(q), 100), dtype=np.int64)
                ms = []
                for j in range(len(q)):
                    t = time.perf_counter()
                    _, ids = search_faiss(index, q[j : j + 1].astype(np.float32), approx_k)
                    ms.append((time.perf_counter() - t) * 1e3)
                    cand = np.union1d(ids[0][ids[0] >= 0], sample)
                    s = method.scores(q[j], rows, cand)
                    top[j] = cand[np.argsort(s, kind="stable")[:100]]
                row = {
                    "factory": factory,
                    "params": setting,
                    "approx_k": approx_k,
                    "bytes_per_reference": nbytes / n,
                    "train_rows": len(pick),
                    "train_s": train_s,
                    "add_s": add_s,
                    "recall_at_100": _overlap(top, exact, 100),
                    "recall_at_10": _overlap(top, exact, 10),
                    "right_in_exact_top10": _right(exact, gt, 10),
                    "right_in_approx_top10": _right(top, gt, 10),
                    "faiss_ms_p50": statistics.median(ms),
                }
                rows_out.append(row)
                print(
                    f"  {factory:24s} {setting}: recall@100 {row['recall_at_100']:.4f}, "
                    f"@10 {row['recall_at_10']:.4f}; right in top 10 exact "
                    f"{row['right_in_exact_top10']:.3f} / approx {row['right_in_approx_top10']:.3f}"
                    f"; {nbytes / n:.0f} B per reference; FAISS {row['faiss_ms_p50']:.2f} ms "
                    f"p50 (top {approx_k}); train {train_s:.0f} s, add {add_s:.0f} s",
                    flush=True,
                )
            faiss.omp_set_num_threads(threads)
            del index
    path = a.json or OUT / f"factories-{mid}-{size_label(n)}.json"
    results = {
        "index": str(a.index),
        "references": n,
        "method": mid,
        "queries": {"folder": str(qdir), "every": a.every, "count": len(q)},
        "settings": rows_out,
    }
    write_json(path, {**provenance(reader.config.name, reader.config, a), **results})
    print(f"wrote {path}")


def cmd_measure(a: argparse.Namespace) -> None:
    qdir = a.queries or Path(a.datasets) / QUERY_FOLDER
    out: dict[str, Any] = {}
    t = time.perf_counter()
    reader = IndexReader(a.index, verify=False, approx_k=a.approx_k[0] if a.approx_k else None)
    out["open_s"] = time.perf_counter() - t
    n = reader.n_rows
    config = reader.config
    planted = planted_rows(reader)
    paths = list_images(qdir)
    if len(paths) != len(planted):
        raise SystemExit(f"{len(paths)} queries in {qdir} for {len(planted)} planted rows")
    gt = [planted[max(0, i - TOLERANCE) : i + TOLERANCE + 1] for i in range(len(paths))]
    disk = sum(int(v["bytes"]) for v in reader.manifest["files"].values())
    print(machine(), f"(load {os.getloadavg()[0]:.2f})")
    print(
        f"{a.index} ({reader.version}): {n} references, {len(planted)} planted at rows "
        f"{planted[0]}..{planted[-1]}, {disk / n / 1024:.2f} KiB per reference on disk "
        f"(ONNX models included); {config_line(config)}"
    )
    if not a.no_recall:
        glob = [m for m, meth in reader.methods.items() if meth.kind == "global"]
        queries = query_features(reader, qdir, a.cache_dir, glob)  # write's cache
        print(
            f"tier-1 recall of the reader's approximate path (FAISS top {reader.approx_k} + "
            f"sample, re-scored exactly) against exact search, {len(paths)} queries of {qdir}:"
        )
        out["recall"] = measure_recall(reader, queries, gt, a)
    reader.close()
    del reader
    if not a.no_serve:
        frames = [p.read_bytes() for p in paths]
        s = measure_serve(a.index, frames, gt, a)
        out["serve"] = s
        print_serve(s, n)
    path = a.json or OUT / f"measure-{size_label(n)}.json"
    results = {"index": str(a.index), "references": n, "disk_bytes": disk, **out}
    write_json(path, {**provenance(config.name, config, a), **results})
    print(f"wrote {path}")


def print_serve(s: Mapping[str, Any], n: int) -> None:
    def mem(r: Mapping[str, float]) -> str:
        return f"{r['VmRSS']:.0f} MiB (anonymous {r['RssAnon']:.0f}, file {r['RssFile']:.0f})"

    v = s.get("verification", {})

    def secs(x: Any) -> str:
        return "none" if x is None else f"{x:.1f} s"

    print(
        f"hmpf-serve (1 worker x 1 thread): ready {s['ready_s']:.1f} s, first answer "
        f"{s['first_answer_s']:.1f} s after the start (verification {v.get('state')}; every "
        f"byte hashed before answering: {secs(v.get('seconds'))}; background check: "
        f"{secs(v.get('check_seconds'))})"
    )
    print(f"  resident after warm-up: {mem(s['rss_after_warmup_mib'])}")
    print(
        f"  resident after {s['queries']} queries: {mem(s['rss_after_queries_mib'])}; "
        f"{s['rss_after_queries_mib']['VmRSS'] * 1024 * 1024 / n / 1024:.2f} KiB per reference"
    )
    print(
        f"  latency p50 {s['p50_ms']:.1f} ms, p99 {s['p99_ms']:.1f} ms (single-frame mode, one "
        f"at a time), server CPU {s['cpu_ms_per_query']:.1f} ms per query; recall@1 "
        f"{s['recall_at_1']:.3f} (+-{TOLERANCE} frames; {s['answers_on_distractors']} answers "
        f"on a distractor); load {s['load_1min_after']:.2f}"
    )


# -- report ------------------------------------------------------------------------------------
def search_settings(a: argparse.Namespace) -> list[str | None]:
    """The FAISS search parameters to try: ``--nprobe N`` as ``nprobe=N``, then every
    ``--params`` string; [None] (the stored setting) when neither is given."""
    out: list[str | None] = [f"nprobe={n}" for n in a.nprobe or []]
    out += list(a.params or [])
    return out or [None]


def _setting(row: Mapping[str, Any]) -> str:
    """A recall row's FAISS parameters (records before ``params`` said ``nprobe``)."""
    if "params" in row:
        return str(row["params"])
    return f"nprobe={row['nprobe']}" if isinstance(row["nprobe"], int) else str(row["nprobe"])


def cmd_report(a: argparse.Namespace) -> None:
    """One table of the measure records given: per size, the disk, the service's figures,
    the ratios to the smallest size and tier-1 recall@100 at the version's stored nprobe."""
    recs = [json.loads(Path(p).read_text()) for p in a.records]
    recs.sort(key=lambda r: r["references"])
    base = next((r for r in recs if "serve" in r), None)
    print(
        "| references | config | disk KiB/ref | first answer s | RSS MiB (anonymous / file) | "
        "KiB/ref (slope) | p50 ms | p99 ms | p50 / smallest | recall@1 | tier-1 recall@100 |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for r in recs:
        s = r.get("serve", {})
        rec = "; ".join(
            f"{mid} {st['recall_at_100']:.3f}"
            for mid, m in r.get("recall", {}).items()
            for st in m["settings"]
            if _setting(st) in (m["stored_params"], f"nprobe={m['stored_params']}")
        )
        cfg = f"{r.get('preset') or ''} {r['digest'][:12]}"
        disk = r["disk_bytes"] / r["references"] / 1024
        if not s:
            print(f"| {r['references']} | {cfg} | {disk:.1f} | | | | | | | | {rec} |")
            continue
        rss, b = s["rss_after_queries_mib"], (base or r)["serve"]
        dn = r["references"] - (base or r)["references"]
        slope = (rss["VmRSS"] - b["rss_after_queries_mib"]["VmRSS"]) * 1024 / dn if dn else math.nan
        print(
            f"| {r['references']} | {cfg} | {disk:.1f} | {s['first_answer_s']:.1f} | "
            f"{rss['VmRSS']:.0f} ({rss['RssAnon']:.0f} / {rss['RssFile']:.0f}) | "
            f"{rss['VmRSS'] * 1024 / r['references']:.2f} ({slope:.2f}) | {s['p50_ms']:.1f} | "
            f"{s['p99_ms']:.1f} | {s['p50_ms'] / b['p50_ms']:.2f} | {s['recall_at_1']:.3f} | "
            f"{rec} |"
        )


# -- main --------------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m bench.scale", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write", help="write a version of --refs references")
    w.add_argument("--refs", type=int, required=True)
    w.add_argument("--out", type=Path, required=True, help="index folder to create")
    w.add_argument("--config", type=Path, default=CONFIG)
    w.add_argument("--source", type=Path, default=WORK / "source", help="the real source index")
    w.add_argument("--nordland", type=int, default=None, help="source: first N Nordland frames")
    w.add_argument(
        "--faiss",
        action="append",
        default=None,
        metavar="[METHOD=]FACTORY",
        help="as hmpf-index build's, {nlist} replaced (default gem=IVF{nlist},PQ64np and "
        "netvlad=IVF{nlist},PQ256np; np: no polysemous training)",
    )
    w.add_argument("--faiss-params", action="append", default=None, metavar="[METHOD=]PARAMS")
    w.add_argument("--nlist", type=int, default=None, help="default round(4 sqrt(N))")
    w.add_argument("--train-rows", type=int, default=None, help="default max(65536, 40 nlist)")
    w.add_argument("--precision", choices=["exact", "compact"], default="exact")
    w.add_argument("--seed", type=int, default=0)
    w.add_argument("--planted-at", type=int, default=None, help="first planted row (middle)")
    w.add_argument("--route-len", type=int, default=1000)
    w.add_argument("--components", type=int, default=256, help="principal components fitted")
    w.add_argument("--replace", action="store_true", help="delete --out first")
    w.add_argument("--check", action="store_true", help="run hmpf-index verify and info after")
    m = sub.add_parser("measure", help="recall, load, memory and latency of a written version")
    m.add_argument("--index", type=Path, required=True)
    m.add_argument("--queries", type=Path, default=None, help="default night_right")
    m.add_argument("--nprobe", type=int, nargs="*", default=None, help="tier-1 settings to try")
    m.add_argument(
        "--params",
        nargs="*",
        default=None,
        help="FAISS search settings to try (k_factor_rf=16)",
    )
    m.add_argument(
        "--serve-params",
        default=None,
        metavar="PARAMS",
        help="FAISS search parameters hmpf-serve sets on every approximate tier-1 method "
        "on top of the version's (HMPF_FAISS_PARAMS), e.g. k_factor_front=2",
    )
    m.add_argument("--warmup", type=int, default=5)
    m.add_argument("--no-serve", action="store_true")
    m.add_argument("--no-recall", action="store_true")
    m.add_argument("--no-reload", action="store_true", help="skip the reload under queries")
    m.add_argument(
        "--approx-k",
        type=int,
        nargs="+",
        default=None,
        help="rows re-scored: the recall's depths, the first also hmpf-serve's "
        "(HMPF_APPROX_K; default the reader's)",
    )
    fa = sub.add_parser("factories", help="other FAISS types for one method of a version")
    fa.add_argument("--index", type=Path, required=True)
    fa.add_argument("--method", required=True)
    fa.add_argument("--factory", nargs="+", required=True, help="{nlist} replaced")
    fa.add_argument("--nlist", type=int, default=None, help="default round(4 sqrt(N))")
    fa.add_argument("--train-rows", type=int, default=None, help="default max(65536, 40 nlist)")
    fa.add_argument("--nprobe", type=int, nargs="*", default=None)
    fa.add_argument(
        "--params",
        nargs="*",
        default=None,
        help="FAISS search settings to try (k_factor_rf=16)",
    )
    fa.add_argument(
        "--approx-k", type=int, nargs="+", default=None, help="rows re-scored (the reader's)"
    )
    fa.add_argument("--queries", type=Path, default=None, help="default night_right")
    fa.add_argument("--every", type=int, default=1, help="every N-th query frame")
    r = sub.add_parser("report", help="one table of measure records")
    r.add_argument("records", nargs="+")
    for sp in (w, m, fa):
        sp.add_argument("--datasets", default=str(dataset_root()))
        sp.add_argument("--cache-dir", type=Path, default=WORK, help="query features' cache")
        sp.add_argument("--json", type=Path, default=None, help=f"default {OUT}/<cmd>-<size>.json")
    a = p.parse_args(argv)
    if a.cmd in ("measure", "factories"):
        # one thread, as a replica's query thread searches (hmpf-serve caps FAISS's OpenMP
        # pool the same way); more would spin-wait on a busy machine
        from hmpf.index.ann import faiss_module

        faiss_module().omp_set_num_threads(1)
    if a.cmd == "write":
        a.faiss = a.faiss or ["gem=IVF{nlist},PQ64np", "netvlad=IVF{nlist},PQ256np"]
        a.faiss_params = a.faiss_params or ["nprobe=32"]
        cmd_write(a)
    elif a.cmd == "measure":
        cmd_measure(a)
    elif a.cmd == "factories":
        cmd_factories(a)
    else:
        cmd_report(a)


if __name__ == "__main__":
    sys.exit(main())
