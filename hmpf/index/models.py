"""The exported inference models a version carries (``onnx/``), so that serving needs no torch.

A build exports each CNN forward-pass group (methods sharing a backbone, its weights and an
input size: :func:`hmpf.methods.base.method_groups`) to ONNX, one model per input size with
one output per map its methods read, into the version folder::

    v0001/onnx/efficientnet_lite0-224x224-<key>.onnx

The models are the ones the build's extraction ran (:func:`hmpf.backbones.onnx_runtime.
export_model`: a copy of the exported model, keyed by the weights, layers, input size and
exporter versions), listed in the manifest's ``models`` and, like every file of a version,
in its ``files`` with their sha256 (``hmpf-index verify`` and every reader check them). A
version derived from another (``add``, ``remove``) copies its parent's models instead of
exporting: the stored descriptors and new queries keep coming from the same model.

A reader attaches the models to its methods (:meth:`hmpf.methods.cnn.CnnMethod.
use_stored_models`), and queries then run them in ONNX Runtime alone: torch is not imported
(``pip install 'hmpf[serve]'`` serves). Backbones that do not export (``vgg16``, ``caffenet``,
``vgg_m_1024``: :attr:`~hmpf.backbones.base.Backbone.onnx` False) and methods on a non-CPU
device store no model and run in torch, as do versions built before models were stored
(torch is then needed to serve them; without it the first query says to rebuild).

Manifest entry (``models``, a list)::

    {"file": "onnx/....onnx", "format": "onnx", "backbone": "efficientnet_lite0",
     "input_size": [224, 224], "layers": ["head", "s5"], "methods": ["gem", "olo"],
     "export_key": "...", "opset": 17, "exporter": {"torch": "...", "onnx": "..."}}
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hmpf.backbones import backbone_class
from hmpf.backbones import onnx_runtime as ox
from hmpf.backbones.onnx_runtime import StoredModel
from hmpf.errors import MissingDependencyError
from hmpf.index.layout import IndexCorruptError
from hmpf.methods import Method
from hmpf.methods.base import method_groups
from hmpf.methods.cnn import CnnMethod

__all__ = ["MODELS_DIR", "attach_models", "torch_needed", "write_models"]

#: Folder of a version's exported models.
MODELS_DIR = "onnx"


def _cnn_groups(methods: Mapping[str, Method]) -> list[dict[str, CnnMethod]]:
    """The CNN forward-pass groups of ``methods`` whose backbone exports, on the CPU."""
    out = []
    for group in method_groups(methods):
        cnn = {mid: m for mid, m in group.items() if isinstance(m, CnnMethod)}
        if not cnn:
            continue
        head = next(iter(cnn.values()))
        if head.cnn.device == "cpu" and backbone_class(head.cnn.backbone).onnx:
            out.append(cnn)
    return out


def write_models(out: Path, methods: Mapping[str, Method]) -> list[dict[str, Any]]:
    """Export (or copy from the version the methods were loaded from) the models of every
    CNN forward-pass group of ``methods`` into ``out/onnx/``.

    Returns:
        the manifest's ``models`` entries (empty: no method runs a model that exports).
    """
    entries: dict[str, dict[str, Any]] = {}
    for group in _cnn_groups(methods):
        head = next(iter(group.values()))
        layers = sorted({layer for m in group.values() for layer in m.layers()})
        stored = head.stored_for(layers)
        for i, size in enumerate(head.input_sizes()):
            if stored is not None:
                src = stored[i]
                rel = f"{MODELS_DIR}/{src.path.name}"
                dest = out / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                if not dest.exists():
                    _link_or_copy(src.path, dest)
                info = dict(src.info)
            else:
                info = _export(head, layers, size, out)
                rel = info["file"]
            entry = entries.setdefault(rel, {**info, "file": rel, "methods": []})
            entry["methods"] += [mid for mid in group if mid not in entry["methods"]]
    return list(entries.values())


def _link_or_copy(src: Path, dest: Path) -> None:
    """A hard link to the parent version's file (versions are immutable: the model takes no
    more room), or a copy where links are not possible."""
    try:
        os.link(src, dest)
    except OSError:
        shutil.copyfile(src, dest)


def _export(head: CnnMethod, layers: list[str], size: tuple[int, int], out: Path) -> dict:
    """Export ``head``'s backbone for ``layers`` at ``size`` into ``out`` (needs torch)."""
    import onnx  # exporting only (needs the cnn extra; a server need not have it)
    import torch  # imported here: exporting needs torch (a build has it; a server need not)

    net = head.backbone()
    key = ox.export_key(net, layers, size)
    rel = f"{MODELS_DIR}/{net.name}-{size[0]}x{size[1]}-{key[:16]}.onnx"
    if not (out / rel).exists():
        ox.export_model(net, layers, size, out / rel)
    return {
        "file": rel,
        "format": "onnx",
        "backbone": net.name,
        "input_size": [int(size[0]), int(size[1])],
        "layers": list(layers),
        "export_key": key,
        "opset": ox.OPSET,
        "exporter": {"torch": torch.__version__, "onnx": onnx.__version__},
    }


def attach_models(
    version_dir: Path, manifest: Mapping[str, Any], methods: Mapping[str, Method]
) -> None:
    """Give every CNN method of ``methods`` the models the manifest lists for it
    (:meth:`~hmpf.methods.cnn.CnnMethod.use_stored_models`; none for a version built before
    models were stored).

    Raises:
        IndexCorruptError: an entry is malformed, names a method that is not in the version,
            or a file the manifest's checksums do not cover.
    """
    entries = manifest.get("models") or []
    files = manifest.get("files") or {}
    where = version_dir / "manifest.json"
    per_method: dict[str, dict[tuple[int, int], StoredModel]] = {}
    if not isinstance(entries, list):
        raise IndexCorruptError(f"{where}: models is not a list")
    for e in entries:
        try:
            name = str(e["file"])
            rows, cols = (int(v) for v in e["input_size"])
            layers = [str(v) for v in e["layers"]]
            mids = [str(v) for v in e["methods"]]
        except (KeyError, TypeError, ValueError):
            raise IndexCorruptError(f"{where}: malformed models entry {e!r:.200}") from None
        if name not in files:  # only a file the checksums cover
            raise IndexCorruptError(f"{where}: model file {name!r} is not in its files")
        model = StoredModel(version_dir / name, layers, (rows, cols), info=dict(e))
        for mid in mids:
            m = methods.get(mid)
            if not isinstance(m, CnnMethod):
                raise IndexCorruptError(f"{where}: model {name!r} names {mid!r}, no CNN method")
            per_method.setdefault(mid, {})[(rows, cols)] = model
    for mid, m in methods.items():
        if isinstance(m, CnnMethod):
            m.use_stored_models(per_method.get(mid, {}), version_dir)


def torch_needed(methods: Mapping[str, Method]) -> bool:
    """True when a query over ``methods`` would run a forward pass in torch (a CNN method
    without a stored model, on the ``torch`` runtime, or on a backbone that does not
    export): torch's version then matters (:data:`hmpf.index.reader.STRICT_PACKAGES`)."""
    for m in methods.values():
        if not isinstance(m, CnnMethod):
            continue
        try:
            if m.runtime() == "torch" or m.stored_for(m.layers()) is None:
                return True
        except MissingDependencyError:  # a torch-only backbone, and no torch here
            return True
    return False
