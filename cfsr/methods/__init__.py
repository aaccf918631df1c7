"""Reconstruction methods. Importing this package registers every built-in method."""

from cfsr.methods import cfsr_fine, csr, snm, tfa, tfi, tfp, tfstp  # noqa: F401  (registration side effects)
from cfsr.methods.registry import Method, Output, Param, get_method, methods, resolve_params

__all__ = ["Method", "Output", "Param", "get_method", "methods", "resolve_params"]
