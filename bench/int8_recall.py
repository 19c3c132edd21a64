"""Cheaper CNN passes for the default hierarchy: static int8 (QDQ) backbones and other
runtimes (OpenVINO in float32 and bfloat16), recall and time against ONNX Runtime float32.

    python -m bench.int8_recall [--variants static ...] [--calibration 32]
        [--nordland-frames 1000] [--images 20] [--rounds 3] [--out F.json]

For every route (the three Gardens Point protocols, whole: 200 references, 200 queries; and
Nordland summer -> winter 64x32, its first ``--nordland-frames`` frames of each traverse, or
all with 0) and every int8 variant:

* each forward pass of the default preset (GeM on Lite0 at 224 and 128 px, NetVLAD on Lite1 at
  320 x 544, OLO on Lite0 at 416 x 416) is quantised from the float32 model the onnx runtime
  runs (the cached export), its activation ranges calibrated on ``--calibration`` of the
  route's *references*, evenly spaced (what an index build has: the images being indexed);
* references and queries are extracted with those int8 models (NetVLAD's centroids fitted on
  the int8 maps of the references, as a build would), in a feature cache of their own (a
  folder per set of int8 models: never the float32 descriptors' keys);
* recall@1 (+-2 frames) of each CNN method alone (over every reference) and of the default
  hierarchy (Gist stays float: it is no CNN), int8 against float32, with an exact paired sign
  test per route; the hierarchy also with only some passes int8 (a method's descriptors depend
  on its own passes only, so mixing the two extractions is exactly that hierarchy).

Variants (``onnxruntime.quantization``; all after ``quant_pre_process``):

* ``static``: QDQ, per-channel int8 weights, uint8 activations, MinMax calibration, every
  operator ONNX Runtime quantises;
* ``static_ends``: the same, with the first convolution and the nodes from the last
  convolution to each output left in float32;
* ``static_pct`` / ``static_entropy``: ``static`` with the activation ranges from the 99.999th
  percentile of the calibration values / the entropy (KL) method instead of min and max;
* ``dynamic``: int8 weights, activations quantised per run (no calibration).

Runtime variants (no calibration; the float32 model itself, run by another runtime, the
reference and query extraction both in it, as a version built and served with
``HMPF_CNN_RUNTIME`` set to it):

* ``openvino``: OpenVINO on the CPU in float32 (within float32 rounding of ONNX Runtime);
* ``openvino-bf16``: OpenVINO with bfloat16 inference precision (where the CPU has it).

For runtime variants the route also gets the figure a server sees after changing its runtime
(``served``): an index built with ONNX Runtime, queries through the version's stored models in
the variant (:func:`served_figures`).

Columns named ``int8`` in older records are the variant's figures (``variant`` in new ones).

Time (Gardens Point day_right -> night_right, one compute thread, the variants interleaved
``--rounds`` times): each forward pass alone (median ms of ``--images`` preprocessed
queries) and a whole query as ``bench.default_query`` measures it (decode + extraction +
hierarchy against the 200 references, :func:`hmpf.evaluation.study.measure_query_ms`).
"""

from __future__ import annotations

import hashlib
import json
import os
import statistics
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import (
    ROOT,
    add_cache_dir,
    add_json,
    machine,
    parser,
    protocol_data,
    provenance,
    record,
    samples_ms,
    write_json,
)
from hmpf.backbones import backbone_class
from hmpf.backbones.onnx_runtime import StoredModel, onnx_maps
from hmpf.config import HierarchyConfig, build_methods, load_config
from hmpf.evaluation.evaluate import EvalData, evaluate_index, prepare
from hmpf.evaluation.metrics import paired_test
from hmpf.evaluation.study import ScoreBank, measure_query_ms
from hmpf.features import FeatureCache, file_digest
from hmpf.imageio import load_image, to_rgb
from hmpf.index import IndexReader
from hmpf.methods.base import Method
from hmpf.methods.cnn import CnnMethod
from hmpf.runtime import compute_threads, default_cache_dir, set_cnn_runtime, set_compute_threads
from indexer.build import BuildOptions, build

OUT = ROOT / "docs" / "experiments" / "int8" / "int8_recall.json"
GP = ("gp_dr_nr", "gp_dl_nr", "gp_dl_dr")
NL = "nordland_s_w"
CNN = ("gem", "netvlad", "olo")
INT8_VARIANTS = ("static", "static_ends", "static_pct", "static_entropy", "dynamic")
#: The float32 models run by another runtime (:data:`hmpf.runtime.CNN_RUNTIMES`).
RUNTIME_VARIANTS = ("openvino", "openvino-bf16")
VARIANTS = INT8_VARIANTS + RUNTIME_VARIANTS
#: Partial variants: the CNN methods whose passes are int8 (the others float32).
SUBSETS = {
    "all": CNN,
    "gem": ("gem",),
    "netvlad": ("netvlad",),
    "olo": ("olo",),
    "gem+olo": ("gem", "olo"),
    "gem+netvlad": ("gem", "netvlad"),
    "netvlad+olo": ("netvlad", "olo"),
}
#: Bump when the quantisation procedure of this bench changes (new model and cache keys).
PROCEDURE = "1"


# -- quantisation ------------------------------------------------------------------------------


class Batches:
    """An ``onnxruntime.quantization.CalibrationDataReader`` over preprocessed images."""

    def __init__(self, name: str, batches: list[np.ndarray]) -> None:
        self.items = iter([{name: b} for b in batches])

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self.items, None)


def end_nodes(model_path: Path) -> list[str]:
    """The first Conv node, and for each graph output the nodes from it back to (and with)
    the last Conv that produces it."""
    import onnx

    g = onnx.load(str(model_path)).graph
    producer = {o: n for n in g.node for o in n.output}
    out: list[str] = []
    convs = [n for n in g.node if n.op_type == "Conv"]
    if convs:
        out.append(convs[0].name)
    for o in g.output:
        n = producer.get(o.name)
        while n is not None:
            out.append(n.name)
            if n.op_type == "Conv":
                break
            # follow the first input produced by a node (the data path, not a weight)
            n = next((producer[i] for i in n.input if i in producer), None)
    return sorted(set(out))


def quantise(fp32: Path, dest: Path, variant: str, calib: list[np.ndarray]) -> None:
    """Write ``variant`` of the float32 model ``fp32`` to ``dest``."""
    import onnxruntime
    from onnxruntime.quantization import (
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quant_pre_process,
        quantize_dynamic,
        quantize_static,
    )

    CALIBRATION = {
        "static_pct": CalibrationMethod.Percentile,
        "static_entropy": CalibrationMethod.Entropy,
    }
    onnxruntime.set_default_logger_severity(3)
    dest.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(fp32), str(pre))
        out = Path(tmp) / "q.onnx"
        if variant == "dynamic":
            quantize_dynamic(str(pre), str(out), weight_type=QuantType.QInt8, per_channel=True)
        else:
            exclude = end_nodes(pre) if variant == "static_ends" else []
            quantize_static(
                str(pre),
                str(out),
                Batches("input", calib),
                quant_format=QuantFormat.QDQ,
                per_channel=True,
                activation_type=QuantType.QUInt8,
                weight_type=QuantType.QInt8,
                calibrate_method=CALIBRATION.get(variant, CalibrationMethod.MinMax),
                nodes_to_exclude=exclude,
                extra_options={"CalibPercentile": 99.999},
            )
        os.replace(out, dest)


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def calibration_paths(refs: list[Path], n: int) -> list[Path]:
    """``n`` references evenly spaced along the route (all when fewer): deterministic."""
    pick = np.unique(np.linspace(0, len(refs) - 1, min(n, len(refs))).round().astype(int))
    return [refs[i] for i in pick]


def int8_models(
    methods: dict[str, CnnMethod], refs: list[Path], variant: str, n_calib: int, root: Path
) -> dict[str, dict[tuple[int, int], StoredModel]]:
    """Method id -> its int8 models by input size, calibrated on ``refs`` (kept under
    ``root`` by content key: the float32 model, the variant, the calibration images)."""
    calib = calibration_paths(refs, n_calib)
    calib_key = hashlib.sha256("".join(file_digest(p) for p in calib).encode()).hexdigest()
    rgb: list[np.ndarray] | None = None
    out: dict[str, dict[tuple[int, int], StoredModel]] = {}
    for mid, m in methods.items():
        net = m.backbone()
        prep = backbone_class(m.cnn.backbone).preprocessor(m.cnn.backbone_options)
        assert prep is not None
        layers = sorted(m.layers())
        out[mid] = {}
        for size in m.input_sizes():
            fp32 = onnx_maps(net, layers, size).path
            key = hashlib.sha256(
                f"{PROCEDURE}:{variant}:{sha(fp32)}:{calib_key}:{n_calib}".encode()
            ).hexdigest()[:24]
            dest = root / f"{fp32.stem}-{variant}-{key}.onnx"
            if not dest.exists():
                if rgb is None:
                    rgb = [to_rgb(load_image(p)) for p in calib]
                batches = [prep(im, size)[None].astype(np.float32) for im in rgb]
                quantise(fp32, dest, variant, batches)
            out[mid][size] = StoredModel(dest, layers, size, {"variant": variant, "key": key})
    return out


# -- recall ------------------------------------------------------------------------------------


def bank_of(methods: dict[str, Method], data: EvalData, cache: FeatureCache) -> ScoreBank:
    """:meth:`ScoreBank.build` for already built (and model-bearing) method instances."""
    prep = prepare(methods, data, cache=cache, workers=1)
    scores = {}
    feats = {}
    for mid, m in prep.methods.items():
        db, qs = prep.db[mid], prep.queries[mid]
        scores[mid] = np.stack([np.asarray(m.scores(q, db), np.float64) for q in qs])
        feats[mid] = (db, qs)
    return ScoreBank(prep.methods, scores, np.asarray(data.gt, bool), data, feats)


def mixed(fp32: ScoreBank, int8: ScoreBank, which: tuple[str, ...]) -> ScoreBank:
    """``fp32`` with the methods ``which`` taken from ``int8``."""
    pick = {m: (int8 if m in which else fp32) for m in fp32.methods}
    return ScoreBank(
        {m: b.methods[m] for m, b in pick.items()},
        {m: b.scores[m] for m, b in pick.items()},
        fp32.gt,
        fp32.data,
        {m: b.features[m] for m, b in pick.items()},
    )


def sign(a: np.ndarray, b: np.ndarray) -> dict[str, Any]:
    return paired_test(np.asarray(a, bool), np.asarray(b, bool))


def route_data(name: str, nordland_frames: int) -> EvalData:
    data = protocol_data(name)
    if name == NL and nordland_frames:
        n = nordland_frames
        data = replace(data, reference=data.reference[:n], query=data.query[:n], gt=data.gt[:n, :n])
    return data


def runtime_models(
    methods: dict[str, CnnMethod], variant: str
) -> dict[str, dict[tuple[int, int], StoredModel]]:
    """Method id -> its float32 exports by input size, run in the runtime ``variant`` (no
    calibration: the model itself, another runtime)."""
    out: dict[str, dict[tuple[int, int], StoredModel]] = {}
    for mid, m in methods.items():
        net, layers = m.backbone(), sorted(m.layers())
        out[mid] = {}
        for size in m.input_sizes():
            fp32 = onnx_maps(net, layers, size).path
            # ":run-own": features cached before a stored model's own runtime was honoured
            # (commit 81cd913) were ONNX Runtime's under this variant's name: not reused
            key = hashlib.sha256(f"{variant}:{sha(fp32)}:run-own".encode()).hexdigest()[:24]
            info = {"variant": variant, "key": key}
            out[mid][size] = StoredModel(fp32, layers, size, info, runtime=variant)
    return out


def int8_bank(
    config: HierarchyConfig,
    data: EvalData,
    variant: str,
    n_calib: int,
    root: Path,
) -> tuple[ScoreBank, dict[str, Any]]:
    """The CNN methods' bank with ``variant`` models: int8 ones calibrated on ``data``'s
    references, or the float32 exports in another runtime (:data:`RUNTIME_VARIANTS`)."""
    methods = {m: x for m, x in build_methods(config).items() if isinstance(x, CnnMethod)}
    if variant in RUNTIME_VARIANTS:
        models = runtime_models(methods, variant)
    else:
        models = int8_models(methods, list(data.reference), variant, n_calib, root / "models")
    for mid, m in methods.items():
        m.use_stored_models(models[mid], root / "models")
    key = hashlib.sha256(
        json.dumps(
            {m: {str(s): v.info["key"] for s, v in d.items()} for m, d in models.items()}
        ).encode()
    ).hexdigest()[:24]
    cache = FeatureCache(root / "features" / key)  # never the float32 descriptors' folders
    info = {
        "models": {
            m: {
                f"{s[0]}x{s[1]}": {"file": v.path.name, "bytes": v.path.stat().st_size}
                for s, v in d.items()
            }
            for m, d in models.items()
        },
        "feature_cache": str(cache.root),
    }
    return bank_of(dict(methods), data, cache), info


def route_figures(config: HierarchyConfig, fp32: ScoreBank, int8: ScoreBank) -> dict[str, Any]:
    """recall@1 of each CNN method and of the hierarchy (every int8 subset), with sign tests."""
    out: dict[str, Any] = {"methods": {}, "hierarchy": {}}
    for mid in CNN:
        a, b = int8.single_correct(mid), fp32.single_correct(mid)
        out["methods"][mid] = {
            "fp32": float(b.mean()),
            "variant": float(a.mean()),
            "sign_test": sign(a, b),
        }
    base = fp32.run(config).correct
    out["hierarchy"]["fp32"] = float(base.mean())
    out["hierarchy_flags_fp32"] = base.astype(int).tolist()
    for name, which in SUBSETS.items():
        got = mixed(fp32, int8, which).run(config).correct
        out["hierarchy"][name] = {"variant": float(got.mean()), "sign_test": sign(got, base)}
        out.setdefault("hierarchy_flags", {})[name] = got.astype(int).tolist()
    return out


def served_figures(
    config: HierarchyConfig,
    route: str,
    data: EvalData,
    variants: list[str],
    work: Path,
    cache: FeatureCache,
) -> dict[str, Any]:
    """The hierarchy as ``hmpf-serve`` answers after a change of runtime: an index of the
    route's references built with ONNX Runtime (float32, what every existing index holds),
    its queries extracted from the version's stored models in each runtime ``variants``
    (:func:`~hmpf.evaluation.evaluate.evaluate_index`, the service's per-query path):
    recall@1 and a sign test against the same queries in ONNX Runtime."""
    base = work / "served" / route
    refs, index = base / "refs", base / "index"
    if not (index / "CURRENT").exists():
        refs.mkdir(parents=True, exist_ok=True)
        for p in data.reference:
            link = refs / Path(p).name
            if not link.exists():
                link.symlink_to(Path(p).resolve())
        build(config, refs, index, options=BuildOptions(progress=False))
    column = {Path(p).name: j for j, p in enumerate(data.reference)}
    correct: dict[str, np.ndarray] = {}
    for rt in ("onnx", *variants):
        set_cnn_runtime(rt)
        try:
            with IndexReader(index) as reader:
                rep = evaluate_index(
                    reader, list(data.query), data.gt, data.ground_truth, cache=cache, workers=1
                )
        finally:
            set_cnn_runtime("onnx")
        matches = rep["hierarchy"]["matches"]
        correct[rt] = np.array(
            [m is not None and bool(data.gt[qi, column[m]]) for qi, m in enumerate(matches)]
        )
    base_flags = correct["onnx"]
    out: dict[str, Any] = {"index": str(index), "onnx": float(base_flags.mean())}
    for v in variants:
        out[v] = {"variant": float(correct[v].mean()), "sign_test": sign(correct[v], base_flags)}
    return out


# -- time --------------------------------------------------------------------------------------


def pass_times(
    fp32: ScoreBank, int8: dict[str, ScoreBank], images: list[np.ndarray], rounds: int
) -> dict[str, Any]:
    """Per forward pass (method, input size): median ms on one thread, the variants in turn
    each round (float32 from the same cached export the onnx runtime runs)."""
    out: dict[str, Any] = {}
    previous = compute_threads()
    set_compute_threads(1)
    try:
        for mid in CNN:
            m8 = {v: b.methods[mid] for v, b in int8.items()}
            m32 = fp32.methods[mid]
            assert isinstance(m32, CnnMethod)
            prep = backbone_class(m32.cnn.backbone).preprocessor(m32.cnn.backbone_options)
            assert prep is not None
            layers = sorted(m32.layers())
            net = m32.backbone()
            for size in m32.input_sizes():
                xs = [prep(to_rgb(im), size)[None].astype(np.float32) for im in images]
                runners = {"fp32": onnx_maps(net, layers, size)}
                for v, m in m8.items():
                    assert isinstance(m, CnnMethod) and m.stored_models is not None
                    runners[v] = m.stored_models[size].maps(layers)
                runs: dict[str, list[float]] = {k: [] for k in runners}
                for _ in range(rounds):
                    for k, r in runners.items():
                        runs[k].append(statistics.median(samples_ms(r, xs)))
                out[f"{mid} {size[0]}x{size[1]}"] = {
                    k: {"median_ms": statistics.median(v), "rounds_ms": v} for k, v in runs.items()
                }
    finally:
        set_compute_threads(previous)
    return out


def query_times(
    config: HierarchyConfig, banks: dict[str, ScoreBank], images: int, rounds: int
) -> dict[str, Any]:
    """Whole query (decode + extraction + hierarchy, one thread) per bank, in turn each round."""
    runs: dict[str, list[dict[str, float]]] = {k: [] for k in banks}
    for _ in range(rounds):
        for k, bank in banks.items():
            runs[k].append(measure_query_ms(config, bank, images=images, threads=1))
    return {
        k: {
            "total_ms": statistics.median(r["total_ms"] for r in rs),
            "extract_ms": statistics.median(r["extract_ms"] for r in rs),
            "hierarchy_ms": statistics.median(r["hierarchy_ms"] for r in rs),
            "rounds_total_ms": [r["total_ms"] for r in rs],
        }
        for k, rs in runs.items()
    }


# -- report ------------------------------------------------------------------------------------


def _got(entry: dict[str, Any]) -> float:
    """The variant's recall of a figure (``int8`` in records before runtime variants)."""
    return float(entry["variant"] if "variant" in entry else entry["int8"])


def print_route(route: str, variant: str, fig: dict[str, Any]) -> None:
    print(f"\n{route}, {variant}:", flush=True)
    for mid, r in fig["methods"].items():
        t = r["sign_test"]
        print(
            f"  {mid}: fp32 {r['fp32']:.3f} {variant} {_got(r):.3f} "
            f"({t['wins']} won / {t['losses']} lost, p {t['p']:.3g})",
            flush=True,
        )
    h = fig["hierarchy"]
    for name in SUBSETS:
        t = h[name]["sign_test"]
        print(
            f"  hierarchy, {variant} {name}: fp32 {h['fp32']:.3f} {variant} {_got(h[name]):.3f} "
            f"({t['wins']} won / {t['losses']} lost, p {t['p']:.3g})",
            flush=True,
        )


def recall_table(report: dict[str, Any]) -> list[str]:
    """Markdown table of a JSON record's recall: per route, variant and method, and the
    hierarchy with each subset of its passes in the variant."""
    lines = [
        "| route | variant | method | float32 | in the variant | won / lost | sign test p |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for route, entry in report["routes"].items():
        for variant, fig in entry["variants"].items():
            for mid, r in fig["methods"].items():
                t = r["sign_test"]
                lines.append(
                    f"| {route} | {variant} | {mid} | {r['fp32']:.3f} | {_got(r):.3f} "
                    f"| {t['wins']} / {t['losses']} | {t['p']:.2g} |"
                )
            h = fig["hierarchy"]
            for name in SUBSETS:
                if name not in h:  # a subset this record did not measure
                    continue
                t = h[name]["sign_test"]
                lines.append(
                    f"| {route} | {variant} | hierarchy, variant {name} | {h['fp32']:.3f} "
                    f"| {_got(h[name]):.3f} | {t['wins']} / {t['losses']} | {t['p']:.2g} |"
                )
    return lines


def time_tables(report: dict[str, Any]) -> list[str]:
    """Markdown tables of a JSON record's times: each forward pass, and whole queries."""
    lines: list[str] = []
    if "pass_ms" in report:
        names = list(next(iter(report["pass_ms"].values())))
        lines += ["| forward pass | " + " | ".join(f"{n} ms" for n in names) + " | speed-up |"]
        lines.append("|---|" + "---:|" * (len(names) + 1))
        for k, v in report["pass_ms"].items():
            ups = ", ".join(
                f"{n} {v['fp32']['median_ms'] / v[n]['median_ms']:.2f}x" for n in names[1:]
            )
            cells = " | ".join(f"{v[n]['median_ms']:.1f}" for n in names)
            lines.append(f"| {k} | {cells} | {ups} |")
    if "query_ms" in report:
        q = report["query_ms"]
        if lines:
            lines.append("")
        lines += ["| whole query | total ms | extraction | hierarchy | rounds | speed-up |"]
        lines.append("|---|---:|---:|---:|---|---:|")
        for k, v in q.items():
            rounds = " / ".join(f"{t:.1f}" for t in v["rounds_total_ms"])
            lines.append(
                f"| {k} | {v['total_ms']:.1f} | {v['extract_ms']:.1f} | {v['hierarchy_ms']:.1f} "
                f"| {rounds} | {q['fp32']['total_ms'] / v['total_ms']:.2f}x |"
            )
    return lines


def tables(report: dict[str, Any]) -> list[str]:
    """Markdown tables of a JSON record: recall per route, method and variant; times."""
    times = time_tables(report)
    return recall_table(report) + ([""] + times if times else [])


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--table", type=Path, default=None, help="print the tables of this JSON")
    ap.add_argument("--variants", nargs="+", default=["static"], choices=VARIANTS)
    ap.add_argument("--routes", nargs="+", default=[*GP, NL], choices=[*GP, NL])
    ap.add_argument("--calibration", type=int, default=32, help="reference images calibrating")
    ap.add_argument("--nordland-frames", type=int, default=1000, help="0: the whole route")
    ap.add_argument("--images", type=int, default=20, help="queries timed per round")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds")
    ap.add_argument("--no-time", action="store_true")
    ap.add_argument(
        "--work",
        type=Path,
        default=default_cache_dir().parent / "int8-bench",
        help="int8 models and their features (kept apart from the float32 feature cache)",
    )
    add_cache_dir(ap)
    add_json(ap, "--out", type=Path, default=OUT, help="the JSON record")
    args = ap.parse_args()
    if args.table is not None:
        print("\n".join(tables(json.loads(args.table.read_text()))))
        return 0
    set_cnn_runtime("onnx")
    config = load_config("default")
    print(f"Machine: {machine()}; digest {config.digest()}", flush=True)
    print(f"Load average at start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    prov = provenance("default", config, args)
    report: dict[str, Any] = {
        "load_start": list(os.getloadavg()),
        "nordland_frames": args.nordland_frames,
        "calibration_images": args.calibration,
        "routes": {},
    }

    def save() -> None:
        write_json(args.out, record(report, prov=prov))

    cache = FeatureCache(args.cache_dir)
    timing_banks: dict[str, ScoreBank] = {}
    partial: dict[str, ScoreBank] = {}  # only some passes int8: timed as whole queries
    for route in args.routes:
        data = route_data(route, args.nordland_frames)
        fp32 = bank_of(build_methods(config), data, cache)
        variants: dict[str, Any] = {}
        report["routes"][route] = {
            "references": len(data.reference),
            "queries": len(data.query),
            "variants": variants,
        }
        for variant in args.variants:
            int8, info = int8_bank(config, data, variant, args.calibration, args.work)
            fig = route_figures(config, fp32, int8)
            variants[variant] = {**fig, **info}
            print_route(route, variant, fig)
            save()
            if route == "gp_dr_nr":
                timing_banks[variant] = mixed(fp32, int8, CNN)
                partial[f"{variant}, netvlad only"] = mixed(fp32, int8, ("netvlad",))
        if route == "gp_dr_nr" and {"openvino", "openvino-bf16"} <= set(timing_banks):
            # NetVLAD in OpenVINO float32, GeM and OLO in bfloat16
            partial["openvino, gem+olo in bf16"] = mixed(
                timing_banks["openvino"], timing_banks["openvino-bf16"], ("gem", "olo")
            )
        runtimes = [v for v in args.variants if v in RUNTIME_VARIANTS]
        if runtimes:
            served = served_figures(config, route, data, runtimes, args.work, cache)
            report["routes"][route]["served"] = served
            for v in runtimes:
                t = served[v]["sign_test"]
                print(
                    f"  served (index built in onnx, queries in {v}): onnx {served['onnx']:.3f} "
                    f"{v} {served[v]['variant']:.3f} ({t['wins']} won / {t['losses']} lost, "
                    f"p {t['p']:.3g})",
                    flush=True,
                )
            save()
        if route == "gp_dr_nr":
            timing_banks["fp32"] = fp32
    if not args.no_time and "fp32" in timing_banks:
        fp32 = timing_banks.pop("fp32")
        paths = list(fp32.data.query)
        pick = np.linspace(0, len(paths) - 1, args.images).round().astype(int)
        images = [load_image(paths[i]) for i in pick]
        report["load_before_timing"] = list(os.getloadavg())
        report["pass_ms"] = pass_times(fp32, timing_banks, images, args.rounds)
        report["query_ms"] = query_times(
            config, {"fp32": fp32, **timing_banks, **partial}, args.images, args.rounds
        )
        report["load_after_timing"] = list(os.getloadavg())
        for k, v in report["pass_ms"].items():
            cells = ", ".join(f"{n} {x['median_ms']:.1f}" for n, x in v.items())
            print(f"pass {k}: {cells} ms", flush=True)
        for k, v in report["query_ms"].items():
            print(
                f"query {k}: {v['total_ms']:.1f} ms (extraction {v['extract_ms']:.1f}, "
                f"hierarchy {v['hierarchy_ms']:.1f}; rounds "
                f"{' / '.join(f'{t:.1f}' for t in v['rounds_total_ms'])})",
                flush=True,
            )
    report["load_end"] = list(os.getloadavg())
    save()
    print(f"Load average at end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
