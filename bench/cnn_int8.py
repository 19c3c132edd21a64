"""Lower precision for the backbone: int8 EfficientNet-Lite0 in ONNX Runtime against float32.

    python -m bench.cnn_int8 [--size 288 512] [--images 20] [--calibration 32]

The float32 model is the default runtime's cached export (the layers the default hierarchy
reads, at ``--size``). Two int8 variants from ``onnxruntime.quantization``:

* ``dynamic``: weights int8, activations quantised per run (``quantize_dynamic``);
* ``static``: weights and activations int8 (QDQ, per-channel weights), activation ranges
  calibrated on ``--calibration`` Gardens Point day_left images (not the timed ones).

For each: median ms per image on one thread (preprocessing excluded, same images, one run,
float32 timed between them), and how far the maps move: relative L2 error of every layer,
and the cosine similarity of the GeM descriptor (the mean-pooled ``head`` map cubed-rooted,
as GeM with p = 3) to float32's, over the timed day_right images.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import onnxruntime
from onnxruntime.quantization import (
    CalibrationDataReader,
    QuantFormat,
    QuantType,
    quantize_dynamic,
    quantize_static,
)

from bench.harness import machine, median_ms, parser
from hmpf.config import build_methods, load_config
from hmpf.datasets import dataset_root, list_images
from hmpf.imageio import load_image, to_rgb
from hmpf.methods.cnn import CnnMethod
from hmpf.runtime import set_compute_threads


class Images(CalibrationDataReader):
    def __init__(self, name: str, batches: list[np.ndarray]) -> None:
        self.items = iter([{name: b} for b in batches])

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self.items, None)


def session(path: Path) -> onnxruntime.InferenceSession:
    opts = onnxruntime.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    return onnxruntime.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def session_ms(sess: onnxruntime.InferenceSession, xs: list[np.ndarray]) -> float:
    """Median ms of one ``sess.run`` per input of ``xs``, after a warm-up run."""
    name = sess.get_inputs()[0].name
    return median_ms(lambda x: sess.run(None, {name: x}), xs)


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--size", type=int, nargs=2, default=(288, 512))
    ap.add_argument("--images", type=int, default=20)
    ap.add_argument("--calibration", type=int, default=32)
    args = ap.parse_args()
    set_compute_threads(1)
    onnxruntime.set_default_logger_severity(3)  # the quantiser's notes on unused constants
    from hmpf.backbones.onnx_runtime import onnx_maps

    methods = [m for m in build_methods(load_config("default")).values()]
    cnn = [m for m in methods if isinstance(m, CnnMethod)]
    net = cnn[0].backbone()
    size = (int(args.size[0]), int(args.size[1]))
    layers = sorted({layer for m in cnn for layer in m.layers()})
    fp32_path = onnx_maps(net, layers, size).path
    gp = dataset_root() / "gardens_point"
    timed = list_images(gp / "day_right")
    pick = np.linspace(0, len(timed) - 1, args.images).round().astype(int)
    xs = [net.preprocess(to_rgb(load_image(timed[i])), size)[None] for i in pick]
    calib = list_images(gp / "day_left")[:: max(1, 200 // args.calibration)][: args.calibration]
    cs = [net.preprocess(to_rgb(load_image(p)), size)[None] for p in calib]
    print(f"Machine: {machine()}; onnxruntime {onnxruntime.__version__}")
    print(f"EfficientNet-Lite0 at {size[0]} x {size[1]}, layers {', '.join(layers)}\n")
    base = session(fp32_path)
    name = base.get_inputs()[0].name
    ref = [base.run(None, {name: x}) for x in xs]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        dyn = Path(tmp) / "dynamic.onnx"
        quantize_dynamic(str(fp32_path), str(dyn), weight_type=QuantType.QInt8)
        static = Path(tmp) / "static.onnx"
        quantize_static(
            str(fp32_path),
            str(static),
            Images(name, cs),
            quant_format=QuantFormat.QDQ,
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
        )
        for label, path in (("dynamic", dyn), ("static", static)):
            sess = session(path)
            t32, t8 = session_ms(base, xs), session_ms(sess, xs)
            out = [sess.run(None, {name: x}) for x in xs]
            errs = []
            for li, layer in enumerate(layers):
                e = [
                    np.linalg.norm(o[li] - r[li]) / max(np.linalg.norm(r[li]), 1e-12)
                    for o, r in zip(out, ref, strict=True)
                ]
                errs.append(f"{layer} {np.median(e):.3f}")
            head = layers.index("head") if "head" in layers else 0
            cos = []
            for o, r in zip(out, ref, strict=True):
                a = np.cbrt(np.mean(np.maximum(o[head][0], 0) ** 3, axis=(1, 2)))
                b = np.cbrt(np.mean(np.maximum(r[head][0], 0) ** 3, axis=(1, 2)))
                cos.append(float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12)))
            rows.append((label, t32, t8, "; ".join(errs), float(np.min(cos))))
    print(
        "| int8 variant | float32 ms | int8 ms | speed-up | median relative L2 error | "
        "min GeM cosine |"
    )
    print("|---|---:|---:|---:|---|---:|")
    for label, t32, t8, errs, cos in rows:
        print(f"| {label} | {t32:.1f} | {t8:.1f} | {t32 / t8:.2f}x | {errs} | {cos:.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
