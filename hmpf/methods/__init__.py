"""Image-matching methods, one module per method, registered by name.

>>> from hmpf.methods import create_method
>>> hog = create_method("hog")
"""

from hmpf.methods import (  # noqa: F401  (registration side effects)
    gem,
    gist,
    hog,
    hybridnet,
    inliers,
    kaze,
    netvlad,
    olo,
    sad,
)
from hmpf.methods.base import GlobalMethod, LocalMethod, Method, MethodConfig
from hmpf.methods.registry import available_methods, create_method, get_method_class, register

__all__ = [
    "GlobalMethod",
    "LocalMethod",
    "Method",
    "MethodConfig",
    "available_methods",
    "create_method",
    "get_method_class",
    "register",
]
