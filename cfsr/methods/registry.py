"""The method registry: one record per reconstruction, used by the library, CLI and worker.

Every method is a pure function of a *window* of spike frames around the output step ``t``:
``compute(window, center, start_step, params) -> Output``, where ``window[center]`` is step
``t`` and ``window[0]`` is step ``start_step``. The window spans ``before`` steps before ``t``
and ``after`` steps after it, clipped at the ends of the recording. Because the result depends
only on that window, the whole-array path (:func:`cfsr.reconstruct`) and the block-by-block
streaming path (:class:`cfsr.StreamingReconstructor`) give identical numbers by construction.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Param", "Method", "Output", "register", "get_method", "methods", "resolve_params"]


@dataclass(frozen=True)
class Param:
    """One method parameter: default value, unit and meaning."""

    default: Any
    unit: str
    help: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[Any, ...] | None = None

    def coerce(self, name: str, value: Any) -> Any:
        """Convert a CLI/JSON value to the default's type and check bounds."""
        kind = type(self.default)
        try:
            if kind is bool and isinstance(value, str):
                low = value.strip().lower()
                if low not in ("1", "0", "true", "false", "yes", "no", "on", "off"):
                    raise ValueError(value)
                v: Any = low in ("1", "true", "yes", "on")
            elif kind is int:
                fv = float(value)
                if fv != int(fv):
                    raise ValueError(value)
                v = int(fv)
            else:
                v = kind(value)
        except (TypeError, ValueError):
            raise ValueError(
                f"parameter {name}={value!r}: expected {kind.__name__} ({self.unit})"
            ) from None
        if self.choices is not None and v not in self.choices:
            raise ValueError(f"parameter {name}={v!r}: must be one of {list(self.choices)}")
        if self.minimum is not None and v < self.minimum:
            raise ValueError(f"parameter {name}={v!r}: must be >= {self.minimum}")
        if self.maximum is not None and v > self.maximum:
            raise ValueError(f"parameter {name}={v!r}: must be <= {self.maximum}")
        return v


@dataclass
class Output:
    """One reconstructed frame.

    ``rate`` is float32 ``(H, W)``, firing rate in spikes per step (0..1), upright.
    ``masks`` maps names (``"coarse"``, ``"fine"``) to boolean ``(H, W)`` dynamic-pixel masks.
    """

    rate: np.ndarray
    masks: dict[str, np.ndarray] = field(default_factory=dict)


ComputeFn = Callable[[np.ndarray, int, int, Mapping[str, Any]], Output]
PackedComputeFn = Callable[[np.ndarray, Any, int, int, Mapping[str, Any]], Output]
WindowFn = Callable[[Mapping[str, Any]], tuple[int, int]]


@dataclass(frozen=True)
class Method:
    """A registered reconstruction method.

    Attributes
    ----------
    name : str
        Lower-case name used by the library, CLI and service (``tfi``, ``tfp``, ...).
    summary : str
        One line for ``cfsr.methods()`` and ``--help``.
    params : mapping of str to Param
        Parameters with their defaults (our calibrated defaults).
    window : callable
        ``params -> (before, after)``: steps needed before and after ``t``.
    compute : callable
        ``(window, center, start_step, params) -> Output``.
    masks : tuple of str
        Names of the masks this method returns.
    presets : mapping
        Named parameter sets, e.g. ``{"paper": {...}}`` for the paper's real-data defaults.
    reference : str
        Paper equation or publication implemented.
    compute_packed : callable, optional
        ``(packed_window, layout, center, start_step, params) -> Output``: the same result as
        ``compute`` computed straight from packed frames (no unpacking). When present, the
        library and the streaming reconstructor use it; tests check both agree exactly.
    """

    name: str
    summary: str
    params: Mapping[str, Param]
    window: WindowFn
    compute: ComputeFn
    masks: tuple[str, ...] = ()
    presets: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    reference: str = ""
    compute_packed: PackedComputeFn | None = None

    def run_window(
        self, recording_like: Any, a: int, b: int, t: int, params: Mapping[str, Any]
    ) -> Output:
        """Compute step ``t`` from frames ``[a, b)`` of anything with ``packed(a, b)``,
        ``frames(a, b)`` and ``layout`` (a SpikeRecording or the streaming buffer)."""
        if self.compute_packed is not None:
            return self.compute_packed(
                recording_like.packed(a, b), recording_like.layout, t - a, a, params
            )
        return self.compute(recording_like.frames(a, b), t - a, a, params)

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "summary": self.summary,
            "reference": self.reference,
            "masks": list(self.masks),
            "params": {
                k: {"default": p.default, "unit": p.unit, "help": p.help}
                for k, p in self.params.items()
            },
            "presets": {k: dict(v) for k, v in self.presets.items()},
        }


_REGISTRY: dict[str, Method] = {}


def register(method: Method) -> Method:
    if method.name in _REGISTRY:
        raise ValueError(f"method {method.name!r} registered twice")
    _REGISTRY[method.name] = method
    return method


def _load_all() -> None:
    # Importing the package modules registers every built-in method exactly once.
    import cfsr.methods  # noqa: F401


def get_method(name: str) -> Method:
    _load_all()
    key = name.strip().lower()
    if key not in _REGISTRY:
        raise ValueError(f"unknown method {name!r}; available: {', '.join(sorted(_REGISTRY))}")
    return _REGISTRY[key]


def methods() -> dict[str, dict[str, Any]]:
    """All methods with their summary, parameters (default, unit, help), masks and presets."""
    _load_all()
    return {name: m.describe() for name, m in _REGISTRY.items()}


def resolve_params(
    method: Method, params: Mapping[str, Any] | None = None, preset: str | None = None
) -> dict[str, Any]:
    """Defaults, then the preset, then explicit values; unknown names are an error."""
    out = {k: p.default for k, p in method.params.items()}
    if preset is not None:
        if preset not in method.presets:
            raise ValueError(
                f"method {method.name!r} has no preset {preset!r}; "
                f"available: {sorted(method.presets) or 'none'}"
            )
        out.update(method.presets[preset])
    for k, v in (params or {}).items():
        if k not in method.params:
            raise ValueError(
                f"method {method.name!r} has no parameter {k!r}; "
                f"parameters: {', '.join(method.params) or 'none'}"
            )
        out[k] = method.params[k].coerce(k, v)
    return out
