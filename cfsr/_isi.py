"""The TFI interval rule (CFSR paper Eq. 3), once for every representation of a pixel's spikes.

The rule is arithmetic on the spikes around a step c; finding them depends on how the spikes
are held (a byte column, packed bits, spike words, a list of spike times), so each kernel
searches in its own way and calls :func:`tfi_interval` with what it found.
"""

from __future__ import annotations

from cfsr._jit import njit

__all__ = ["search_range", "tfi_interval", "needs_before", "needs_after", "isi_from_times"]


@njit(helper=True)
def search_range(c, m, n):  # pragma: no cover - numba
    """Steps ``[a, b)`` searched for the spikes around step ``c``: ``m`` steps each side,
    inside a window of ``n`` steps (the ``max_isi`` reach of Eq. 3)."""
    return max(0, c - m), min(n, c + m + 1)


@njit(helper=True)
def tfi_interval(p, n, pp, nn, a, b):  # pragma: no cover - numba
    """The interval (steps, >= 1) containing step c, spikes searched in ``[a, b)``.

    ``p``: the last spike at or before c; ``n``: the first after c (-1: none in range).
    ``pp``: the spike before ``p``, read only when ``n`` is missing (:func:`needs_before`);
    ``nn``: the spike after ``n``, read only when ``p`` is missing (:func:`needs_after`).
    A whole interval is ``n - p``. One open on the right is at least ``b - p`` steps and at
    least as long as the whole interval before it; one open on the left likewise; the larger
    is used, so dark pixels get small, finite rates instead of 0 or Inf. No spike in range:
    ``b - a + 1``.
    """
    if p >= 0 and n >= 0:
        return n - p
    if p >= 0:
        bound = b - p
        return max(bound, p - pp) if pp >= 0 else bound
    if n >= 0:
        bound = n - a + 1
        return max(bound, nn - n) if nn >= 0 else bound
    return b - a + 1


@njit(helper=True)
def needs_before(p, n):  # pragma: no cover - numba
    """Whether :func:`tfi_interval` reads ``pp`` (the interval is open on the right)."""
    return p >= 0 and n < 0


@njit(helper=True)
def needs_after(p, n):  # pragma: no cover - numba
    """Whether :func:`tfi_interval` reads ``nn`` (the interval is open on the left)."""
    return p < 0 and n >= 0


@njit(helper=True)
def isi_from_times(tv, ns, ip, a, b):  # pragma: no cover - numba
    """:func:`tfi_interval` at a step c from a pixel's ascending spike times ``tv[:ns]``;
    ``ip`` indexes the last spike ``<= c`` (-1: none); spikes searched in ``[a, b)``."""
    i_n = ip + 1
    p = tv[ip] if ip >= 0 and tv[ip] >= a else -1
    n = tv[i_n] if i_n < ns and tv[i_n] < b else -1
    pp = -1
    if needs_before(p, n) and ip >= 1 and tv[ip - 1] >= a:
        pp = tv[ip - 1]
    nn = -1
    if needs_after(p, n) and i_n + 1 < ns and tv[i_n + 1] < b:
        nn = tv[i_n + 1]
    return tfi_interval(p, n, pp, nn, a, b)
