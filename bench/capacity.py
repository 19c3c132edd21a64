"""Per-query CPU and resident memory of one ``hmpf-serve`` replica: inputs of docs/scale.md.

    .venv/bin/python -m bench.capacity --index INDEX --queries DIR [--n 100] [--workers 1]

Starts a real ``hmpf-serve`` on INDEX (loopback, no auth), reads its resident memory when
ready, sends ``--n`` frames from DIR one at a time through :class:`hmpf.client.Client`
(sequence tracking on, as a vehicle does), then prints:

* CPU per answered query: the server process's user + system CPU time (``/proc/PID/stat``)
  over the run divided by the answers. CPU time, unlike wall time, barely moves when other
  jobs share the cores, so this is the figure to size cores with;
* wall p50 per request (affected by other jobs; quoted for reference only);
* resident memory (``VmRSS``) at ready and after the run, and the index's bytes on disk.

Two indexes of different sizes queried by the same frames give the CPU and resident memory per
reference as the slope between them: keep the frames' places in both (e.g. Gardens Point
day_right, 200 references, and the same with 800 Nordland references added), since frames
off the map change what the sequence filter and the later tiers do, not only the map's size.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

from bench.harness import add_json, machine, parser, write_record
from bench.service_load import _free_port, _start
from hmpf.client import Client
from hmpf.datasets import list_images
from hmpf.index import layout

CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process (fields 14 and 15 of /proc/PID/stat)."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def rss_mib(pid: int) -> dict[str, float]:
    """Resident MiB of a process: total, anonymous (its own) and file-backed (memory-mapped
    index files and libraries: page cache that replicas on one machine share)."""
    out = {}
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            key = line.split(":")[0]
            if key in ("VmRSS", "RssAnon", "RssFile"):
                out[key] = int(line.split()[1]) / 1024
    return out


def show(r: dict[str, float]) -> str:
    return f"{r['VmRSS']:.0f} MiB (anonymous {r['RssAnon']:.0f}, file-backed {r['RssFile']:.0f})"


def version_bytes(index: Path) -> tuple[int, int, dict]:
    """(bytes on disk of the current version, references in it, its manifest)."""
    version = index / str(layout.current_version(index))
    total = sum(f.stat().st_size for f in version.rglob("*") if f.is_file())
    manifest = layout.read_manifest(version)
    return total, int(manifest["images"]["count"]), manifest


def main() -> None:
    p = parser(__doc__)
    p.add_argument("--index", type=Path, required=True)
    p.add_argument("--queries", type=Path, required=True, help="folder of query frames")
    p.add_argument("--n", type=int, default=100, help="queries sent (evenly spaced frames)")
    p.add_argument("--workers", type=int, default=1, help="HMPF_WORKERS of the replica")
    p.add_argument("--threads", type=int, default=1, help="HMPF_THREADS_PER_WORKER")
    p.add_argument("--warmup", type=int, default=5)
    add_json(p)
    a = p.parse_args()
    a.queue = None
    paths = list_images(a.queries)
    step = max(1, len(paths) // (a.n + a.warmup))
    frames = [q.read_bytes() for q in paths[::step][: a.n + a.warmup]]
    port = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        proc = _start(a.index, port, a, Path(tmp) / "serve.log")
        try:
            rss_ready = rss_mib(proc.pid)
            with Client(f"http://127.0.0.1:{port}", timeout=120) as client:
                for f in frames[: a.warmup]:
                    client.localize(f, vehicle_id="capacity")
                cpu0 = cpu_seconds(proc.pid)
                walls = []
                for f in frames[a.warmup :]:
                    t0 = time.perf_counter()
                    client.localize(f, vehicle_id="capacity")
                    walls.append((time.perf_counter() - t0) * 1e3)
                cpu1 = cpu_seconds(proc.pid)
            rss_after = rss_mib(proc.pid)
        finally:
            proc.terminate()
            proc.wait(30)
    disk, refs, manifest = version_bytes(a.index)
    n = len(walls)
    print(machine())
    print(f"index {a.index}: {refs} references, {disk / refs / 1024:.1f} KiB per reference on disk")
    print(
        f"replica HMPF_WORKERS={a.workers} x {a.threads} thread(s); "
        f"{n} queries from {a.queries} (after {a.warmup})"
    )
    print(f"CPU per answered query: {(cpu1 - cpu0) / n * 1e3:.1f} ms (server process, user+sys)")
    print(
        f"wall per request p50: {statistics.median(walls):.1f} ms (load {os.getloadavg()[0]:.2f})"
    )
    print(f"resident at ready: {show(rss_ready)}")
    print(f"resident after the queries: {show(rss_after)}")
    if a.json:
        config = manifest["config"]  # the name and sha256 digest it was built with
        results = {
            "index": str(a.index),
            "index_config_digest": config["sha256"],
            "references": refs,
            "disk_bytes_per_reference": disk / refs,
            "queries": n,
            "cpu_ms_per_query": (cpu1 - cpu0) / n * 1e3,
            "wall_p50_ms": statistics.median(walls),
            "load_1min_after": os.getloadavg()[0],
            "rss_ready_mib": rss_ready,
            "rss_after_mib": rss_after,
        }
        write_record(a.json, results, a, preset=config["name"])
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
