"""What methods declare, checked against what they do: the FAISS metric of every global method
(against a detection on real descriptors), the index build's use of it, and the extraction
capabilities (batched, grouped) that :mod:`hmpf.features` reads instead of method types."""

from __future__ import annotations

import signal
from collections.abc import Hashable, Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
import pytest

from hmpf.config import parse_config
from hmpf.datasets import list_images
from hmpf.features import extract_images, extract_query, fit_methods
from hmpf.index import IndexBuildError, IndexReader
from hmpf.methods import (
    GlobalMethod,
    Method,
    MethodConfig,
    available_methods,
    create_method,
    get_method_class,
)
from hmpf.methods.base import GroupOutput, MetricSpec, euclidean
from hmpf.methods.cnn import CnnMethod
from tests.conftest import synthetic_image

# -- the detection, kept as the check of every declaration --------------------------------------


def detect_metric(method: GlobalMethod, matrix: np.ndarray, rows: int = 32) -> MetricSpec | None:
    """The FAISS metric reproducing ``method.pairwise`` on up to ``rows`` of ``matrix``'s rows
    (evenly spaced), up to a least-squares scale, or None when none does."""
    step = max(1, matrix.shape[0] // rows)
    sample = np.asarray(matrix[::step][:rows])
    scores = np.asarray(method.pairwise(sample, sample), dtype=np.float64)
    x = sample.astype(np.float64)
    d = x[:, None, :] - x[None, :, :]
    candidates = {"l2": np.sqrt((d * d).sum(-1)), "l1": np.abs(d).sum(-1), "ip": x @ x.T}
    for kind, cand in candidates.items():
        denom = float((cand * cand).sum())
        if denom == 0.0:
            continue
        scale = float((scores * cand).sum() / denom)
        tol = 1e-4 * max(1e-12, float(np.abs(scores).max()))
        if scale == 0.0 or not np.allclose(scores, scale * cand, rtol=1e-4, atol=tol):
            continue
        # FAISS ranks l2 / l1 ascending and ip descending: the method must agree.
        ascending = (kind != "ip") == (scale > 0)
        if ascending == method.higher_is_better:
            continue
        return MetricSpec(kind, scale)  # type: ignore[arg-type]
    return None


def _assert_declared(method: GlobalMethod, matrix: np.ndarray) -> None:
    declared, detected = method.faiss_metric(), detect_metric(method, matrix)
    if declared is None:
        assert detected is None, f"{method.name} declares no metric but its scores are {detected}"
        return
    assert detected is not None, f"{method.name} declares {declared}; its scores are no metric"
    assert (detected.kind, detected.proxy) == (declared.kind, declared.proxy), method.name
    assert detected.scale == pytest.approx(declared.scale, rel=1e-9), method.name


def test_detection_on_synthetic_vectors() -> None:
    rng = np.random.default_rng(0)
    x = rng.random((20, 64)).astype(np.float32)
    gist = create_method("gist")
    assert isinstance(gist, GlobalMethod)
    assert detect_metric(gist, x) == MetricSpec("l2", pytest.approx(1.0))  # type: ignore[arg-type]
    sad = create_method("sad")
    assert isinstance(sad, GlobalMethod)
    spec = detect_metric(sad, rng.integers(0, 256, (20, sad.dim), dtype=np.uint8))
    assert spec is not None and spec.kind == "l1" and spec.scale == pytest.approx(1 / sad.dim)


#: hmpf's own methods (other test modules register toy ones).
BUILT_IN = sorted(
    n for n in available_methods() if get_method_class(n).__module__.startswith("hmpf.")
)
GLOBAL = [name for name in BUILT_IN if get_method_class(name).kind == "global"]
VARIANTS = {"sad": [{}, {"faithful": True}], "netvlad": [{"clusters": 8}]}


@pytest.mark.dataset
@pytest.mark.parametrize(
    ("name", "params"),
    [(name, params) for name in GLOBAL for params in VARIANTS.get(name, [{}])],
)
def test_declared_metric_equals_detection_on_real_descriptors(
    gardens_point: Path, name: str, params: dict[str, Any]
) -> None:
    paths = list_images(gardens_point / "day_left")[::25]
    method = create_method(name, params)
    assert isinstance(method, GlobalMethod)
    fit_methods({name: method}, paths)
    feats = extract_images(paths, {name: method}, workers=1).features[name]
    _assert_declared(method, method.stack(feats))


def test_every_registered_global_method_is_checked() -> None:
    assert {"gem", "gist", "hog", "hybridnet", "netvlad", "sad"} <= set(GLOBAL)
    for name in GLOBAL:
        create_method(name).faiss_metric()  # declared: does not raise


# -- the index build uses the declaration ----------------------------------------------------


class _Config(MethodConfig):
    dim: int = 4


class _Undeclared(GlobalMethod):
    """A Euclidean global method that does not declare its FAISS metric."""

    name = "undeclared_metric_test"
    Config: ClassVar[type[MethodConfig]] = _Config
    dim = 4

    def _extract(self, image: np.ndarray) -> np.ndarray:
        return np.append(image.reshape(-1, 3).mean(0), 1.0).astype(np.float32)

    def pairwise(self, queries: np.ndarray, references: np.ndarray) -> np.ndarray:
        return euclidean(queries, references)


def _write_images(folder: Path, n: int) -> Path:
    folder.mkdir()
    for i in range(n):
        cv2.imwrite(str(folder / f"img{i:03d}.png"), synthetic_image(i)[:, :, ::-1])
    return folder


def test_build_refuses_a_tier1_method_without_a_declared_metric(tmp_path, monkeypatch) -> None:
    from hmpf.methods import registry
    from indexer.build import BuildOptions, build

    monkeypatch.setitem(registry._REGISTRY, _Undeclared.name, _Undeclared)
    cfg = parse_config({"tiers": [{"methods": [_Undeclared.name, "sad"], "k": 1}]})
    images = _write_images(tmp_path / "img", 3)
    opts = BuildOptions(workers=1, progress=False)
    with pytest.raises(IndexBuildError, match="declares no FAISS metric.*faiss_metric"):
        build(cfg, images, tmp_path / "index", options=opts)
    # Refused up front: no work folder, so no image was fitted or extracted.
    assert not (tmp_path / "index" / ".build").exists()


def test_build_refuses_an_approximate_factory_without_a_metric_before_any_work(tmp_path) -> None:
    from indexer.build import BuildOptions, build

    cfg = parse_config(
        {"methods": {"sad": {"faithful": True}}, "tiers": [{"methods": ["sad", "hog"], "k": 1}]}
    )
    images = _write_images(tmp_path / "img", 3)
    opts = BuildOptions(workers=1, progress=False, faiss={"sad": "IVF2,Flat"})
    with pytest.raises(IndexBuildError, match="'sad' has no FAISS metric.*IVF2,Flat"):
        build(cfg, images, tmp_path / "index", options=opts)
    assert not (tmp_path / "index" / ".build").exists()


def test_build_records_the_declared_metric_even_where_detection_fails(tmp_path) -> None:
    # One reference: a fit on the stored rows cannot tell the metric (it stored none before).
    from indexer.build import BuildOptions, build

    cfg = parse_config({"tiers": [{"methods": ["hog", "sad"], "k": 1}]})
    images = _write_images(tmp_path / "img", 1)
    build(cfg, images, tmp_path / "index", options=BuildOptions(workers=1, progress=False))
    with IndexReader(tmp_path / "index") as reader:
        hog, sad = reader.faiss_info("hog"), reader.faiss_info("sad")
    assert hog is not None and hog["metric"] == {"kind": "l2", "scale": 1.0, "proxy": False}
    assert sad is not None and sad["metric"] == {"kind": "l1", "scale": 1 / 2048, "proxy": False}


# -- extraction capabilities ---------------------------------------------------------------


def test_cnn_methods_declare_batched_and_grouped() -> None:
    for name in BUILT_IN:
        m = create_method(name)
        assert m.batched == isinstance(m, CnnMethod), name
        assert (m.group_key() is not None) == isinstance(m, CnnMethod), name


class _Toy(Method):
    """A method of one-value features that is only extracted, never scored."""

    kind = "global"

    def scores(self, query: Any, references: Any, subset: np.ndarray | None = None) -> np.ndarray:
        raise NotImplementedError

    def stack(self, features: Sequence[Any]) -> Any:
        return np.stack(features)


class _Batched(_Toy):
    """A non-CNN batched, grouped method: features read what it declares, not its type."""

    name = "batched_test"
    batched = True
    calls: ClassVar[list[tuple[str, ...]]] = []

    @property
    def batch_size(self) -> int:
        return 2

    def group_key(self) -> Hashable:
        return ("batched_test",)

    def _extract(self, image: np.ndarray) -> np.ndarray:
        return np.array([float(image.mean())])

    @classmethod
    def extract_group(
        cls, methods: Mapping[str, Method], images: Sequence[np.ndarray]
    ) -> GroupOutput:
        cls.calls.append(tuple(methods))
        feats = {mid: [np.array([float(im.mean())]) for im in images] for mid in methods}
        own = {mid: [1.0] * len(images) for mid in methods}
        return GroupOutput(feats, own, [10.0] * len(images))


def test_batched_grouped_method_runs_in_process_in_batches(tmp_path: Path) -> None:
    paths = list_images(_write_images(tmp_path / "img", 5))
    _Batched.calls.clear()
    res = extract_images(paths, {"a": _Batched(), "b": _Batched()}, workers=2)
    assert _Batched.calls == [("a", "b")] * 3  # batches of 2, 2, 1; one call per batch
    assert np.allclose(res.ms["a"], 11.0) and np.allclose(res.ms["b"], 11.0)
    ms: dict[str, float] = {}
    extract_query({"a": _Batched(), "b": _Batched()}, synthetic_image(1), ms)
    assert ms == {"a": 11.0, "b": 1.0}  # the shared pass is counted once


class _SigintProbe(_Toy):
    """Its feature is whether the process extracting it ignores Ctrl-C."""

    name = "sigint_probe_test"

    def _extract(self, image: np.ndarray) -> np.ndarray:
        return np.array([signal.getsignal(signal.SIGINT) == signal.SIG_IGN])


def test_pool_workers_leave_ctrl_c_to_the_parent(tmp_path: Path) -> None:
    paths = list_images(_write_images(tmp_path / "img", 4))
    # The parent stops on Ctrl-C as on a terminal (a background job inherits SIGINT ignored).
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        res = extract_images(paths, {"p": _SigintProbe()}, workers=2)
        assert all(bool(f[0]) for f in res.features["p"])  # the workers ignore it
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # not the parent
    finally:
        signal.signal(signal.SIGINT, before)
