"""Several ``hmpf-serve`` replicas behind HAProxy: its configuration, and a reload that reaches
every replica (docs/replicas.md).

    hmpf-serve replicas haproxy --bind 0.0.0.0:8000 \\
        --replica 127.0.0.1:8001 --replica 127.0.0.1:8002 --out /etc/haproxy/hmpf
    haproxy -f /etc/haproxy/hmpf/haproxy.cfg
    hmpf-serve replicas reload --key-file admin.key \\
        http://127.0.0.1:8001 http://127.0.0.1:8002
    hmpf-serve replicas run --index /srv/hmpf/index --replicas 2 \\
        --bind 0.0.0.0:8000 --out /tmp/hmpf-haproxy      (all on one machine, foreground)

``haproxy`` writes ``haproxy.cfg`` and the JSON error answers HAProxy itself gives
(``errors/*.http``) into ``--out`` (``deploy/haproxy/`` in the repository is this command's
output for two replicas). What the configuration does:

* balances each request (``leastconn``: a replica busy with a slow query gets the next one
  later) over the replicas that answer ``GET /readyz`` (checked every second; two failures
  take a replica out, two successes put it back);
* a connection a replica refuses or drops before answering is tried again on another replica
  (``retries``, ``option redispatch 1``, ``retry-on conn-failure empty-response``; a request
  body larger than HAProxy's buffer, 16 KiB by default, cannot be kept for that);
* what HAProxy answers itself is the service's error JSON: no replica up, or a replica that
  failed mid-request, is a **503 with Retry-After: 1** (``hmpf.client`` sends the request
  again; the service keeps no state between requests, so a frame sent twice is answered the
  same way twice); a bad request 400, a slow client 408, a replica that does not answer in
  ``--server-timeout`` seconds 504 (not retried: the query may still be running);
* every answer names the replica that gave it (``X-Hmpf-Replica``);
* HAProxy, not the replica, faces the clients' connections: it waits ``timeout http-request``
  for a request's headers and holds idle client connections itself. Towards each replica it
  keeps at most ``--server-maxconn`` requests in progress (default 96, under the replica's
  ``max_connections`` of 128; more wait in HAProxy's queue up to ``timeout queue``) and at
  most 32 idle connections (``pool-max-conn``, under the replica's ``max_idle_connections``
  of 64), so a replica neither refuses HAProxy's requests nor closes its pooled connections.
  Raise the replica's two settings with these if you raise them.

``reload`` posts ``POST /v1/index/reload`` to each replica directly (a reload sent through the
balancer reaches one replica only); with ``watch_current_s`` set on the replicas (the
recommended way), ``hmpf-index use`` alone reaches all of them.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["ERROR_ANSWERS", "HaproxyOptions", "error_files", "haproxy_config", "main"]

#: HAProxy's own answers, as the service's error JSON: status -> (status sent, code, message).
#: 502 (a replica broke the connection before answering) and 503 (no replica up) become a
#: 503 with Retry-After, which clients retry.
ERROR_ANSWERS: dict[int, tuple[int, str, str]] = {
    400: (400, "bad_request", "the request is not valid HTTP"),
    408: (408, "request_timeout", "the request did not arrive in time"),
    500: (500, "balancer_error", "the load balancer failed"),
    502: (503, "replica_failed", "the replica serving the request failed; send it again"),
    503: (503, "no_replica", "no replica is available; try again"),
    504: (504, "replica_timeout", "the replica did not answer in time"),
}
_REASONS = {
    400: "Bad Request",
    408: "Request Timeout",
    500: "Internal Server Error",
    503: "Service Unavailable",
    504: "Gateway Timeout",
}


@dataclass(frozen=True)
class HaproxyOptions:
    """What varies between deployments (the defaults suit replicas on one machine)."""

    bind: str = "127.0.0.1:8000"
    replicas: tuple[str, ...] = ("127.0.0.1:8001", "127.0.0.1:8002")
    #: seconds between health checks of a replica (/readyz)
    check_interval_s: float = 1.0
    #: longest a replica may take to answer a request (then 504)
    server_timeout_s: float = 60.0
    #: connections HAProxy accepts at once
    maxconn: int = 4096
    #: requests in progress on one replica at once (keep it under its max_connections)
    server_maxconn: int = 96
    #: idle connections HAProxy keeps to one replica (under its max_idle_connections)
    server_pool: int = 32
    #: stats page address (``host:port``), or None for none
    stats: str | None = None


def error_files() -> dict[str, str]:
    """``errors/<status>.http`` -> the full HTTP answer HAProxy sends instead of its own."""
    out = {}
    for status, (sent, code, message) in ERROR_ANSWERS.items():
        body = json.dumps({"error": {"code": code, "message": message}}) + "\n"
        head = [
            f"HTTP/1.1 {sent} {_REASONS[sent]}",
            "Content-Type: application/json",
            f"Content-Length: {len(body.encode())}",
            "Cache-Control: no-cache",
            "Connection: close",
        ]
        if sent == 503:
            head.append("Retry-After: 1")
        out[f"errors/{status}.http"] = "\r\n".join(head) + "\r\n\r\n" + body
    return out


def _ms(seconds: float) -> str:
    return f"{max(1, round(seconds * 1000))}ms"


def haproxy_config(options: HaproxyOptions) -> str:
    """``haproxy.cfg`` for ``options``; the error files lie in ``errors/`` beside it."""
    if not options.replicas:
        raise ValueError("at least one replica expected")
    errors = "\n".join(
        f"    errorfile {status} errors/{status}.http" for status in sorted(ERROR_ANSWERS)
    )
    servers = "\n".join(
        f"    server replica{i} {address}" for i, address in enumerate(options.replicas, 1)
    )
    stats = (
        ""
        if options.stats is None
        else f"""
frontend stats
    bind {options.stats}
    stats enable
    stats uri /stats
    stats refresh 5s
"""
    )
    limits = f"maxconn {options.server_maxconn} pool-max-conn {options.server_pool}"
    return f"""\
# hmpf-serve replicas behind HAProxy (written by `hmpf-serve replicas haproxy`;
# docs/replicas.md). Every replica serves the same index folder with the same keys file and
# sequence key, and watches the index's CURRENT (HMPF_WATCH_CURRENT_S).
global
    # relative paths (errors/) are relative to this file
    default-path config
    maxconn {options.maxconn}
    log stdout format raw local0 notice

defaults
    mode http
    log global
    option httplog
    option dontlognull
    timeout connect 2s
    timeout client 75s
    timeout http-request 15s
    timeout http-keep-alive 10s
    timeout queue 10s
    timeout server {_ms(options.server_timeout_s)}
    # a refused or dropped connection is tried again, on another replica each time
    retries 3
    option redispatch 1
    retry-on conn-failure empty-response
{errors}

frontend hmpf
    bind {options.bind}
    default_backend replicas

backend replicas
    balance leastconn
    option httpchk GET /readyz
    http-check expect status 200
    default-server check inter {_ms(options.check_interval_s)} fall 2 rise 2 {limits}
    http-response set-header X-Hmpf-Replica %[srv_name]
{servers}
{stats}"""


def write_haproxy(options: HaproxyOptions, out: Path) -> Path:
    """Write ``haproxy.cfg`` and its error files into ``out``; returns the config's path."""
    (out / "errors").mkdir(parents=True, exist_ok=True)
    for name, text in error_files().items():
        (out / name).write_bytes(text.encode())
    cfg = out / "haproxy.cfg"
    cfg.write_text(haproxy_config(options))
    return cfg


def reload_all(urls: list[str], api_key: str | None, timeout: float = 300.0) -> int:
    """``POST /v1/index/reload`` to each replica; prints one line each; 0 when all
    answered 200, else 1."""
    import httpx  # ~0.2 s to import: only the reload command needs it

    headers = {"X-API-Key": api_key} if api_key else {}
    failed = 0
    for url in urls:
        try:
            r = httpx.post(url.rstrip("/") + "/v1/index/reload", headers=headers, timeout=timeout)
        except httpx.HTTPError as exc:
            print(f"{url}: no answer: {type(exc).__name__}: {exc}")
            failed += 1
            continue
        if r.status_code == 200:
            body = r.json()
            print(f"{url}: {body['previous']} -> {body['version']}")
        else:
            print(f"{url}: {r.status_code} {r.text.strip()[:300]}")
            failed += 1
    return 1 if failed else 0


def run_replicas(
    index: Path,
    n: int,
    bind: str,
    first_port: int,
    haproxy: str,
    folder: Path,
    watch_s: float = 2.0,
) -> int:
    """Start ``n`` ``hmpf-serve`` replicas on ``first_port``.. (the other settings from the
    environment: ``HMPF_KEYS_FILE``, ``HMPF_SEQUENCE_KEY_FILE``, ...) and HAProxy on ``bind``
    in front of them, until SIGINT / SIGTERM or until one of them exits; then stop all.
    Returns the exit status: 0 after a signal, 1 when a process ended by itself."""
    env = dict(os.environ)
    env.setdefault("HMPF_WATCH_CURRENT_S", str(watch_s))
    ports = [first_port + i for i in range(n)]
    cfg = write_haproxy(
        HaproxyOptions(bind=bind, replicas=tuple(f"127.0.0.1:{p}" for p in ports)), folder
    )
    procs: list[subprocess.Popen[bytes]] = []
    stop = False

    def on_signal(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        for port in ports:
            cmd = [sys.executable, "-m", "service.cli", "--index", str(index)]
            procs.append(subprocess.Popen([*cmd, "--port", str(port)], env=env))
        procs.append(subprocess.Popen([haproxy, "-db", "-f", str(cfg)]))
        print(f"{n} replicas on ports {ports[0]}..{ports[-1]}, HAProxy on {bind} ({cfg})")
        while not stop and all(p.poll() is None for p in procs):
            time.sleep(0.2)
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return 0 if stop else 1


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="hmpf-serve replicas",
        description="hmpf-serve replicas behind HAProxy (docs/replicas.md).",
    )
    sub = ap.add_subparsers(dest="command", required=True)
    h = sub.add_parser("haproxy", help="write haproxy.cfg and its error answers")
    h.add_argument("--bind", default=HaproxyOptions.bind, help="address:port clients use")
    h.add_argument(
        "--replica",
        action="append",
        metavar="HOST:PORT",
        help="a replica's address (repeat; default 127.0.0.1:8001 and :8002)",
    )
    h.add_argument("--check-interval", type=float, default=HaproxyOptions.check_interval_s)
    h.add_argument("--server-timeout", type=float, default=HaproxyOptions.server_timeout_s)
    h.add_argument(
        "--server-maxconn",
        type=int,
        default=HaproxyOptions.server_maxconn,
        help="requests in progress on one replica at once (under its max_connections)",
    )
    h.add_argument("--stats", metavar="HOST:PORT", help="serve HAProxy's stats page there")
    h.add_argument("--out", type=Path, required=True, help="folder to write into")
    run = sub.add_parser(
        "run",
        help="start N hmpf-serve replicas and HAProxy in front of them (one machine)",
        description="Start N hmpf-serve replicas on ports PORT+1.. and HAProxy on --bind; "
        "other settings come from HMPF_* variables (HMPF_KEYS_FILE, "
        "HMPF_SEQUENCE_KEY_FILE, ...); HMPF_WATCH_CURRENT_S defaults to 2 here.",
    )
    run.add_argument("--index", type=Path, required=True)
    run.add_argument("--replicas", type=int, default=2, metavar="N")
    run.add_argument("--bind", default="127.0.0.1:8000", help="address:port clients use")
    run.add_argument("--haproxy", default="haproxy", help="the haproxy binary")
    run.add_argument("--out", type=Path, required=True, help="folder for haproxy.cfg")
    r = sub.add_parser("reload", help="POST /v1/index/reload to every replica directly")
    r.add_argument("urls", nargs="+", metavar="URL", help="each replica's base URL")
    r.add_argument("--key-file", type=Path, help="file holding an admin API key")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "haproxy":
        options = HaproxyOptions(
            bind=args.bind,
            replicas=tuple(args.replica or HaproxyOptions.replicas),
            check_interval_s=args.check_interval,
            server_timeout_s=args.server_timeout,
            server_maxconn=args.server_maxconn,
            stats=args.stats,
        )
        print(write_haproxy(options, args.out))
        return 0
    if args.command == "run":
        if args.replicas < 1:
            raise SystemExit("--replicas: at least 1")
        port = int(args.bind.rsplit(":", 1)[1])
        return run_replicas(args.index, args.replicas, args.bind, port + 1, args.haproxy, args.out)
    key = args.key_file.read_text().strip() if args.key_file else None
    return reload_all(args.urls, key)


if __name__ == "__main__":
    sys.exit(main())
