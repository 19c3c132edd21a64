"""The CNN methods on a CUDA device against the CPU (torch runtime on both).

    python -m bench.cuda_check --images DIR --json results/cuda_check.json

``DIR`` holds ``ref/*.jpg`` and ``query/*.jpg`` (docs/experiments/cuda/ used every 12th
Gardens Point day_right and night_right frame, 16 each). Cases: every CNN method (gem, netvlad,
olo, hybridnet; gem with R-MAC crops) on the bundled EfficientNet-Lite0, and the paper's
backbones (VGG16 + NetVLAD, VGG-M-1024 for OLO, CaffeNet for HybridNet) on synthetic weight
files of the published layouts, written by the weight tests' own writers
(``tests/hmpf/methods/test_backbones_weights.py``). Each case is fitted where the method fits
and describes the queries and references on each device, three times:

1. as shipped (a backbone on CUDA turns TF32 off, :func:`hmpf.backbones.base.full_float32_on`),
   fitted on each device;
2. as shipped, the CUDA method loaded with the CPU's fitted state;
3. TF32 forced back on (PyTorch's default for cuDNN convolutions), the CPU's fitted state: the
   control.

Per case: the largest relative descriptor difference (integer arrays, such as OLO's word ids:
the share that differ), the fitted states' difference, the score matrices' difference, how
many queries have the same top-1 reference, and the time per image (batched; median of 3).
``--device cpu`` compares the CPU with itself (a dry run of this script, no GPU needed).
"""

from __future__ import annotations

import glob
import importlib.util
import statistics
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch

from bench.harness import ROOT, add_json, parser, write_record
from hmpf import runtime
from hmpf.backbones import load_backbone
from hmpf.imageio import load_image
from hmpf.methods.base import extract_many, fit_many
from hmpf.methods.registry import create_method


def weight_writers() -> ModuleType:
    """The synthetic weight files' writers of the backbone weight tests."""
    pattern = str(ROOT / "tests" / "**" / "test_backbones_weights.py")
    spec = importlib.util.spec_from_file_location(
        "weights_writers", glob.glob(pattern, recursive=True)[0]
    )
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def arrays(feature: Any) -> dict[str, np.ndarray]:
    """A feature's arrays: the array itself, or a dataclass / named tuple's fields."""
    if isinstance(feature, np.ndarray):
        return {"": feature}
    items = feature._asdict() if hasattr(feature, "_asdict") else vars(feature)
    return {k: np.asarray(v) for k, v in items.items()}


def rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| / max |a| (inf when the shapes differ)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        return float("inf")
    if not a.size:
        return 0.0
    return float(np.abs(a - b).max()) / max(float(np.abs(a).max()), 1e-12)


def feature_diff(x: Any, y: Any) -> float:
    """Float arrays: :func:`rel_diff`; integer arrays: the share of entries that differ."""
    ax, ay = arrays(x), arrays(y)
    out = [0.0]
    for k, v in ax.items():
        if v.dtype.kind == "f":
            out.append(rel_diff(v, ay[k]))
        elif v.dtype.kind in "iu":
            out.append(float(np.mean(v != ay[k])) if v.shape == ay[k].shape else float("inf"))
    return max(out)


def describe(name: str, params: dict, device: str, refs: list, queries: list, state: Any) -> dict:
    """Fit (or load ``state``), describe the references and the queries (timed) on ``device``."""
    m = create_method(name, {**params, "device": device})
    t0 = time.perf_counter()
    if m.requires_fit():
        if state is not None:
            m.load_state(state)
        else:
            fit_many({name: m}, refs)
    fit_s = time.perf_counter() - t0
    ref = extract_many({name: m}, refs)[name]
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        query = extract_many({name: m}, queries)[name]
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    matrix = m.stack_references(ref)
    scores = np.stack([m.scores(q, matrix) for q in query])
    return {
        "method": m,
        "features": list(query) + list(ref),
        "scores": scores,
        "ms_per_image": 1000 * statistics.median(times) / len(queries),
        "fit_s": fit_s,
    }


def run_case(name: str, params: dict, device: str, refs: list, queries: list, share: bool) -> dict:
    """One method on the CPU and on ``device``: the differences and times."""
    cpu = describe(name, params, "cpu", refs, queries, None)
    state = cpu["method"].state_arrays() if share else None
    dev = describe(name, params, device, refs, queries, state)
    sc, sd = cpu["method"].state_arrays(), dev["method"].state_arrays()
    return {
        "method": name,
        "params": {k: v for k, v in params.items() if k != "weights"},
        "share_state": share,
        "tf32": bool(torch.backends.cudnn.allow_tf32 or torch.backends.cuda.matmul.allow_tf32),
        "state_keys": sorted(sc),
        "state_rel_diff": max((rel_diff(sc[k], sd[k]) for k in sc), default=0.0),
        "descriptor_rel_diff_max": max(
            feature_diff(a, b) for a, b in zip(cpu["features"], dev["features"], strict=True)
        ),
        "score_rel_diff": rel_diff(cpu["scores"], dev["scores"]),
        "top1_agree": int((cpu["scores"].argmax(1) == dev["scores"].argmax(1)).sum()),
        "queries": len(queries),
        "ms_per_image_cpu": round(cpu["ms_per_image"], 2),
        "ms_per_image_device": round(dev["ms_per_image"], 2),
        "fit_s_cpu": round(cpu["fit_s"], 2),
        "fit_s_device": round(dev["fit_s"], 2),
    }


def cases(weights: Path) -> list[tuple[str, dict[str, Any]]]:
    """The methods checked; the paper backbones' synthetic weight files written to ``weights``."""
    writers = weight_writers()
    caffe, vggm, pitts = (weights / n for n in ("HybridNet.caffemodel", "vggm.mat", "pitts.mat"))
    writers._write_caffemodel(caffe)
    writers._write_vggm(vggm)
    layers, _ = writers._pitts_layers(np.random.default_rng(0))
    writers._save_pitts(pitts, layers)
    return [
        ("gem", {}),
        ("netvlad", {}),
        ("olo", {}),
        ("hybridnet", {}),
        ("gem", {"crops": 2}),
        ("netvlad", {"backbone": "vgg16", "weights": str(pitts)}),
        ("olo", {"backbone": "vgg_m_1024", "weights": str(vggm)}),
        ("hybridnet", {"backbone": "caffenet", "weights": str(caffe)}),
    ]


def raw_maps(device: str, queries: list) -> dict[str, dict[str, float]]:
    """The bundled backbone's maps of one batch, CPU against ``device``, TF32 off and on."""
    out = {}
    cpu, dev = (
        load_backbone("efficientnet_lite0", None, "cpu"),
        load_backbone("efficientnet_lite0", None, device),
    )
    x = torch.from_numpy(np.stack([cpu.preprocess(im, (224, 224)) for im in queries]))
    for tf32 in (False, True):
        torch.backends.cudnn.allow_tf32 = tf32
        with torch.inference_mode():
            a = cpu.forward_maps(x, ["s5", "head"])
            b = dev.forward_maps(x.to(device), ["s5", "head"])
        out[f"tf32_{tf32}"] = {k: rel_diff(a[k].numpy(), b[k].float().cpu().numpy()) for k in a}
    return out


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--images", required=True, help="a folder with ref/*.jpg and query/*.jpg")
    ap.add_argument("--device", default="cuda")
    add_json(ap)
    args = ap.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("no CUDA device (--device cpu compares the CPU with itself)")
    runtime.set_cnn_runtime("torch")
    refs = [load_image(p) for p in sorted(Path(args.images, "ref").glob("*.jpg"))]
    queries = [load_image(p) for p in sorted(Path(args.images, "query").glob("*.jpg"))]
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        checked = cases(Path(tmp))
        # rounds 1-2 as shipped, round 3 with TF32 forced on after the backbones loaded
        plan = [(False, None), (True, None), (True, True)]
        for share, tf32 in plan:
            for name, params in checked:
                if tf32 is not None:
                    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = tf32
                try:
                    r = run_case(name, params, args.device, refs, queries, share)
                except Exception as exc:  # every case is reported, not just the first failure
                    r = {"method": name, "params": params, "error": f"{type(exc).__name__}: {exc}"}
                results.append(r)
                print(r, flush=True)
    raw = raw_maps(args.device, queries)
    print({"raw_maps_rel_diff": raw})
    if args.json:
        write_record(
            args.json,
            {
                "device": torch.cuda.get_device_name(0) if args.device != "cpu" else "cpu",
                "torch": torch.__version__,
                "cpu_threads": torch.get_num_threads(),
                "images": {"reference": len(refs), "query": len(queries)},
                "raw_maps_rel_diff": raw,
                "cases": results,
            },
            args,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
