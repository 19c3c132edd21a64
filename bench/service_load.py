"""Load test of ``hmpf-serve`` over loopback: throughput, latency percentiles, errors, 503s.

    .venv/bin/python -m bench.service_load [--config configs/default.yaml] [--clients 1 8]
        [--duration 30] [--overload 48] [--index DIR] [--workers N] [--queue Q]

Builds (once, under ``results/service-index/<config name>``) an index of Gardens Point
``day_right``, starts a real ``hmpf-serve`` process on a free loopback port (authentication
off, as under ``make run``), and for each client count runs that many closed-loop clients
posting ``night_right`` frames as raw JPEG bodies for ``--duration`` seconds, each through
its own :class:`hmpf.client.Client` (retries off: the bench counts them). A client sends its
next request when the previous answer arrives; after a 503 it waits the server's
``Retry-After`` (capped at 0.2 s, so the overload phase keeps pressing).

Per phase it prints: answers per second (200s), latency p50/p95/p99/max of the 200s (client
side, end to end over HTTP), the server's own median stage times, 503s, other errors
(non-200/503 codes, timeouts, transport errors) and the share of answers within +-2 frames.
The ``--overload`` phase uses more clients than workers + queue: the service must answer the
excess with 503 promptly, not time out. Client and server share the machine's cores.
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from bench.harness import ROOT, add_json, machine, parser, write_record
from hmpf.client import Client, ServiceError, ServiceUnreachable
from hmpf.datasets import dataset_root, list_images

TIMEOUT_S = 30.0


@dataclass
class Phase:
    clients: int
    seconds: float = 0.0
    latencies: list[float] = field(default_factory=list)
    stages: dict[str, list[float]] = field(default_factory=dict)
    busy_ms: list[float] = field(default_factory=list)
    codes: dict[str, int] = field(default_factory=dict)
    correct: int = 0

    def count(self, code: str) -> None:
        self.codes[code] = self.codes.get(code, 0) + 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ensure_index(config: Path, index: Path | None) -> Path:
    if index is None:
        index = ROOT / "results" / "service-index" / config.stem
    if (index / "CURRENT").exists():
        print(f"index: {index} (exists)")
        return index
    refs = dataset_root() / "gardens_point" / "day_right"
    print(f"index: building {index} from {refs} with {config} ...", flush=True)
    cmd = [str(ROOT / ".venv" / "bin" / "hmpf-index"), "build", "--config", str(config)]
    cmd += ["--images", str(refs), "--index", str(index), "--quiet"]
    subprocess.run(cmd, check=True)
    return index


def _start(index: Path, port: int, args: argparse.Namespace, log: Path) -> subprocess.Popen:
    # The service's own settings only; the CNN runtime and caches may be chosen by the caller.
    keep = ("HMPF_CNN_RUNTIME", "HMPF_CACHE_DIR")
    env = {k: v for k, v in os.environ.items() if not k.startswith("HMPF_") or k in keep}
    env.update(HMPF_AUTH="false", HMPF_LOG_LEVEL="warning")
    if args.workers:
        env["HMPF_WORKERS"] = str(args.workers)
    if args.queue is not None:
        env["HMPF_QUEUE"] = str(args.queue)
    if getattr(args, "threads", None):
        env["HMPF_THREADS_PER_WORKER"] = str(args.threads)
    if getattr(args, "approx_k", None):
        env["HMPF_APPROX_K"] = str(args.approx_k)
    if getattr(args, "faiss_params", None):
        env["HMPF_FAISS_PARAMS"] = json.dumps({"*": args.faiss_params})
    cmd = [str(ROOT / ".venv" / "bin" / "hmpf-serve"), "--index", str(index)]
    cmd += ["--port", str(port)]
    proc = subprocess.Popen(cmd, env=env, stdout=log.open("wb"), stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"hmpf-serve exited {proc.returncode}:\n{log.read_text()[-3000:]}")
        try:
            status, _ = _request(port, "GET", "/readyz", b"", 2.0)
            if status == 200:
                return proc
        except OSError:
            pass
        time.sleep(0.3)
    proc.kill()
    raise SystemExit("hmpf-serve did not become ready in 300 s")


def _request(port: int, method: str, path: str, body: bytes, timeout: float) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        headers = {"Content-Type": "image/jpeg"} if body else {}
        conn.request(method, path, body=body or None, headers=headers)
        r = conn.getresponse()
        return r.status, r.read()
    finally:
        conn.close()


def _run_phase(port: int, clients: int, seconds: float, frames: list[bytes]) -> Phase:
    phase = Phase(clients)
    lock = threading.Lock()
    stop_at = time.monotonic() + seconds

    def client(seed: int) -> None:
        k = seed * 37
        # retries=0: the bench counts every 503 and error itself
        with Client(f"http://127.0.0.1:{port}", timeout=TIMEOUT_S, retries=0) as service:
            while time.monotonic() < stop_at:
                qi = k % len(frames)
                k += 1
                t0 = time.perf_counter()
                retry = None
                try:
                    answer = service.localize(frames[qi])
                    status = 200
                except ServiceError as exc:
                    status, retry = exc.status, exc.retry_after
                except ServiceUnreachable as exc:
                    cause = exc.__cause__
                    with lock:
                        timeout = isinstance(cause, httpx.TimeoutException)
                        phase.count("timeout" if timeout else type(cause).__name__)
                    continue
                ms = (time.perf_counter() - t0) * 1e3
                with lock:
                    phase.count(str(status))
                    if status == 200:
                        phase.latencies.append(ms)
                        timing = answer.timing_ms
                        for stage in ("queue", "decode", "extract", "hierarchy", "total"):
                            phase.stages.setdefault(stage, []).append(timing[stage])  # type: ignore[arg-type]
                        m = answer.match
                        phase.correct += m is not None and abs(m.reference_id - qi) <= 2
                    elif status == 503:
                        phase.busy_ms.append(ms)
                if status == 503:
                    time.sleep(min(0.2, retry if retry is not None else 1.0))

    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    phase.seconds = time.perf_counter() - t0
    return phase


def _pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, int(round(q / 100 * (len(s) - 1))))]


def _report(p: Phase) -> dict[str, object]:
    ok = len(p.latencies)
    errors = {c: n for c, n in p.codes.items() if c not in ("200", "503")}
    row = {
        "clients": p.clients,
        "seconds": round(p.seconds, 1),
        "answers": ok,
        "answers_per_s": ok / p.seconds,
        "p50_ms": _pct(p.latencies, 50),
        "p95_ms": _pct(p.latencies, 95),
        "p99_ms": _pct(p.latencies, 99),
        "max_ms": max(p.latencies, default=float("nan")),
        "server_median_ms": {k: statistics.median(v) for k, v in p.stages.items()},
        "503": p.codes.get("503", 0),
        "503_p99_ms": _pct(p.busy_ms, 99),
        "errors": errors,
        "within_2_frames": p.correct / ok if ok else float("nan"),
    }
    st = row["server_median_ms"]
    print(
        f"{p.clients:>3} clients: {row['answers_per_s']:6.1f} answers/s  "
        f"p50 {row['p50_ms']:6.1f}  p95 {row['p95_ms']:6.1f}  p99 {row['p99_ms']:6.1f}  "
        f"max {row['max_ms']:6.1f} ms  | 503s {row['503']:>4} (p99 {row['503_p99_ms']:.1f} ms)  "
        f"errors {sum(errors.values())} {errors or ''}  "
        f"| within +-2 frames {row['within_2_frames']:.3f}"
    )
    if st:
        print(
            "             server medians (ms): " + "  ".join(f"{k} {v:.1f}" for k, v in st.items())  # type: ignore[union-attr]
        )
    return row


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "default.yaml")
    ap.add_argument("--index", type=Path, default=None)
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 8])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--overload", type=int, default=48, help="clients of the overload phase")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--queue", type=int, default=None)
    add_json(ap, type=Path)
    args = ap.parse_args()

    index = _ensure_index(args.config.resolve(), args.index)
    queries = list_images(dataset_root() / "gardens_point" / "night_right")
    frames = [p.read_bytes() for p in queries]
    print(f"machine: {machine()}")
    print(f"config {args.config.name}, {len(frames)} night_right query frames, raw JPEG bodies")
    with tempfile.TemporaryDirectory() as tmp:
        port = _free_port()
        proc = _start(index, port, args, Path(tmp) / "serve.log")
        try:
            with Client(f"http://127.0.0.1:{port}", timeout=10) as service:
                meta = service.index()
            print(
                f"index {meta.version}: {meta.references} references, methods "
                f"{', '.join(meta.methods)}"
            )
            _run_phase(port, 2, 3.0, frames)  # warm-up
            rows = []
            for n in [*args.clients, *([args.overload] if args.overload else [])]:
                rows.append(_report(_run_phase(port, n, args.duration, frames)))
            alive = _request(port, "GET", "/healthz", b"", 5)[0] == 200
            print(f"server alive after the run: {alive}")
        finally:
            proc.terminate()
            proc.wait(30)
    if args.json:
        results = {"config": str(args.config), "phases": rows, "server_alive_after": alive}
        write_record(args.json, results, args, preset=args.config.stem, config=args.config)
    return 0


if __name__ == "__main__":
    sys.exit(main())
