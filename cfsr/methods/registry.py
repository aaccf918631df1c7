"""The method registry: one record per reconstruction, used by the library, CLI and worker.

Every method is a pure function of a *window* of spike frames around the output step ``t``:
``compute(window, center, start_step, params) -> Output``, where ``window[center]`` is step
``t`` and ``window[0]`` is step ``start_step``. The window spans ``before`` steps before ``t``
and ``after`` steps after it, clipped at the ends of the recording. Because the result depends
only on that window, the whole-array path (:func:`cfsr.reconstruct`) and the block-by-block
streaming path (:class:`cfsr.StreamingReconstructor`) give identical numbers by construction.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, fields
from enum import StrEnum
from functools import cache
from typing import Any, Self, get_type_hints

import numpy as np

from cfsr.layout import STEP_RATE_HZ

__all__ = [
    "MAX_UNPACKED_STEPS",
    "MAX_WINDOW_STEPS",
    "Memo",
    "MethodSettings",
    "Param",
    "ParamValue",
    "Params",
    "Method",
    "Output",
    "register",
    "get_method",
    "methods",
    "resolve_params",
]

#: Most steps a method's window may reach around the output step t (``before + after``):
#: 1 s at 40 kHz. The streaming reconstructor keeps the window plus its slack twice (mirrored
#: ring), so at this limit a 400 x 250 sensor holds 2 x 41,000 x 12,500 B, about 1 GB. Window-
#: like parameters (``window``, ``T``, ``max_isi``, ...) are bounded so that no parameter set
#: needs more (:func:`resolve_params` checks the combination).
MAX_WINDOW_STEPS = STEP_RATE_HZ
#: The same limit for methods without a packed path (``compute_packed``): they unpack their
#: whole window to one byte per pixel per step, 100 kB per step on a 400 x 250 sensor, so
#: 0.1 s (4,000 steps) already costs 400 MB per frame.
MAX_UNPACKED_STEPS = STEP_RATE_HZ // 10


#: A parameter's value as it comes from outside (API, CLI, library call, preset), before
#: :func:`resolve_params` checks it.
ParamValue = bool | int | float | str
#: Parameter values by name: the untyped form, checked and turned into a method's
#: :class:`MethodSettings` by the registry.
Params = Mapping[str, ParamValue]
#: What a recurrent method keeps between the outputs of one stream (:attr:`Method.recurrent`).
Memo = dict[str, object]


def choices_of(kind: type[StrEnum]) -> tuple[str, ...]:
    """A choice parameter's accepted values, in the order of the StrEnum that types them in
    the method's settings (the Param table keeps plain text, the settings the members)."""
    return tuple(member.value for member in kind)


def _is_number(kind: type) -> bool:
    return kind in (int, float)


def _num(x: float | None) -> str:
    """A bound in words: ``40000``, ``0.5``, ``1e-06``."""
    if x is None:
        return "?"
    return str(int(x)) if float(x).is_integer() else repr(float(x))


@dataclass(frozen=True)
class Param:
    """One method parameter: default value, unit, meaning and accepted values.

    Every numeric parameter has a closed range ``[minimum, maximum]`` (in ``unit``) and every
    text parameter a list of ``choices``: a value from outside (CLI, HTTP, file) is checked
    against them once, in :meth:`check`, so no method ever sees a value it was not built for
    (a window of 10^9 steps, a NaN threshold). The range is part of the method's description
    (:func:`methods`, ``cfsr methods``, ``GET /api/methods``).
    """

    default: Any
    unit: str
    help: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[Any, ...] | None = None

    def __post_init__(self) -> None:
        # Checked when a method module is imported: a parameter without bounds is a bug.
        kind = type(self.default)
        if _is_number(kind):
            if self.minimum is None or self.maximum is None:
                raise ValueError(f"numeric parameter ({self.help!r}) needs minimum and maximum")
            lo, hi = float(self.minimum), float(self.maximum)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= self.default <= hi):
                raise ValueError(
                    f"parameter ({self.help!r}): default {self.default!r} outside "
                    f"[{self.minimum}, {self.maximum}]"
                )
        elif kind is str and not self.choices:
            raise ValueError(f"text parameter ({self.help!r}) needs choices")

    @classmethod
    def steps(
        cls,
        default: float,
        help: str,
        *,
        minimum: float = 1,
        maximum: float = MAX_WINDOW_STEPS // 2,
    ) -> Param:
        """A parameter counted in sensor steps (25 us each): by default a window-like one, at
        least one step and at most half the window limit (:data:`MAX_WINDOW_STEPS`) on its
        side of t, so that any two of them fit in a window together."""
        return cls(default, "steps", help, minimum=minimum, maximum=maximum)

    @property
    def range_text(self) -> str:
        """The accepted values in words, e.g. ``1..40000 steps`` or ``trailing|centred``."""
        if self.choices is not None:
            return "|".join(str(c) for c in self.choices)
        if type(self.default) is bool:
            return "true|false"
        unit = f" {self.unit}" if self.unit else ""
        return f"{_num(self.minimum)}..{_num(self.maximum)}{unit}"

    def check(self, value: Any, strict: bool = True, *, name: str = "value") -> Any:
        """``value`` as this parameter's type, checked against its range or choices: the one
        validation of a value from outside (the API, the CLI, a library call).

        ``strict``: the value's own type must be the parameter's, as JSON gives it (the API):
        a number for a numeric parameter (``true`` and ``"32"`` are not), text among the
        choices, ``true``/``false`` for a switch. Not strict (the CLI, whose values are
        text): ``"32"``, ``"yes"`` and the like are converted first. Raises ValueError naming
        the parameter (``name``), the value and the accepted range. Numbers must be finite:
        NaN compares false with every bound, so it is refused first.
        """
        kind = type(self.default)
        v = _BAD if strict and not _own_type(kind, value) else _convert(kind, value)
        if v is _BAD:
            raise ValueError(
                f"parameter {name}={_show(value)}: expected {kind.__name__} in {self.range_text}"
            )
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(
                f"parameter {name}={_show(value)}: must be a finite number in {self.range_text}"
            )
        if self.choices is not None and v not in self.choices:
            raise ValueError(f"parameter {name}={_show(v)}: must be one of {list(self.choices)}")
        if self.minimum is not None and v < self.minimum:
            raise ValueError(
                f"parameter {name}={_show(v)}: must be >= {_num(self.minimum)} "
                f"(range {self.range_text})"
            )
        if self.maximum is not None and v > self.maximum:
            raise ValueError(
                f"parameter {name}={_show(v)}: must be <= {_num(self.maximum)} "
                f"(range {self.range_text})"
            )
        return v


def _own_type(kind: type, value: Any) -> bool:
    """Whether ``value`` has the JSON type of a ``kind`` parameter (strict :meth:`Param.check`):
    a boolean for a switch, a number (not a boolean) for a numeric one, text for a choice."""
    if kind is bool:
        return isinstance(value, bool | np.bool_)
    if _is_number(kind):
        return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
            value, bool | np.bool_
        )
    return isinstance(value, str)


def _show(value: Any) -> str:
    """``repr`` cut to a readable length (values come from outside: a 400-digit number)."""
    r = repr(value)
    return r if len(r) <= 40 else r[:37] + "..."


_BAD = object()
_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")


def _convert(kind: type, value: Any) -> Any:
    """``value`` as ``kind`` (a non-finite float stays a float, for the caller to name), or
    ``_BAD``."""
    try:
        if kind is bool:
            if isinstance(value, str):
                low = value.strip().lower()
                return low in _TRUE if low in _TRUE + _FALSE else _BAD
            if isinstance(value, bool | int | np.bool_ | np.integer) and value in (0, 1):
                return bool(value)
            return _BAD
        if kind in (int, float):
            if isinstance(value, bool | np.bool_):  # true/false is not a number of steps
                return _BAD
            fv = float(value)
            if kind is float or not math.isfinite(fv):
                return fv
            return int(fv) if fv == int(fv) else _BAD
        return kind(value)
    except (TypeError, ValueError, OverflowError):  # OverflowError: float(10**400)
        return _BAD


@dataclass(frozen=True)
class MethodSettings:
    """Base of a method's typed settings: a frozen dataclass with one field per parameter of
    the method's Param table, exactly (:func:`register` checks the names). The registry builds
    it from the resolved values (:meth:`of`) and hands it to the method's ``window`` and
    ``compute``, so that the pipeline reads typed attributes: a choice parameter's field is
    typed by a StrEnum and holds its member, a number's is an int or float.

    Subclasses declare the fields with their types and no defaults: the defaults, ranges and
    units stay in the Param table, the one source of them.
    """

    @classmethod
    def names(cls) -> frozenset[str]:
        """The parameter names this settings type holds."""
        return frozenset(f.name for f in fields(cls))

    @classmethod
    def of(cls, p: Params | MethodSettings) -> Self:
        """``p`` as this type: an instance as it is, else its fields taken from ``p`` (a
        mapping of resolved values, :func:`resolve_params`, or a settings object of another
        method that holds them); other names in ``p`` are ignored. A missing name raises
        KeyError (a partial parameter set has no meaning here: resolve it first); a value
        of another type than its field's raises TypeError (resolve it first)."""
        if isinstance(p, cls):
            return p
        if isinstance(p, MethodSettings):
            return cls(**{f.name: getattr(p, f.name) for f in fields(cls)})
        kinds = _field_kinds(cls)
        return cls(**{name: _typed(name, kind, p[name]) for name, kind in kinds.items()})

    def pick(self, *names: str) -> dict[str, ParamValue]:
        """``{name: value}`` of ``names``: the keywords of a stage function whose parameters
        are named as the method's."""
        return {name: getattr(self, name) for name in names}


@cache
def _field_kinds(cls: type[MethodSettings]) -> dict[str, type]:
    """Each field of a settings type with its type (``bool``, ``int``, ``float`` or a
    StrEnum)."""
    hints = get_type_hints(cls)
    return {f.name: hints[f.name] for f in fields(cls)}


def _typed(name: str, kind: type, value: ParamValue) -> ParamValue:
    """A resolved value as its settings field's type: a StrEnum field takes the member of its
    text; numbers and switches must have their field's type already (resolved values do)."""
    if isinstance(kind, type) and issubclass(kind, StrEnum):
        return kind(value)
    if kind is bool and isinstance(value, bool | np.bool_):
        return bool(value)
    if kind is int and isinstance(value, int | np.integer) and not isinstance(value, bool):
        return int(value)
    number = isinstance(value, int | float | np.number) and not isinstance(value, bool)
    if kind is float and number:
        return float(value)
    raise TypeError(f"setting {name}={value!r}: expected {kind.__name__} (resolve it first)")


class _TypedCall:
    """A method's function called with its settings: the argument at ``index`` (resolved
    parameters, or the settings already) becomes the method's :class:`MethodSettings`
    (:meth:`Method.settings_of`) before the call."""

    def __init__(self, fn: Callable[..., Any], index: int, method: Method) -> None:
        self.__wrapped__ = fn
        self._index = index
        self._method = method

    def __call__(self, *args: Any, **kw: Any) -> Any:
        a = list(args)
        a[self._index] = self._method.settings_of(a[self._index])
        return self.__wrapped__(*a, **kw)


#: Settings built from resolved parameters, by settings type and values: a stream's frames
#: share one parameter set, so each is typed once (bounded: a sweep's sets are dropped).
_TYPED: dict[tuple[type, tuple[tuple[str, ParamValue], ...]], MethodSettings] = {}
_TYPED_MAX = 256


@dataclass
class Output:
    """One reconstructed frame.

    ``rate`` is float32 ``(H, W)``, firing rate in spikes per step (0..1), upright.
    ``masks`` maps names (``"coarse"``, ``"fine"``) to boolean ``(H, W)`` dynamic-pixel masks.
    """

    rate: np.ndarray
    masks: dict[str, np.ndarray] = field(default_factory=dict)


#: ``(window, center, start_step, settings) -> Output``
ComputeFn = Callable[..., Output]
#: ``(packed_window, layout, center, start_step, settings) -> Output``
PackedComputeFn = Callable[..., Output]
#: ``settings -> (before, after)``
WindowFn = Callable[..., tuple[int, int]]
#: ``(times, settings) -> groups of steps``
GroupsFn = Callable[..., list[list[int]]]


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
        ``settings -> (before, after)``: steps needed before and after ``t``.
    compute : callable
        ``(window, center, start_step, settings) -> Output``.
    masks : tuple of str
        Names of the masks this method returns.
    presets : mapping
        Named parameter sets, e.g. ``{"paper": {...}}`` for the paper's real-data defaults.
    reference : str
        Paper equation or publication implemented.
    compute_packed : callable, optional
        ``(packed_window, layout, center, start_step, settings) -> Output``: the same result as
        ``compute`` computed straight from packed frames (no unpacking). When present, the
        library and the streaming reconstructor use it; tests check both agree exactly.
    recurrent : bool
        The method keeps a state over steps. Its ``compute`` and ``compute_packed`` take a
        keyword ``memo``: a dict the caller keeps for one stream
        (:class:`~cfsr.streaming.StreamingReconstructor`, one ``reconstruct`` call), in which
        outputs close together continue a state instead of rebuilding it. TFSTP's result is
        the same with or without it; CFSR's carried outputs differ slightly from isolated ones
        (under 0.1 dB, docs/methods.md): for them the contract is :meth:`carry_groups`.
    groups : callable, optional
        ``(times, settings) -> list of lists of steps``: :meth:`carry_groups` for this method.
    settings : MethodSettings subclass, optional
        The method's typed settings (:class:`MethodSettings`): its field names are exactly
        the names of ``params`` (checked by :func:`register`). With it, ``window``,
        ``compute``, ``compute_packed`` and ``groups`` take the settings: the registry types
        the resolved parameters at this boundary (:meth:`settings_of`), once per parameter
        set, so that callers pass either. Without it they take the resolved parameters.
    max_window : int, optional
        Most steps ``before + after`` (default: see :attr:`max_span`).
    borrowed_mask : str, optional
        The output mask inside which the method builds a pixel's rate from other pixels'
        spikes (CFSR's ``coarse``: its dynamic pixels); a flat-field gain is divided out of
        the rate only outside it (:func:`cfsr.defects.flatten`). None: every pixel's rate is
        its own.
    """

    name: str
    summary: str
    params: Mapping[str, Param]
    window: WindowFn
    compute: ComputeFn
    masks: tuple[str, ...] = ()
    presets: Mapping[str, Params] = field(default_factory=dict)
    reference: str = ""
    compute_packed: PackedComputeFn | None = None
    recurrent: bool = False
    max_window: int | None = None
    groups: GroupsFn | None = None
    settings: type[MethodSettings] | None = None
    borrowed_mask: str | None = None

    def __post_init__(self) -> None:
        if self.settings is None:
            return
        # where each function takes its settings: (window) (..., start, settings) (times, settings)
        for name, index in (("window", 0), ("compute", 3), ("compute_packed", 4), ("groups", 1)):
            fn = getattr(self, name)
            if fn is not None:
                object.__setattr__(self, name, _TypedCall(fn, index, self))

    def settings_of(self, params: Params | MethodSettings) -> Any:
        """``params`` (resolved, :func:`resolve_params`) as this method's settings, built once
        per parameter set; settings as they are; ``params`` itself without a settings type."""
        kind = self.settings
        if kind is None or isinstance(params, kind):
            return params
        if isinstance(params, MethodSettings):
            return kind.of(params)
        key = (kind, tuple(sorted(params.items())))
        try:
            return _TYPED[key]
        except KeyError:
            pass
        except TypeError:  # a value that cannot be a key (not a resolved one): typed as it is
            return kind.of(params)
        if len(_TYPED) >= _TYPED_MAX:
            _TYPED.clear()
        typed = _TYPED[key] = kind.of(params)
        return typed

    def carry_groups(self, times: Iterable[int], params: Params) -> list[list[int]]:
        """The output steps ``times`` (sorted, deduplicated) split into groups to run in
        order, each with one ``memo`` emptied before it: the first output of a group is the
        isolated one, the others may continue from the output before them. The groups
        depend only on ``times`` and ``params``, so results do not depend on how groups are
        shared between processes. Without a rule of its own (``groups``), a recurrent method
        (identical results either way) keeps all outputs in one group and any other method
        puts each output alone."""
        ts = sorted({int(t) for t in times})
        if self.groups is not None:
            return self.groups(ts, params)
        if self.recurrent:
            return [ts] if ts else []
        return [[t] for t in ts]

    def run_window(
        self,
        recording_like: Any,
        a: int,
        b: int,
        t: int,
        params: Params | MethodSettings,
        memo: Memo | None = None,
    ) -> Output:
        """Compute step ``t`` from frames ``[a, b)`` of anything with ``packed(a, b)``,
        ``frames(a, b)`` and ``layout`` (a SpikeRecording or the streaming buffer).

        ``memo`` reaches recurrent methods only (see ``recurrent``)."""
        kw = {"memo": memo} if self.recurrent else {}
        params = self.settings_of(params)
        if self.compute_packed is not None:
            return self.compute_packed(
                recording_like.packed(a, b), recording_like.layout, t - a, a, params, **kw
            )
        return self.compute(recording_like.frames(a, b), t - a, a, params, **kw)

    @property
    def max_span(self) -> int:
        """Most steps ``before + after`` a parameter set may ask for: ``max_window`` when
        set, else :data:`MAX_WINDOW_STEPS`, or :data:`MAX_UNPACKED_STEPS` for methods that
        unpack their window (no ``compute_packed``)."""
        if self.max_window is not None:
            return self.max_window
        return MAX_WINDOW_STEPS if self.compute_packed is not None else MAX_UNPACKED_STEPS

    def describe(self) -> dict[str, Any]:
        """Summary, parameters (default, unit, help, accepted range), masks and presets."""
        return {
            "name": self.name,
            "summary": self.summary,
            "reference": self.reference,
            "masks": list(self.masks),
            "max_window_steps": self.max_span,
            "params": {
                k: {
                    "default": p.default,
                    "unit": p.unit,
                    "help": p.help,
                    "minimum": p.minimum,
                    "maximum": p.maximum,
                    "choices": None if p.choices is None else list(p.choices),
                    "range": p.range_text,
                }
                for k, p in self.params.items()
            },
            "presets": {k: dict(v) for k, v in self.presets.items()},
        }


_REGISTRY: dict[str, Method] = {}


def register(method: Method) -> Method:
    if method.name in _REGISTRY:
        raise ValueError(f"method {method.name!r} registered twice")
    if method.settings is not None and method.settings.names() != set(method.params):
        # the Param table is the one source of names: a settings type must hold them all
        raise ValueError(
            f"method {method.name!r}: settings fields differ from its parameters: "
            f"{sorted(method.settings.names() ^ set(method.params))}"
        )
    _REGISTRY[method.name] = method
    return method


def _load_all() -> None:
    # Importing the package modules registers every built-in method exactly once.
    # deferred: a cycle (the cfsr.methods package imports this module before its methods)
    import cfsr.methods  # noqa: F401


def get_method(name: str) -> Method:
    _load_all()
    key = name.strip().lower()
    if key not in _REGISTRY:
        raise ValueError(f"unknown method {name!r}; available: {', '.join(sorted(_REGISTRY))}")
    return _REGISTRY[key]


def methods() -> dict[str, dict[str, Any]]:
    """All methods with their summary, parameters (default, unit, help, minimum, maximum,
    choices and ``range`` in words), masks and presets."""
    _load_all()
    return {name: m.describe() for name, m in _REGISTRY.items()}


def resolve_params(
    method: Method,
    params: Params | None = None,
    preset: str | None = None,
    *,
    strict: bool = False,
) -> dict[str, Any]:
    """Defaults, then the preset, then explicit values; unknown names are an error.

    Each value is checked against its parameter's range (:meth:`Param.check`; ``strict``: its
    type must be the parameter's own, as the API asks; otherwise text such as the CLI's is
    converted), then the
    combination against the window limit (:attr:`Method.max_span` steps around t): several
    parameters in range can still add up to a window no ring holds (CFSR's history reaches
    ``mog_frames * mog_stride`` steps back). Raises ValueError naming what is wrong.
    """
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
        out[k] = method.params[k].check(v, strict, name=k)
    before, after = method.window(out)
    if before + after > method.max_span:
        changed = [
            f"{k}={v!r}"
            for k, v in out.items()
            if v != method.params[k].default and _is_number(type(method.params[k].default))
        ]
        raise ValueError(
            f"method {method.name!r}: these parameters need a window of {before} steps before "
            f"t and {after} after; at most {method.max_span} steps in all "
            f"({method.max_span / STEP_RATE_HZ:g} s)"
            + (f" (set: {', '.join(changed)})" if changed else "")
        )
    return out
