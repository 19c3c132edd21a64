"""Soak test of ``hmpf-serve``: a real server under a mixed, partly hostile load for minutes.

    .venv/bin/python -m bench.soak [--minutes 10] [--vehicles 4] [--reload-every 120]
        [--add-every 180] [--out results/soak.json]

Builds a fresh index (default config) of the first 150 Gardens Point ``day_right`` frames in a
temporary folder, creates a vehicle and an admin API key, and starts a real ``hmpf-serve``
process on a free loopback port (authentication on, default limits). Then, for ``--minutes``:

* ``--vehicles`` vehicles, each a closed loop posting ``night_right`` frames in route order
  in sequence mode (``vehicle_id``, ``timestamp``, the ``track`` token of its last answer),
  through :class:`hmpf.client.Client` (one pooled connection each);
* one hostile client cycling through: random bytes as a JPEG, a truncated JPEG, an upload
  announcing 1 MiB more than ``max_upload_bytes`` (its answer read after 64 kB), an
  upload aborted mid-body (a raw socket that announces more bytes than it sends and hangs
  up), a batch of three frames, a request without a key;
* an operator: ``POST /v1/index/reload`` every ``--reload-every`` seconds, and every
  ``--add-every`` seconds ``hmpf-index add`` of ten more ``day_right`` frames (a new version)
  followed by a reload.

Every request is bounded (30 s timeout) and goes to loopback only. A sampler reads the
server's resident memory (``VmRSS``) and open file descriptors from ``/proc`` every 5 s.

Prints and writes: requests by kind and status, latency p50/p99 of the vehicles' answers,
RSS and open descriptors at start, end and peak (and every sample, in the JSON), and the
number of 5xx answers. The run fails, exit 1, on any 5xx, when the *floor* of the resident
memory rises: the lowest RSS of the last ``--floor-minutes`` exceeds the first minute's
median by more than ``--rss-growth-mb``; or when the open descriptors grow by more than
``--fd-growth`` between the first and the last minute. The floor, not a median: a reload
holds the old version until the new one's background check has passed (minutes on cores
busy with queries), and a version published meanwhile can add a third, so the level between
reloads is mostly peaks; a leak raises the level the server comes back to, which is the
lowest sample of a window longer than a reload's check. The medians' growth and the peak
are reported beside.
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import random
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any, NamedTuple

from bench.harness import ROOT, add_json, parser, write_record
from hmpf.client import Client, ServiceError, ServiceUnreachable
from hmpf.datasets import dataset_root, list_images

TIMEOUT_S = 30.0
BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def request(
    port: int,
    method: str,
    path: str,
    body: bytes | None = None,
    headers: dict[str, str] | None = None,
) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=TIMEOUT_S)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        r = conn.getresponse()
        return r.status, r.read()
    finally:
        conn.close()


def multipart(files: list[tuple[str, str, bytes]]) -> tuple[bytes, str]:
    """(field, filename, JPEG bytes) parts as a multipart/form-data body and its type."""
    boundary = uuid.uuid4().hex
    out = bytearray()
    for field, name, data in files:
        out += f"--{boundary}\r\n".encode()
        out += f'Content-Disposition: form-data; name="{field}"; filename="{name}"\r\n'.encode()
        out += b"Content-Type: image/jpeg\r\n\r\n" + data + b"\r\n"
    out += f"--{boundary}--\r\n".encode()
    return bytes(out), f"multipart/form-data; boundary={boundary}"


def proc_stats(pid: int) -> tuple[float, int]:
    """(resident MiB, open file descriptors) of a process, from /proc."""
    rss = 0.0
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            rss = int(line.split()[1]) / 1024.0
    return rss, len(os.listdir(f"/proc/{pid}/fd"))


class Log:
    """Thread-safe tallies of what was sent and what came back."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.codes: Counter[tuple[str, str]] = Counter()
        self.latency: list[float] = []
        self.errors: list[str] = []

    def add(self, kind: str, status: int | str, ms: float | None = None) -> None:
        with self.lock:
            self.codes[(kind, str(status))] += 1
            if ms is not None:
                self.latency.append(ms)

    def error(self, text: str) -> None:
        with self.lock:
            if len(self.errors) < 50:
                self.errors.append(text)


def vehicle(
    port: int, key: str, name: str, frames: list[bytes], stop: threading.Event, log: Log
) -> None:
    """A vehicle on :class:`hmpf.client.Client`, which carries its track (retries off: every
    answer is tallied)."""
    i, t = 0, 0.0
    with Client(f"http://127.0.0.1:{port}", key, timeout=TIMEOUT_S, retries=0) as service:
        while not stop.is_set():
            t0 = time.perf_counter()
            try:
                service.localize(frames[i % len(frames)], vehicle_id=name, timestamp=t)
                log.add("vehicle", 200, (time.perf_counter() - t0) * 1e3)
            except ServiceUnreachable as e:
                log.add("vehicle", type(e.__cause__).__name__)
                log.error(f"vehicle {name}: {e}")
                time.sleep(0.2)
                continue
            except ServiceError as e:  # an invalid_track: the client starts a new track
                log.add("vehicle", e.status)
                if e.status >= 500:
                    log.error(f"vehicle {name}: {e.status} {e.body!r:.300}")
                    if e.status == 503:
                        time.sleep(0.2)
            i += 1
            t += 0.5


def aborted_upload(port: int, key: str) -> str:
    """Announce a 200 kB JPEG body, send 4 kB of it, hang up."""
    with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S) as s:
        head = (
            "POST /v1/localize HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/jpeg\r\n"
            f"X-API-Key: {key}\r\nContent-Length: 200000\r\n\r\n"
        )
        s.sendall(head.encode() + b"\xff\xd8" + os.urandom(4096))
    return "sent"


def oversize_upload(port: int, key: str, max_upload: int) -> int | str:
    """Announce a body 1 MiB over ``max_upload`` (past the route's limit, which allows the
    multipart framing on top of the image), send 64 kB of it, read the answer (the server
    refuses from the Content-Length, before the body)."""
    with socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S) as s:
        head = (
            "POST /v1/localize HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/jpeg\r\n"
            f"X-API-Key: {key}\r\nContent-Length: {max_upload + 2**20}\r\n\r\n"
        )
        try:
            s.sendall(head.encode() + b"\xff\xd8" + bytes(65536))
        except OSError:
            pass  # refused early: the answer is still to be read
        line = s.makefile("rb").readline()
    parts = line.split()
    return int(parts[1]) if len(parts) >= 2 and parts[1].isdigit() else "no answer"


def hostile(
    port: int, key: str, frames: list[bytes], max_upload: int, stop: threading.Event, log: Log
) -> None:
    rng = random.Random(0)
    jpeg = {"Content-Type": "image/jpeg", "X-API-Key": key}
    kinds = ["garbage", "truncated", "oversize", "aborted", "batch", "no_key"]
    n = 0
    while not stop.is_set():
        kind = kinds[n % len(kinds)]
        n += 1
        try:
            if kind == "garbage":
                status, _ = request(port, "POST", "/v1/localize", rng.randbytes(5000), jpeg)
            elif kind == "truncated":
                frame = frames[n % len(frames)]
                status, _ = request(port, "POST", "/v1/localize", frame[: len(frame) // 3], jpeg)
            elif kind == "oversize":
                status = oversize_upload(port, key, max_upload)
            elif kind == "aborted":
                log.add(kind, aborted_upload(port, key))
                continue
            elif kind == "batch":
                body, ctype = multipart([("images", f"{j}.jpg", frames[j]) for j in range(3)])
                status, _ = request(
                    port,
                    "POST",
                    "/v1/localize/batch",
                    body,
                    {"Content-Type": ctype, "X-API-Key": key},
                )
            else:
                status, _ = request(
                    port, "POST", "/v1/localize", frames[0], {"Content-Type": "image/jpeg"}
                )
        except OSError as e:
            status = type(e).__name__
        log.add(kind, status)
        if isinstance(status, int) and status >= 500:
            log.error(f"hostile {kind}: {status}")
        time.sleep(0.05)


def operator(
    port: int,
    admin: str,
    index: Path,
    extra: list[Path],
    reload_every: float,
    add_every: float,
    stop: threading.Event,
    log: Log,
) -> None:
    start = time.monotonic()
    next_reload, next_add = start + reload_every, start + add_every
    batch = 0
    while not stop.wait(1.0):
        now = time.monotonic()
        if now >= next_add and batch * 10 < len(extra):
            with tempfile.TemporaryDirectory() as tmp:
                for p in extra[batch * 10 : (batch + 1) * 10]:
                    shutil.copy(p, Path(tmp) / p.name)
                cmd = [str(BIN / "hmpf-index"), "add", "--images", tmp, "--index", str(index)]
                r = subprocess.run(cmd + ["--quiet"], capture_output=True, text=True)
                log.add("index_add", r.returncode)
                if r.returncode:
                    log.error(f"hmpf-index add: {r.stderr[-500:]}")
            batch += 1
            next_add = now + add_every
            next_reload = now  # publish it
        if now >= next_reload:
            try:
                status, body = request(port, "POST", "/v1/index/reload", b"", {"X-API-Key": admin})
            except OSError as e:
                status, body = type(e).__name__, b""
            log.add("reload", status)
            if status != 200:
                log.error(f"reload: {status} {body[:300]!r}")
            next_reload = now + reload_every


def percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    v = sorted(values)
    return v[min(len(v) - 1, int(round(q * (len(v) - 1))))]


def build_index(work: Path, refs: list[Path]) -> Path:
    """A fresh index (default config) of ``refs`` copied under ``work``."""
    images = work / "refs"
    images.mkdir()
    for p in refs:
        shutil.copy(p, images / p.name)
    index = work / "index"
    t0 = time.perf_counter()
    subprocess.run(
        [str(BIN / "hmpf-index"), "build", "--config", "default", "--images", str(images)]
        + ["--index", str(index), "--quiet"],
        check=True,
    )
    print(f"index: {index} built in {time.perf_counter() - t0:.0f} s", flush=True)
    return index


class Server(NamedTuple):
    proc: subprocess.Popen[bytes]
    port: int
    vehicle_key: str
    admin_key: str
    max_upload: int


def start_server(work: Path, index: Path) -> Server:
    """``hmpf-serve`` on ``index`` on a free loopback port (authentication on, a vehicle and
    an admin key), once it answers ``/readyz``."""
    from service.auth import add_key
    from service.settings import load_settings

    keys = work / "keys.yaml"
    vkey, akey = add_key(keys, "soak-car", "vehicle"), add_key(keys, "soak-ops", "admin")
    max_upload = load_settings(None, index=index, keys_file=keys).max_upload_bytes
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("HMPF_")}
    env.update(HMPF_KEYS_FILE=str(keys), HMPF_LOG_LEVEL="warning")
    if "HMPF_DATASETS" in os.environ:
        env["HMPF_DATASETS"] = os.environ["HMPF_DATASETS"]
    log_path = work / "serve.log"
    server = subprocess.Popen(
        [str(BIN / "hmpf-serve"), "--index", str(index), "--port", str(port)],
        env=env,
        stdout=log_path.open("wb"),
        stderr=subprocess.STDOUT,
    )
    deadline = time.monotonic() + 300
    while True:
        if server.poll() is not None:
            raise SystemExit(f"hmpf-serve exited {server.returncode}: {log_path.read_text()}")
        try:
            if request(port, "GET", "/readyz")[0] == 200:
                return Server(server, port, vkey, akey, max_upload)
        except OSError:
            pass
        if time.monotonic() > deadline:
            server.kill()
            raise SystemExit("hmpf-serve did not become ready in 300 s")
        time.sleep(0.3)


def soak(
    srv: Server, index: Path, frames: list[bytes], extra_refs: list[Path], args: argparse.Namespace
) -> tuple[Log, list[tuple[float, float, int]], float, bool]:
    """The load for ``args.minutes``: the log, the server's (time, RSS, fds) samples, the
    seconds elapsed and whether the server was alive at the end (it is stopped then)."""
    log, stop = Log(), threading.Event()
    samples: list[tuple[float, float, int]] = []
    t_start = time.monotonic()

    def sampler() -> None:
        while True:
            samples.append((time.monotonic() - t_start, *proc_stats(srv.proc.pid)))
            if stop.wait(5.0):
                return

    threads = [threading.Thread(target=sampler)]
    for v in range(args.vehicles):
        offset = frames[v * len(frames) // max(1, args.vehicles) :] + frames
        threads.append(
            threading.Thread(
                target=vehicle, args=(srv.port, srv.vehicle_key, f"car-{v}", offset, stop, log)
            )
        )
    threads.append(
        threading.Thread(
            target=hostile, args=(srv.port, srv.vehicle_key, frames, srv.max_upload, stop, log)
        )
    )
    operator_args = (srv.port, srv.admin_key, index, extra_refs, args.reload_every, args.add_every)
    threads.append(threading.Thread(target=operator, args=(*operator_args, stop, log)))
    for th in threads:
        th.start()
    print(f"soak: {args.minutes:g} min on port {srv.port} ...", flush=True)
    stop.wait(args.minutes * 60)
    stop.set()
    for th in threads:
        th.join(timeout=TIMEOUT_S + 5)
    elapsed = time.monotonic() - t_start
    alive = srv.proc.poll() is None
    srv.proc.send_signal(signal.SIGTERM)
    try:
        srv.proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        srv.proc.kill()
    return log, samples, elapsed, alive


def rss_figures(
    samples: list[tuple[float, float, int]], elapsed: float, floor_minutes: float = 4.0
) -> dict[str, float]:
    """Resident memory (MiB) over the run: start, end, peak, and the floor of the last
    ``floor_minutes`` against the first minute's median (the judged figure: a leak raises the
    level the server comes back to between reloads), with the medians' and peaks' growth
    from the first to the last minute."""
    first = [s[1] for s in samples if s[0] <= 60] or [samples[0][1]]
    last = [s[1] for s in samples if s[0] >= elapsed - 60] or [samples[-1][1]]
    window = [s[1] for s in samples if s[0] >= elapsed - 60 * floor_minutes] or [samples[-1][1]]
    base = statistics.median(first)
    return {
        "start": samples[0][1],
        "end": samples[-1][1],
        "peak": max(s[1] for s in samples),
        "first_minute_median": base,
        "floor_minutes": floor_minutes,
        "floor_last_window": min(window),
        "floor_growth": min(window) - base,
        "growth_first_to_last_minute": statistics.median(last) - base,
        "peak_growth_first_to_last_minute": max(last) - max(first),
    }


def summary(
    log: Log,
    samples: list[tuple[float, float, int]],
    elapsed: float,
    alive: bool,
    vehicles: int,
    floor_minutes: float = 4.0,
) -> dict[str, Any]:
    """Requests by kind and status, the vehicles' latency, RSS and open descriptors."""
    five = sum(n for (_, st), n in log.codes.items() if st.isdigit() and int(st) >= 500)
    first = [s for s in samples if s[0] <= 60] or samples[:1]
    last = [s for s in samples if s[0] >= elapsed - 60] or samples[-1:]
    return {
        "minutes": elapsed / 60,
        "vehicles": vehicles,
        "requests": {f"{k} {s}": n for (k, s), n in sorted(log.codes.items())},
        "vehicle_latency_ms": {
            "n": len(log.latency),
            "p50": percentile(log.latency, 0.5),
            "p99": percentile(log.latency, 0.99),
            "mean": statistics.fmean(log.latency) if log.latency else None,
        },
        "rss_mib": rss_figures(samples, elapsed, floor_minutes),
        "open_fds": {
            "start": samples[0][2],
            "end": samples[-1][2],
            "peak": max(s[2] for s in samples),
            "growth_first_to_last_minute": max(s[2] for s in last) - max(s[2] for s in first),
        },
        "samples": [
            {"s": round(t, 1), "rss_mib": round(rss, 1), "fds": fds} for t, rss, fds in samples
        ],
        "server_alive_at_end": alive,
        "5xx": five,
        "errors": log.errors,
    }


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--vehicles", type=int, default=4)
    ap.add_argument("--reload-every", type=float, default=120.0)
    ap.add_argument("--add-every", type=float, default=180.0)
    ap.add_argument("--rss-growth-mb", type=float, default=150.0)
    ap.add_argument(
        "--floor-minutes",
        type=float,
        default=4.0,
        help="the window at the end whose lowest RSS is judged (longer than a reload's check)",
    )
    ap.add_argument("--fd-growth", type=int, default=20)
    add_json(ap, "--out", default=str(ROOT / "results" / "soak.json"), help="JSON report")
    args = ap.parse_args()
    gp = dataset_root() / "gardens_point"
    refs, night = list_images(gp / "day_right"), list_images(gp / "night_right")
    frames = [p.read_bytes() for p in night]
    work = Path(tempfile.mkdtemp(prefix="hmpf-soak-"))
    srv = None
    try:
        index = build_index(work, refs[:150])
        srv = start_server(work, index)
        log, samples, elapsed, alive = soak(srv, index, frames, refs[150:], args)
    finally:
        if srv is not None and srv.proc.poll() is None:
            srv.proc.kill()
        shutil.rmtree(work, ignore_errors=True)
    report = summary(log, samples, elapsed, alive, args.vehicles, args.floor_minutes)
    rss_growth = report["rss_mib"]["floor_growth"]
    fd_growth = report["open_fds"]["growth_first_to_last_minute"]
    ok = (
        report["5xx"] == 0
        and alive
        and rss_growth <= args.rss_growth_mb
        and fd_growth <= args.fd_growth
    )
    report["passed"] = ok
    out = write_record(args.out, report, args, config="default")  # build_index's config
    print(json.dumps(report, indent=1))
    print(f"wrote {out}; {'PASSED' if ok else 'FAILED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
