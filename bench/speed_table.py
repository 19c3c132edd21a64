"""Before / after: the default hierarchy's speed with each of its speed levers, one run.

    python -m bench.speed_table [--images 20] [--duration 20] [--rows after openvino ...]
        [--nordland-frames 1000] [--json F]

Rows (the same machine, images and run):

* ``before``: the default hierarchy in torch (GeM 224 x 224, NetVLAD 288 x 512, OLO 416 x 416:
  three EfficientNet-Lite0 passes per query);
* ``after``: the same in ONNX Runtime (the default runtime until 2026-12-07);
* ``fast``: the ``fast`` preset in ONNX Runtime (one shared 224 x 384 pass);
* ``openvino``: the default hierarchy in OpenVINO (``HMPF_CNN_RUNTIME=openvino``, float32:
  the same answers as ONNX Runtime; needs the ``openvino`` extra);
* the levers that change the passes (measured, not adopted), each a config of
  ``bench/cpu_levers/`` in the default runtime (``auto``: OpenVINO on a CPU with AVX-512,
  ONNX Runtime elsewhere): ``olo_288``
  (OLO's pass at 288 x 288), ``netvlad_256`` (NetVLAD's at 256 x 448), ``lite0_320`` (GeM and
  OLO share one Lite0 pass at 320 x 320), ``gem_on_olo`` (GeM reads OLO's pass),
  ``one_pass_lite1`` (every method reads one Lite1 pass), ``bf16_gem_olo`` (GeM and OLO in
  bfloat16 through OpenVINO); and ``default_auto``, the default hierarchy in the default
  runtime. The default rows are ``after``, ``openvino`` and ``fast``. A lever row is compared
  with the row of the default hierarchy in the same runtime (``openvino`` on a CPU with
  AVX-512, ``after`` elsewhere).

Columns:

* one query on one thread, end to end (decode + extraction + hierarchy against the 200
  day_right references; :func:`hmpf.evaluation.study.measure_query_ms`, median of
  ``--images`` night_right frames);
* HTTP (``bench/service_load.py``: a real ``hmpf-serve`` on loopback with its default 2
  workers x 1 thread, raw JPEG bodies, ``--duration`` s per phase): p50 of a lone client and
  answers/s with 8 clients, and the errors of both phases;
* index build of Gardens Point day_right (200 images, no feature cache, every core):
  images/s end to end;
* recall@1 of the hierarchy on the three Gardens Point protocols (+-2 frames) and on
  Nordland summer -> winter's first ``--nordland-frames`` frames, with every query's outcome
  (the record's ``correct``) for paired sign tests against another row.

The runtime is chosen by ``HMPF_CNN_RUNTIME`` (set for the service's process too).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from bench.harness import (
    ROOT,
    add_cache_dir,
    add_json,
    machine,
    parser,
    protocol_data,
    write_record,
)
from hmpf.config import HierarchyConfig, load_config
from hmpf.datasets import GARDENS_POINT_PROTOCOLS, dataset_root, list_images
from hmpf.evaluation.evaluate import EvalData, evaluate
from hmpf.evaluation.study import ScoreBank, measure_query_ms
from hmpf.features import FeatureCache
from hmpf.runtime import cnn_runtime, set_cnn_runtime
from indexer.build import BuildOptions, build

LEVERS = ROOT / "bench" / "cpu_levers"
#: row -> (CNN runtime, preset or config file); ``auto``: the default runtime.
ROWS = {
    "before": ("torch", "default"),
    "after": ("onnx", "default"),
    "fast": ("onnx", "fast"),
    "openvino": ("openvino", "default"),
    "default_auto": ("auto", "default"),
    **{
        lever: ("auto", str(LEVERS / f"{lever}.yaml"))
        for lever in (
            "olo_288",
            "netvlad_256",
            "lite0_320",
            "gem_on_olo",
            "one_pass_lite1",
            "bf16_gem_olo",
        )
    },
}
DEFAULT_ROWS = ["after", "openvino", "fast"]
NORDLAND = "nordland_s_w"


def write_yaml(config: HierarchyConfig, folder: Path) -> Path:
    path = folder / f"{config.name}.yaml"
    path.write_text(yaml.safe_dump(config.model_dump(mode="json", exclude_unset=True)))
    return path


def http(
    config_yaml: Path, index: Path, runtime: str, duration: float, out: Path
) -> dict[str, Any]:
    """``python -m bench.service_load``'s phases with 1 and 8 clients (no overload phase)."""
    cmd = [sys.executable, "-m", "bench.service_load", "--config", str(config_yaml)]
    cmd += ["--index", str(index)]
    cmd += ["--clients", "1", "8", "--duration", str(duration), "--overload", "0"]
    cmd += ["--json", str(out)]
    env = {**os.environ, "HMPF_CNN_RUNTIME": runtime}
    subprocess.run(cmd, check=True, env=env, cwd=ROOT, stdout=subprocess.DEVNULL)
    return json.loads(out.read_text())


def build_rate(config_yaml: Path, tmp: Path, index: Path) -> float:
    images = tmp / "images"
    if not images.exists():
        images.mkdir()
        for src in list_images(dataset_root() / "gardens_point" / "day_right"):
            (images / src.name).symlink_to(src.resolve())
    summary = build(config_yaml, images, index, options=BuildOptions(progress=False))
    return float(summary.images_per_s)


def protocols(nordland_frames: int) -> dict[str, EvalData]:
    """The three Gardens Point protocols and, unless ``nordland_frames`` is 0, Nordland summer
    -> winter's first ``nordland_frames`` frames of each traverse (+-2 frames)."""
    out = {
        name: EvalData.frames(dataset_root() / r, dataset_root() / q, 2)
        for name, (r, q) in GARDENS_POINT_PROTOCOLS.items()
    }
    if nordland_frames:
        n = nordland_frames
        data = protocol_data(NORDLAND)
        out[NORDLAND] = replace(
            data, reference=data.reference[:n], query=data.query[:n], gt=data.gt[:n, :n]
        )
    return out


def recalls(
    config: HierarchyConfig, cache: FeatureCache, data: dict[str, EvalData]
) -> tuple[dict[str, float], dict[str, list[bool]]]:
    """recall@1 of the hierarchy per protocol, and whether each query's answer was right."""
    recall, correct = {}, {}
    for name, d in data.items():
        rep = evaluate(config, d, cache=cache, skip_curves=list(config.method_ids))
        matches = np.asarray(rep["hierarchy"]["matches"], dtype=np.int64)
        right = [bool(m >= 0 and d.gt[i, m]) for i, m in enumerate(matches)]
        recall[name] = float(rep["hierarchy"]["combined_recall_at_1"])
        if abs(recall[name] - float(np.mean(right))) > 1e-9:
            raise RuntimeError(f"{name}: recall {recall[name]} but {np.mean(right)} right")
        correct[name] = right
    return recall, correct


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--images", type=int, default=20, help="queries timed on one thread")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds per HTTP phase")
    ap.add_argument("--rows", nargs="*", default=DEFAULT_ROWS, choices=list(ROWS))
    ap.add_argument(
        "--nordland-frames", type=int, default=1000, help="Nordland frames per traverse (0: none)"
    )
    add_cache_dir(ap)
    add_json(ap, type=Path)
    args = ap.parse_args()
    print(f"Machine: {machine()}", flush=True)
    cache = FeatureCache(args.cache_dir)
    gp = dataset_root() / "gardens_point"
    timed = EvalData.frames(gp / "day_right", gp / "night_right", 2)
    data = protocols(args.nordland_frames)
    table: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for row in args.rows:
            set_cnn_runtime(ROWS[row][0])
            runtime, which = cnn_runtime(), ROWS[row][1]  # auto: the runtime it chose
            config = load_config(which)
            config_yaml = write_yaml(config, tmp)
            bank = ScoreBank.build(config, timed, cache=cache)
            q = measure_query_ms(config, bank, images=args.images, threads=1)
            index = tmp / f"index-{row}"
            rate = build_rate(config_yaml, tmp, index)
            load = http(config_yaml, index, runtime, args.duration, tmp / f"{row}-load.json")
            recall, correct = recalls(config, cache, data)
            table[row] = {
                "runtime": runtime,
                "config": config.name,  # the preset's name, or the lever config's
                "digest": config.digest(),
                "query": q,
                "http": load,
                "build_images_per_s": rate,
                "recall": recall,
                "correct": correct,
            }
            print(f"{row}: {json.dumps({k: v for k, v in table[row].items() if k != 'correct'})}")
            if args.json:  # a row at a time: an interrupted run keeps the rows it measured
                write_record(args.json, {"rows": table}, args)
    print(f"\nMachine: {machine()}; one run of every row.\n")
    names = " / ".join(data)
    print(
        "| row | config, runtime | one query, 1 thread (extract + hierarchy) | HTTP p50, 1 client "
        f"| answers/s, 8 clients (errors) | build, images/s | recall@1 {names} |"
    )
    print("|---|---|---:|---:|---:|---:|---|")
    for row, r in table.items():
        q, phases = r["query"], {p["clients"]: p for p in r["http"]["phases"]}
        one, eight = phases[1], phases[8]
        errors = sum(sum(p["errors"].values()) + int(p["503"]) for p in (one, eight))
        rec = " / ".join(f"{r['recall'][p]:.3f}" for p in r["recall"])
        print(
            f"| {row} | {r['config']}, {r['runtime']} | {q['total_ms']:.1f} ms "
            f"({q['extract_ms']:.1f} + {q['hierarchy_ms']:.1f}) | {one['p50_ms']:.1f} ms "
            f"| {eight['answers_per_s']:.1f} ({errors}) | {r['build_images_per_s']:.1f} | {rec} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
