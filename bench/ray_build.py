"""Build throughput of ``hmpf-index build`` locally and on a local Ray instance, 1 and 2 workers.

    .venv/bin/python -m bench.ray_build [--images ../shared/datasets/gardens_point/day_right]
        [--config default] [--limit 200] [--repeat 1] [--modes local1,local2,ray1,ray2] [--json F]

Every build starts from a fresh index folder, so nothing is cached (the work folder's feature
cache is per build; the exported ONNX backbones in ``HMPF_CACHE_DIR`` / ``~/.cache/hmpf``
are reused, as on any machine after its first build). A Ray build starts its own local Ray
instance (``--ray`` without an address) of as many CPUs as workers, and stops it at the end:
its time includes that; the startup and shutdown of an empty instance is measured on its own
(``ray.init`` + ``ray.shutdown``), and so is a Ray build's time without it. Prints one table
row per mode: median seconds and images/s end to end (hashing, fitting on the driver,
extraction, HDF5, fsync), and the load average before the runs (the machine may be shared).
``--json F`` writes the same figures as a JSON record (provenance, then one entry per mode).
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

from bench.harness import add_json, parser, write_record
from hmpf.datasets import dataset_root, list_images
from indexer.build import BuildOptions, build
from indexer.distributed import RayOptions, require_ray


def _options(mode: str) -> BuildOptions:
    workers = int(mode[-1])
    ray = RayOptions(workers=workers) if mode.startswith("ray") else None
    return BuildOptions(workers=workers, progress=False, ray=ray)


def _ray_startup(workers: int) -> float:
    """Seconds to start and stop an empty local Ray instance of ``workers`` CPUs."""
    ray = require_ray()
    t0 = time.perf_counter()
    ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    ray.shutdown()
    return time.perf_counter() - t0


def main() -> None:
    p = parser(__doc__)
    default_images = dataset_root() / "gardens_point" / "day_right"
    p.add_argument("--images", default=str(default_images))
    p.add_argument("--config", default="default")
    p.add_argument("--limit", type=int, default=200)
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--modes", default="local1,local2,ray1,ray2")
    add_json(p)
    a = p.parse_args()
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    modes = a.modes.split(",")
    load = os.getloadavg()
    rows = []
    by_mode: dict[str, dict[str, float | int | None]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "images"
        folder.mkdir()
        for src in list_images(a.images)[: a.limit]:
            (folder / src.name).symlink_to(src.resolve())
        for mode in modes:
            secs, startup = [], []
            for r in range(a.repeat):
                if mode.startswith("ray"):
                    startup.append(_ray_startup(int(mode[-1])))
                index = Path(tmp) / f"index-{mode}-{r}"
                s = build(a.config, folder, index, options=_options(mode))
                secs.append(s.seconds)
                n = s.images
            med = statistics.median(secs)
            line = f"| {mode} | {med:.1f} | {n / med:.2f} |"
            by_mode[mode] = {
                "workers": int(mode[-1]),
                "ray": mode.startswith("ray"),
                "seconds": med,
                "images_per_s": n / med,
                "ray_start_stop_s": None,
                "images_per_s_without_start_stop": None,
            }
            if startup:
                st = statistics.median(startup)
                line += f" {st:.1f} | {n / (med - st):.2f} |"
                by_mode[mode]["ray_start_stop_s"] = st
                by_mode[mode]["images_per_s_without_start_stop"] = n / (med - st)
            else:
                line += " - | - |"
            rows.append(line)
            print(line, flush=True)
    print(f"\nconfig {a.config}, {n} images of {a.images}, {os.cpu_count()} CPUs")
    print(f"median of {a.repeat} run(s) per mode")
    print(f"load average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print(
        "| mode | build s | images/s | Ray start+stop s | images/s without start+stop |\n"
        "|---|---|---|---|---|"
    )
    print("\n".join(rows))
    if a.json:
        results = {
            "images": n,
            "cpus": os.cpu_count(),
            "load_before": list(load),
            "modes": by_mode,
        }
        print(f"report: {write_record(a.json, results, a, preset=a.config)}")


if __name__ == "__main__":
    main()
