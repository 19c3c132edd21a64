"""A reload gives the memory of the version it retires back to the OS.

A version's CNN sessions, matrices and caches are allocated by many threads; freed, glibc kept
those pages in its arenas, and a server's resident memory grew at every reload (the soak bench
found +720 MiB over 10 minutes of reloads and adds with the default preset). The engine now
trims the heap when a retired version is garbage (``service.engine._trim_soon``).

Measured in a fresh interpreter (the test process holds other tests' garbage): one index with
a CNN method, loaded seven times; without the trim the resident memory grew by about 40 MiB
between the second and the last load on the development machine, with it by nothing.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hmpf.config import parse_config
from indexer.build import BuildOptions, build

PROBE = """
import json, os, sys, time
from pathlib import Path
import service.engine as engine

def rss_mib():
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

if sys.argv[2] == "off":
    engine._TRIM = None
e = engine.Engine(Path(sys.argv[1]), workers=2, queue=8, threads_per_worker=1)
out = []
for _ in range(7):
    e.load()
    e.check_done(timeout=60)
    time.sleep(0.5)  # the trim runs on its own thread
    out.append(rss_mib())
e.close()
print(json.dumps(out))
"""


def _rss_after_loads(index: Path, trim: str) -> list[float]:
    done = subprocess.run(
        [sys.executable, "-c", PROBE, str(index), trim],
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    )
    return [float(x) for x in json.loads(done.stdout.strip().splitlines()[-1])]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc; glibc's trim")
def test_reloads_do_not_grow_resident_memory(gardens_point: Path, tmp_path: Path) -> None:
    refs = tmp_path / "refs"
    refs.mkdir()
    for p in sorted((gardens_point / "day_right").iterdir())[:6]:
        shutil.copy(p, refs / p.name)
    index = tmp_path / "index"
    config = parse_config({"name": "gem-only", "tiers": [{"methods": ["gem"], "k": 1}]})
    build(config, refs, index, options=BuildOptions(workers=1, progress=False))
    rss = _rss_after_loads(index, "on")
    # the first load's peak is the baseline; six reloads later the process holds no more
    assert rss[-1] - rss[1] < 15, f"resident MiB after each load: {rss}"
