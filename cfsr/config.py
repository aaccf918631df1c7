"""A method and its parameters, validated once: the value that travels to a reconstruction.

:class:`MethodConfig` is what the live service sends from the HTTP handler to the worker
process and what :class:`cfsr.streaming.StreamingReconstructor` runs. Making one checks the
method name and every parameter against its range and the window limit
(:func:`cfsr.methods.registry.resolve_params`); after that it is plain data: frozen, picklable,
and not checked again on the way (a copy unpickled in another process is the same value).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import InitVar, dataclass, field
from typing import Any

from cfsr.methods import registry
from cfsr.methods.registry import get_method

__all__ = ["MethodConfig"]


@dataclass(frozen=True, eq=True)
class MethodConfig:
    """A registered method with a complete, validated parameter set.

    Parameters
    ----------
    method : str
        Method name (any case; stored as registered, e.g. ``"tfp"``).
    params : mapping, optional
        Parameters to set; the others take their defaults (after ``preset``). Unknown names
        and values outside a parameter's range raise ValueError naming them.
    preset : str, optional
        Named preset applied before ``params`` (e.g. ``"paper"``).

    Attributes
    ----------
    params : dict
        Every parameter of the method, resolved (defaults filled in). Treat it as read-only:
        the object is a value.

    Examples
    --------
    >>> cfg = MethodConfig("TFP", {"window": 32})
    >>> cfg.method, cfg.params["window"]
    ('tfp', 32)
    >>> cfg.window
    (31, 0)
    """

    method: str
    params: Mapping[str, Any] = field(default_factory=dict)
    preset: InitVar[str | None] = None

    def __post_init__(self, preset: str | None) -> None:
        m = registry.get_method(self.method)
        params = registry.resolve_params(m, self.params, preset)
        object.__setattr__(self, "method", m.name)
        object.__setattr__(self, "params", params)

    def replace(self, *, method: str | None = None, params: Mapping[str, Any] | None = None
                ) -> MethodConfig:
        """A new config: ``params`` update this one's values; a different ``method`` starts
        from that method's defaults (parameters do not carry over between methods)."""
        if method is not None and method.strip().lower() != self.method:
            return MethodConfig(method, params)
        return MethodConfig(self.method, {**self.params, **(params or {})})

    @property
    def spec(self):
        """The registered :class:`cfsr.methods.registry.Method`."""
        return get_method(self.method)

    @property
    def window(self) -> tuple[int, int]:
        """Steps ``(before, after)`` around ``t`` that a frame needs, under these parameters."""
        before, after = self.spec.window(self.params)
        return int(before), int(after)
