"""NetVLAD (method id 6): soft-assignment VLAD over a CNN's local features.

Spec §2.5 (docs/spec/netvlad.md). Two ways to get its parameters:

* ``vgg16`` with the Pitts30k weights (``Pitts30K_struct.mat``): the exact published pipeline
  ``vd16_pitts30k_conv5_3_vlad_preL2_intra_white``: conv5_3 (no ReLU) of the 224 x 224 input,
  preL2 per local descriptor, soft-assignment (1x1 conv without bias, softmax over K = 64),
  residual aggregation ``V[k, d] = sum_i a_ik (x_id - c_kd)``, intra-normalisation, flattening
  with k fastest, L2, WPCA to 4096 and a final L2. The parameters come from the weight file.
* ``efficientnet_lite0`` (default, an unsupervised VLAD): the same layer on stage 6 (``s6``,
  192-d local features at stride 32 of a 288 x 512 input, 9 x 16 = 144 descriptors; it beat
  stage 5 on Gardens Point day_left -> night_right, 0.49 vs 0.39 recall@1). Its K
  centroids are fitted by k-means on the reference images' (preL2) local features; the
  assignment is ``softmax_k(-alpha |x - c_k|^2)`` with ``alpha = -ln(0.01) / mean(d2 - d1)``
  over the fitting features (d1, d2: squared distances to the two nearest centroids), the
  NetVLAD initialisation. With ``pca_dim`` set, a PCA-whitening fitted on the references'
  VLAD vectors reduces the descriptor (then L2 again). The fitted parameters are stored with
  the index and never refitted for a query.
* ``efficientnet_lite1`` / ``efficientnet_lite2``: the same on their stage 6 (192-d / 208-d)
  at 320 x 544 / 352 x 608 (Lite0's input scaled by the variants' ImageNet sizes).

With ``scales`` (a lever: multi-scale pooling; :class:`~hmpf.methods.cnn.MultiScaleConfig`)
the local features of every input scale are pooled into one VLAD (and the centroids fitted on
all of them).

Distance: Euclidean, lower is better.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import ClassVar

import numpy as np
from pydantic import Field

from hmpf.methods.base import DbaConfig, GlobalMethod, MetricSpec, euclidean
from hmpf.methods.cnn import CnnConfig, CnnMethod, MultiScaleConfig, kmeans, l2_rows
from hmpf.methods.kaze import half
from hmpf.methods.registry import register

DEFAULTS = {
    "vgg16": ("conv5_3", (224, 224)),
    "efficientnet_lite0": ("s6", (288, 512)),
    # Lite0's choice scaled to the variants' ImageNet sizes (240 / 224, 260 / 224), in whole
    # stride-32 cells: 10 x 17 and 11 x 19 local features.
    "efficientnet_lite1": ("s6", (320, 544)),
    "efficientnet_lite2": ("s6", (352, 608)),
}


def vlad(
    x: np.ndarray,
    centroids: np.ndarray,
    assign: np.ndarray,
    bias: np.ndarray | None = None,
) -> np.ndarray:
    """NetVLAD core on one image's local features, intra-normalised and L2-normalised.

    Args:
        x: (n, D) preL2-normalised local descriptors.
        centroids: (K, D) cluster centres.
        assign: (D, K) soft-assignment weights (logits = x @ assign + bias).
        bias: (K,) or None.

    Returns:
        (K * D,) float32, flattened with k fastest (index ``k + K * d``), unit norm.
    """
    logits = x @ assign
    if bias is not None:
        logits = logits + bias
    logits = logits - logits.max(axis=1, keepdims=True)
    a = np.exp(logits)
    a /= a.sum(axis=1, keepdims=True)  # (n, K)
    v = a.T @ x - a.sum(axis=0)[:, None] * centroids  # (K, D)
    v = l2_rows(v)  # intra-normalisation
    flat = v.T.reshape(-1)  # (D, K) in C order: k fastest
    return l2_rows(flat[None])[0]


class NetVladConfig(MultiScaleConfig, DbaConfig):
    layer: str | None = Field(None, description="local-feature map; None = backbone default")
    clusters: int = Field(64, ge=2, le=1024, description="K (fitted backbones only)")
    pca_dim: int | None = Field(
        None, ge=2, description="PCA-whitening output size (fitted backbones only)"
    )
    fit_features_per_image: int = Field(300, ge=10, description="local features sampled")
    seed: int = 0


@register
class NetVlad(CnnMethod, GlobalMethod):
    name = "netvlad"
    higher_is_better = False
    version = "2"  # 2: float16-precision descriptors
    Config: ClassVar[type[CnnConfig]] = NetVladConfig
    dim = 0

    def __init__(self, config: NetVladConfig | None = None) -> None:
        super().__init__(config)
        self._state: dict[str, np.ndarray] = {}

    @property
    def nv(self) -> NetVladConfig:
        return self.config  # type: ignore[return-value]

    @property
    def published(self) -> bool:
        """True on the original Pitts30k weights (parameters from the file, nothing fitted)."""
        return self.nv.backbone == "vgg16"

    def _default(self) -> tuple[str, tuple[int, int]]:
        if self.nv.backbone not in DEFAULTS:
            raise ValueError(f"netvlad has no default layer for backbone {self.nv.backbone!r}")
        return DEFAULTS[self.nv.backbone]

    def layers(self) -> list[str]:
        return [self.nv.layer or self._default()[0]]

    def default_input_size(self) -> tuple[int, int]:
        return self._default()[1]

    # -- fitted parameters --------------------------------------------------------------------
    def requires_fit(self) -> bool:
        return not self.published and "centroids" not in self._state

    def state_arrays(self) -> dict[str, np.ndarray]:
        return dict(self._state)

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        if self.published:
            raise ValueError("netvlad on vgg16 takes its parameters from the weight file")
        missing = {"centroids", "alpha"} - set(arrays)
        if missing:
            raise ValueError(f"netvlad state lacks {sorted(missing)}")
        self._state = {k: np.asarray(v) for k, v in arrays.items()}

    def _local(self, maps: Mapping[str, np.ndarray]) -> np.ndarray:
        """PreL2 local features, (sum of h*w over the scales, C)."""
        layer = self.layers()[0]
        per = [m[layer].reshape(m[layer].shape[0], -1).T for m in self.scale_maps(maps)]
        return l2_rows(per[0] if len(per) == 1 else np.concatenate(per))

    def fit_from_maps(self, samples: Sequence[Mapping[str, np.ndarray]]) -> None:
        cfg = self.nv
        rng = np.random.default_rng(cfg.seed)
        feats = []
        for maps in samples:
            x = self._local(maps)
            take = min(len(x), cfg.fit_features_per_image)
            feats.append(x[np.sort(rng.choice(len(x), take, replace=False))])
        x = np.concatenate(feats)
        c = kmeans(x, cfg.clusters, seed=cfg.seed)
        d2 = np.sort(
            np.maximum((x * x).sum(1)[:, None] + (c * c).sum(1)[None] - 2 * x @ c.T, 0), axis=1
        )
        gap = float(np.mean(d2[:, 1] - d2[:, 0])) if c.shape[0] > 1 else 1.0
        alpha = -np.log(0.01) / max(gap, 1e-12)
        self._state = {
            "centroids": c.astype(np.float32),
            "alpha": np.array(alpha, dtype=np.float32),
        }
        if cfg.pca_dim is not None:
            v = np.stack([self._raw_vlad(maps) for maps in samples]).astype(np.float64)
            mean = v.mean(axis=0)
            _, s, vt = np.linalg.svd(v - mean, full_matrices=False)
            p = min(cfg.pca_dim, len(s))
            var = s[:p] ** 2 / max(1, len(v) - 1)
            proj = vt[:p].T / np.sqrt(var + 1e-9 * var.max())
            self._state.update(
                {"pca_mean": mean.astype(np.float32), "pca_proj": proj.astype(np.float32)}
            )

    def _params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(centroids (K, D), assign (D, K), bias (K,) or None)."""
        if self.published:
            p = self.backbone().netvlad_params()  # type: ignore[attr-defined]
            return p["centroids"], p["assign"], None
        if "centroids" not in self._state:
            raise RuntimeError("netvlad is not fitted: run fit_methods on the references first")
        c, alpha = self._state["centroids"], float(self._state["alpha"])
        # -alpha |x - c|^2 = alpha (2 x.c - |c|^2) - alpha |x|^2; the last term cancels.
        return c, (2 * alpha * c).T, -alpha * (c * c).sum(axis=1)

    def _raw_vlad(self, maps: Mapping[str, np.ndarray]) -> np.ndarray:
        c, assign, bias = self._params()
        return vlad(self._local(maps), c, assign, bias)

    def from_maps(self, maps: Mapping[str, np.ndarray]) -> np.ndarray:
        """The descriptor, at float16 precision (what the index stores)."""
        v = self._raw_vlad(maps)
        if self.published:
            p = self.backbone().netvlad_params()  # type: ignore[attr-defined]
            v = l2_rows((v @ p["wpca_w"] + p["wpca_b"])[None])[0]
        elif "pca_proj" in self._state:
            v = l2_rows(((v - self._state["pca_mean"]) @ self._state["pca_proj"])[None])[0]
        return half(v)

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        return euclidean(queries, references)

    def faiss_metric(self) -> MetricSpec:
        return MetricSpec("l2", 1.0)
