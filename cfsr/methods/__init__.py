"""Reconstruction methods. Importing this package registers every built-in method.

The baselines are one module each (``tfi``, ``tfp``, ``tfa``, ``tfstp``, ``snm``); CFSR and its
coarse stage CSR are the package :mod:`cfsr.methods.cfsr`, laid out by the paper's stages.

``cfsr.methods()`` (this package called) is :func:`~cfsr.methods.registry.methods`: every
method's description. The package is callable rather than shadowed by the function, so that
its submodules import as any others (``import cfsr.methods.tfp as tfp``).
"""

import sys
import types
from typing import Any

from cfsr.methods import cfsr, snm, tfa, tfi, tfp, tfstp  # noqa: F401  (registration side effects)
from cfsr.methods.registry import Method, Output, Param, get_method, methods, resolve_params

__all__ = ["Method", "Output", "Param", "get_method", "methods", "resolve_params"]


class _CallablePackage(types.ModuleType):
    """This package, callable as :func:`~cfsr.methods.registry.methods`."""

    def __call__(self) -> dict[str, dict[str, Any]]:
        return methods()


sys.modules[__name__].__class__ = _CallablePackage
