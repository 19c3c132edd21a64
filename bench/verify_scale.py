"""Cost of verifying an index version on load against the map's size: the full check (sha256
of every file) and the verification stamp's check (a ``stat`` of every file).

    python -m bench.verify_scale [--sizes 10000,100000] [--global-kib 17.8] [--local-kib 37.9]
                                 [--repeat 3] [--extrapolate 1000000] [--dir /tmp] [--json F]

Every time a version is opened for reading (``hmpf-serve`` start and reload, ``hmpf-eval
--index``, ``add`` / ``remove`` opening their parent, ``hmpf-index use``), the reader first
checks every file of the version against the size and sha256 in its manifest
(:func:`hmpf.index.layout.check_files`). This measures that check on synthetic version
folders of realistic size per reference: by default the default config's 55.7 KiB per
reference on Gardens Point (README, "Index"), 17.8 KiB in ``references.h5`` (NetVLAD,
GeM and Gist float16 rows, names, metadata) and 37.9 KiB in ``local.h5`` (OLO's N x R x D
blocks), written as real HDF5 files.

Per size, the median of ``--repeat`` runs of:

* ``streamed``: the baseline, one streamed sha256 over the files one after the other;
* ``check (warm)``: :func:`~hmpf.index.layout.check_files`, what the reader runs: the
  same sha256 over 64 MiB pieces (each listed in the manifest, :func:`~hmpf.index.layout.
  file_entry`) on one thread per core, with the files in the page cache (e.g. right after
  they were written or copied);
* ``check (cold)``: the same after evicting the files from the page cache
  (``posix_fadvise(DONTNEED)``, these files only), so the disk is read too;
* ``1 thread (cold)``: the same check on one thread from a cold cache, as the service runs
  it in the background after opening a version by its stamp (``workers=1``);
* ``stamp``: :func:`~hmpf.index.layout.stamp_matches`, what the service runs instead before
  it answers when the version carries a matching verification stamp (written here once by
  :func:`~hmpf.index.layout.write_stamp`, as publish and ``hmpf-index verify`` do): the
  stamp read, the manifest's digest and one ``stat`` per file, whatever the files' size.

Sizes larger than memory or disk can be extrapolated (``--extrapolate``): the check reads
and hashes every byte once, so its time is linear in the bytes (the per-GB rate of the
largest measured size is used, and the output says it is extrapolated). ``--json F`` writes
the same figures as a JSON record (provenance, one row per size, the extrapolation).
"""

from __future__ import annotations

import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bench.harness import add_json, machine, parser, write_record
from hmpf.index import layout

#: Rows written per HDF5 write (bounded memory at any size).
SLAB = 2048


def write_version(folder: Path, n: int, global_kib: float, local_kib: float) -> dict:
    """A version folder with ``references.h5`` and ``local.h5`` of ``n`` references (random
    float16 rows of the given sizes) and a manifest listing their sizes and sha256."""
    import h5py

    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    g_dim = max(1, round(global_kib * 1024 / 2))
    regions, l_dim = 50, max(1, round(local_kib * 1024 / 2 / 50))
    g_slab = np.frombuffer(rng.bytes(SLAB * g_dim * 2), np.float16).reshape(SLAB, g_dim)
    l_slab = np.frombuffer(rng.bytes(SLAB * regions * l_dim * 2), np.float16).reshape(
        SLAB, regions, l_dim
    )
    with h5py.File(folder / layout.REFERENCES_H5, "w", libver="latest") as f:
        names = np.array([f"img{i:07d}.jpg" for i in range(n)], dtype=object)
        f.create_dataset("names", data=names, dtype=h5py.string_dtype())
        f.create_dataset("sha256", data=np.full(n, b"0" * 64, dtype="S64"))
        ds = f.create_dataset("global/vectors", shape=(n, g_dim), dtype=np.float16)
        for a in range(0, n, SLAB):
            ds[a : min(n, a + SLAB)] = g_slab[: min(n, a + SLAB) - a]
    with h5py.File(folder / layout.LOCAL_H5, "w", libver="latest") as f:
        ds = f.create_dataset("local/olo/desc/blocks", shape=(n, regions, l_dim), dtype=np.float16)
        for a in range(0, n, SLAB):
            ds[a : min(n, a + SLAB)] = l_slab[: min(n, a + SLAB) - a]
    layout.fsync_tree(folder)
    files = {p.name: layout.file_entry(p) for p in sorted(folder.iterdir())}
    manifest = {"format_version": layout.FORMAT_VERSION, "files": files}
    return manifest


def evict(folder: Path) -> None:
    """Drop these files' pages from the page cache (they are fsynced, so clean)."""
    for p in folder.iterdir():
        fd = os.open(p, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def median_time(fn: Callable[[], object], repeat: int, before: Callable[[], None]) -> float:
    times = []
    for _ in range(repeat):
        before()
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--sizes", default="10000,100000")
    ap.add_argument("--global-kib", type=float, default=17.8)
    ap.add_argument("--local-kib", type=float, default=37.9)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--extrapolate", type=int, default=1_000_000)
    ap.add_argument("--dir", default=None, help="where to write the synthetic versions")
    add_json(ap)
    args = ap.parse_args()
    per_ref = (args.global_kib + args.local_kib) * 1024
    print(f"machine: {machine()}; {os.cpu_count()} CPUs")
    print(
        f"per reference: {args.global_kib} KiB references.h5 + {args.local_kib} KiB local.h5; "
        f"median of {args.repeat} runs"
    )
    print(
        f"{'references':>10} {'GB':>6} {'streamed':>9} {'check warm':>11} {'check cold':>11} "
        f"{'warm GB/s':>9} {'cold GB/s':>9} {'1 thr cold':>10} {'stamp':>9}  "
        "load average (other jobs on the cores)"
    )
    rows: list[dict[str, float]] = []
    for n in (int(s) for s in args.sizes.split(",")):
        with tempfile.TemporaryDirectory(dir=args.dir, prefix="hmpf-verify-") as tmp:
            folder = Path(tmp) / "v0001"
            manifest = write_version(folder, n, args.global_kib, args.local_kib)
            gb = sum(e["bytes"] for e in manifest["files"].values()) / 1e9

            def streamed(folder: Path = folder) -> None:
                for p in sorted(folder.iterdir()):
                    layout.sha256_file(p)

            def check(folder: Path = folder, manifest: dict = manifest) -> None:
                layout.check_files(folder, manifest)

            def one_thread(folder: Path = folder, manifest: dict = manifest) -> None:
                assert not layout.file_problems(folder, manifest, workers=1)

            def stamp(folder: Path = folder, manifest: dict = manifest) -> None:
                assert layout.stamp_matches(folder, manifest)

            assert layout.write_stamp(folder, manifest)
            load = os.getloadavg()[0]
            t_base = median_time(streamed, args.repeat, lambda: None)
            t_warm = median_time(check, args.repeat, lambda: None)
            t_cold = median_time(check, args.repeat, lambda folder=folder: evict(folder))
            t_one = median_time(one_thread, args.repeat, lambda folder=folder: evict(folder))
            t_stamp = median_time(stamp, max(args.repeat, 25), lambda: None)
            print(
                f"{n:>10} {gb:>6.2f} {t_base:>8.2f}s {t_warm:>10.2f}s {t_cold:>10.2f}s "
                f"{gb / t_warm:>9.2f} {gb / t_cold:>9.2f} {t_one:>9.2f}s {t_stamp * 1e3:>7.2f}ms  "
                f"{load:.1f} -> {os.getloadavg()[0]:.1f}"
            )
            rows.append(
                {
                    "references": n,
                    "gb": gb,
                    "streamed_s": t_base,
                    "check_warm_s": t_warm,
                    "check_cold_s": t_cold,
                    "one_thread_cold_s": t_one,
                    "stamp_ms": t_stamp * 1e3,
                    "load_before": load,
                    "load_after": os.getloadavg()[0],
                }
            )
            shutil.rmtree(folder)
    extrapolated = None
    if rows and args.extrapolate > rows[-1]["references"]:
        last = rows[-1]
        big_gb = args.extrapolate * per_ref / 1e9
        extrapolated = {
            "references": args.extrapolate,
            "gb": big_gb,
            "from_references": int(last["references"]),
            **{
                k: last[k] * big_gb / last["gb"]
                for k in ("check_warm_s", "check_cold_s", "one_thread_cold_s")
            },
        }
        print(
            f"{args.extrapolate:>10} {big_gb:>6.1f} (extrapolated from "
            f"{extrapolated['from_references']}, linear in bytes): check warm "
            f"{extrapolated['check_warm_s']:.1f} s, cold {extrapolated['check_cold_s']:.1f} s, "
            f"1 thread cold {extrapolated['one_thread_cold_s']:.1f} s; stamp: not linear in "
            "bytes (one stat per file), as measured"
        )
    if args.json:
        results = {"kib_per_reference": per_ref / 1024, "sizes": rows, "extrapolated": extrapolated}
        write_record(args.json, results, args)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
