"""Speed of the CNN paths (medians, on this machine).

    python -m bench.cnn_speed [--device cpu|cuda] [--batch 16] [--json F]

* EfficientNet-Lite0 forward per image, batched as for indexing and one image at a time as
  for a query, at every input size the methods use by default, with the inference rewrites
  (BN folding, channels-last) and, for comparison, the package's own model unchanged;
* extraction per image per CNN method (preprocessing + shared forward + descriptor) on real
  Gardens Point images, batched;
* one OLO comparison (200 x 200 regions, IDF words) per candidate pair.

With ``--json`` writes the figures too.
"""

from __future__ import annotations

import statistics
import sys
import time
from typing import Any

import numpy as np
import torch

from bench.harness import add_json, machine, parser, write_record
from bench.harness import timed as median_ms
from hmpf.backbones import load_backbone
from hmpf.datasets import dataset_root, list_images
from hmpf.imageio import load_image
from hmpf.methods import create_method
from hmpf.methods.base import extract_many, fit_many


def main() -> int:
    ap = parser(__doc__)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    add_json(ap)
    args = ap.parse_args()
    print(f"Machine: {machine()}, torch {torch.__version__}, threads {torch.get_num_threads()}")
    print(f"device: {args.device}\n")

    net = load_backbone("efficientnet_lite0", device=args.device)
    # the package's own model, for comparison only: an optional extra (hmpf[cnn])
    from efficientnet_lite_pytorch import EfficientNet

    # beside the optional import above: its bundled weights are for that model
    from hmpf.backbones.efficientnet import bundled_weights

    plain = EfficientNet.from_name("efficientnet-lite0", image_size=None)
    plain.load_state_dict(torch.load(bundled_weights(), map_location="cpu", weights_only=True))
    plain = plain.eval().to(args.device)

    def sync() -> None:
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()

    forward: list[dict[str, Any]] = []
    print("EfficientNet-Lite0 forward (ms per image):")
    for size in [(208, 208), (224, 224), (288, 512)]:
        xb = torch.randn(args.batch, 3, *size, device=args.device)
        x1 = xb[:1]
        with torch.inference_mode():

            def ours(x=xb) -> None:
                net.forward_maps(x, ["head"])
                sync()

            def theirs(x=xb) -> None:
                plain.extract_features(x)
                sync()

            def single(x=x1) -> None:
                net.forward_maps(x, ["head"])
                sync()

            b = median_ms(ours, args.repeats) / args.batch
            p = median_ms(theirs, args.repeats) / args.batch
            s = median_ms(single, args.repeats * 3)
        print(
            f"  {size[0]}x{size[1]}: batched {b:6.1f} (package model unchanged {p:6.1f}, "
            f"ratio {p / b:.2f}x); single image {s:6.1f}"
        )
        forward.append(
            {
                "size": list(size),
                "batched_ms": float(b),
                "package_batched_ms": float(p),
                "single_ms": float(s),
            }
        )

    paths = list_images(dataset_root() / "gardens_point" / "day_right")
    images = [load_image(p) for p in paths[:48]]
    methods = {
        "gem": create_method("gem", {"device": args.device}),
        "netvlad": create_method("netvlad", {"device": args.device}),
        "hybridnet": create_method("hybridnet", {"device": args.device}),
        "olo": create_method("olo", {"device": args.device}),
    }
    t = time.perf_counter()
    fit_many(methods, images[:32])
    fit_s = time.perf_counter() - t
    print(f"\nfitting netvlad + olo on 32 references: {fit_s:.1f} s")
    print("extraction per 960x540 image, batched (median ms; forward shared within a group):")
    extract_ms: dict[str, dict[str, Any]] = {}
    for mid, m in methods.items():
        ms: dict[str, list[float]] = {}
        extract_many({mid: m}, images[:16])
        extract_many({mid: m}, images[16:48], ms)
        med, inp = float(statistics.median(ms[mid])), m.input_size()
        print(f"  {mid:9s} {med:6.1f}  (input {inp})")
        extract_ms[mid] = {"ms": med, "input": str(inp)}

    olo = methods["olo"]
    feats = extract_many({"olo": olo}, images[:40])["olo"]
    refs = olo.stack(feats[1:])
    n_reg = np.mean([len(f) for f in feats])
    per = median_ms(lambda: olo.scores(feats[0], refs), args.repeats * 4) / len(refs)
    print(f"\nOLO comparison: {per:.3f} ms per pair ({n_reg:.0f} regions per image on average)")
    if args.json:
        results = {
            "torch": torch.__version__,
            "device": args.device,
            "threads": int(torch.get_num_threads()),
            "batch": args.batch,
            "forward": forward,
            "fit_s": fit_s,
            "extract_ms": extract_ms,
            "olo_compare_ms": float(per),
            "olo_regions_mean": float(n_reg),
        }
        print(f"report: {write_record(args.json, results, args)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
