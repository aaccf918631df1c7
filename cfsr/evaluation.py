"""Evaluation of reconstruction methods against ground truth (design section 4).

* :func:`evaluate`: simulate each scene once (:mod:`cfsr.simulate`), run every method spec
  through :func:`cfsr.reconstruct_outputs` at the given steps, and score the 8-bit display
  images (``rate / rate_scale * 255``, clipped) against the ground truth displayed the same way:
  PSNR and SSIM over the whole frame and inside the true motion mask, IoU of every mask the
  method returns against the true motion mask, and the time per output frame.
* :func:`evaluate_reds`: the same scores on REDS ``.dat`` files (Spk2ImgNet simulations) whose
  ground truth is frame 150, brightness = rate / 0.6 * 255.
* :func:`parse_method_spec`: ``"tfp:window=32,mode=centred"`` -> method name + parameters, so
  one method can be compared at several settings.
* :func:`format_table`: a plain-text table of the rows.

Rows are plain dicts (JSON-ready: non-finite numbers become None).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cfsr.api import check_times, reconstruct_outputs
from cfsr.datfile import read_dat
from cfsr.display import to_display
from cfsr.methods.registry import get_method, resolve_params
from cfsr.methods.registry import methods as registered
from cfsr.metrics import mask_iou, psnr, ssim
from cfsr.simulate import SCENES, simulate
from cfsr.spikes import SpikeRecording

__all__ = [
    "MethodSpec",
    "parse_method_spec",
    "split_method_specs",
    "default_times",
    "evaluate",
    "evaluate_reds",
    "find_reds_pairs",
    "summarize",
    "format_table",
    "REDS_GAIN",
    "REDS_FRAME",
]

#: REDS (Spk2ImgNet) brightness rule: display = rate / 0.6 * 255.
REDS_GAIN = 0.6
#: REDS ground truth is the centre frame of the 301-frame stream.
REDS_FRAME = 150

Progress = bool | Callable[[str], Any] | None


# --------------------------------------------------------------------------- method specs


@dataclass(frozen=True)
class MethodSpec:
    """A method with parameters, e.g. ``tfp:window=32,mode=centred``.

    Attributes
    ----------
    label : str
        How the spec is shown in tables (the canonical spec string).
    name : str
        Registered method name.
    params : dict
        Parameter values (strings are coerced by the method's parameter types).
    preset : str or None
        Named preset applied before ``params`` (``tfp:preset=paper``).
    """

    label: str
    name: str
    params: dict[str, Any] = field(default_factory=dict)
    preset: str | None = None


def parse_method_spec(
    spec: str | MethodSpec, params: Mapping[str, Any] | None = None
) -> MethodSpec:
    """Parse ``NAME[:KEY=VALUE[,KEY=VALUE...]]`` into a :class:`MethodSpec`.

    Parameters
    ----------
    spec : str
        E.g. ``"tfi"``, ``"tfp:window=32,mode=centred"``, ``"tfp:preset=paper"``.
    params : mapping, optional
        Defaults for this method, overridden by the values in ``spec``.

    Returns
    -------
    MethodSpec
        The method must be registered and every parameter known and valid (checked here, so
        typos fail before any simulation runs).

    Examples
    --------
    >>> s = parse_method_spec("tfp:window=32,mode=centred")
    >>> s.name, s.params, s.label
    ('tfp', {'window': 32, 'mode': 'centred'}, 'tfp:window=32,mode=centred')
    """
    if isinstance(spec, MethodSpec):
        if not params:
            return spec
        return MethodSpec(spec.label, spec.name, {**dict(params), **spec.params}, spec.preset)
    text = str(spec).strip()
    if not text:
        raise ValueError("empty method spec")
    name, _, rest = text.partition(":")
    name = name.strip().lower()
    given: dict[str, Any] = {}
    preset = None
    for part in rest.split(","):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise ValueError(f"method spec {text!r}: bad parameter {part!r}; use KEY=VALUE")
        k, v = (s.strip() for s in part.split("=", 1))
        if k == "preset":
            preset = v
        else:
            given[k] = v
    method = get_method(name)  # raises with the list of methods
    merged = {**dict(params or {}), **given}
    resolved = resolve_params(method, merged, preset)  # validates names, types, bounds
    out_params = {k: resolved[k] for k in merged}
    bits = ([f"preset={preset}"] if preset else []) + [f"{k}={out_params[k]}" for k in given]
    label = name + (":" + ",".join(bits) if bits else "")
    return MethodSpec(label, name, out_params, preset)


def split_method_specs(text: str | Iterable[str]) -> list[str]:
    """Split a ``--methods`` value into specs.

    Commas separate specs, but a ``KEY=VALUE`` item without ``:`` continues the previous spec:
    ``"tfi,tfp:window=32,mode=centred,tfp:window=16"`` -> ``["tfi",
    "tfp:window=32,mode=centred", "tfp:window=16"]``. Semicolons and whitespace also separate
    specs. A list of strings is split item by item.
    """
    items = [text] if isinstance(text, str) else list(text)
    out: list[str] = []
    for item in items:
        for chunk in str(item).replace(";", " ").split():
            for part in chunk.split(","):
                part = part.strip()
                if not part:
                    continue
                if "=" in part and ":" not in part and out and ":" in out[-1]:
                    out[-1] = f"{out[-1]},{part}"
                elif "=" in part and ":" not in part:
                    raise ValueError(f"parameter {part!r} given before any method")
                else:
                    out.append(part)
    return out


def _specs(
    methods: Sequence[str | MethodSpec] | str | None,
    params_by_method: Mapping[str, Mapping[str, Any]] | None,
) -> list[MethodSpec]:
    if methods is None:
        names: list[str | MethodSpec] = list(registered())
    elif isinstance(methods, str):
        names = list(split_method_specs(methods))
    else:
        names = list(methods)
    if not names:
        raise ValueError("no methods to evaluate")
    pbm = dict(params_by_method or {})
    out = []
    for s in names:
        key = s.label if isinstance(s, MethodSpec) else str(s).strip()
        base = key.partition(":")[0].strip().lower()
        defaults = {**dict(pbm.get(base, {})), **dict(pbm.get(key, {}))}
        out.append(parse_method_spec(s, defaults))
    labels = [s.label for s in out]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise ValueError(f"method spec(s) given twice: {dup}")
    return out


# --------------------------------------------------------------------------- helpers


def default_times(steps: int, n: int = 3) -> list[int]:
    """``n`` output steps spread over the middle of a ``steps``-step run.

    Steps between 40 % and 75 % of the run, so trailing windows of a few hundred steps and
    centred ones both fit (e.g. 1200 steps -> 480, 690, 900).
    """
    steps = int(steps)
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if n <= 1:
        return [steps // 2]
    lo = min(steps - 1, (40 * steps) // 100)
    hi = min(steps - 1, (75 * steps) // 100)
    return sorted({lo + (hi - lo) * i // (n - 1) for i in range(n)})


def _finite(v: Any) -> Any:
    if isinstance(v, float | np.floating):
        return float(v) if math.isfinite(float(v)) else None
    return v


def _mean(values: list[float]) -> float | None:
    vals = [v for v in values if v is not None]
    if not vals:
        return None
    return _finite(float(np.mean(vals)))


def _progress(progress: Progress, total: int, desc: str):
    """-> (update(msg), close()) for a bool/callable progress option."""
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=total, desc=desc, unit="job", leave=False)

        def update(msg: str) -> None:
            bar.set_postfix_str(msg, refresh=False)
            bar.update(1)

        return update, bar.close
    if callable(progress):
        return progress, (lambda: None)
    return (lambda msg: None), (lambda: None)


def _score_frames(
    outs: list,
    gts: list[np.ndarray],
    masks: list[np.ndarray | None],
    gain: float,
) -> dict[str, Any]:
    """PSNR/SSIM (all, motion) and mask IoUs averaged over frames."""
    ps, ss, pm, sm = [], [], [], []
    ious: dict[str, list[float]] = {}
    for out, gt, mask in zip(outs, gts, masks, strict=True):
        img = to_display(out.rate, gain=gain)
        ps.append(_finite(psnr(gt, img)))
        ss.append(ssim(gt, img))
        if mask is not None and mask.any():
            pm.append(_finite(psnr(gt, img, mask=mask)))
            sm.append(ssim(gt, img, mask=mask))
        if mask is not None:
            for name, m in out.masks.items():
                ious.setdefault(name, []).append(mask_iou(np.asarray(m, bool), mask))
    row: dict[str, Any] = {
        "psnr_all": _mean(ps),
        "psnr_motion": _mean(pm),
        "ssim": _mean(ss),
        "ssim_motion": _mean(sm),
    }
    for name in sorted(ious):
        row[f"iou_{name}"] = _mean(ious[name])
    return row


# --------------------------------------------------------------------------- simulated scenes


def _scene_names(scenes: Sequence[str] | str | None) -> list[str]:
    """Simulator scene names from a list, a comma-separated string or None (all); ValueError
    naming the unknown ones."""
    if scenes is None:
        names = list(SCENES)
    elif isinstance(scenes, str):
        names = [s.strip() for s in scenes.split(",") if s.strip()]
    else:
        names = [str(s).strip() for s in scenes]
    unknown = [s for s in names if s.lower() not in SCENES]
    if unknown:
        raise ValueError(f"unknown scene(s) {unknown}; choices: {', '.join(SCENES)}")
    if not names:
        raise ValueError("no scenes to evaluate")
    return names


def _sim_times(times: Sequence[int] | None, steps: int) -> list[int]:
    """Output steps inside a simulated run of ``steps`` (default :func:`default_times`)."""
    return check_times(default_times(steps) if times is None else times, steps,
                       "the simulated run")


def _simulated(scene: str, steps: int, ts: Sequence[int], seed: int, height: int, width: int,
               noise: Any) -> tuple[Any, list[np.ndarray], list[np.ndarray], float]:
    """``scene`` simulated: its packed recording, the 8-bit ground truth and the true motion
    masks at ``ts``, and its rate scale (the display gain of both)."""
    sim = simulate(scene.lower(), steps, seed=seed, height=height, width=width, noise=noise)
    gain = sim.rate_scale
    gts = [to_display(sim.ideal_rate(t), gain=gain) for t in ts]
    masks = [sim.motion_mask(t) for t in ts]
    # the packed copy is all the methods need: the simulation's arrays go with this frame
    return SpikeRecording.from_array(sim.spikes, meta={"gain": gain}), gts, masks, gain


def _timed_outputs(rec: Any, spec: MethodSpec, ts: Sequence[int], *, warm: bool
                   ) -> tuple[list[Any], float]:
    """``spec``'s outputs at ``ts`` and the seconds they took in this process (``warm``: one
    untimed call first, so a first use's compilation is not counted)."""
    if warm:
        reconstruct_outputs(rec, spec.name, ts[:1], preset=spec.preset, params=spec.params)
    t0 = time.perf_counter()
    outs = reconstruct_outputs(rec, spec.name, ts, preset=spec.preset, params=spec.params)
    return outs, time.perf_counter() - t0


def evaluate(
    methods: Sequence[str | MethodSpec] | str | None,
    scenes: Sequence[str] | str | None,
    *,
    steps: int = 1200,
    times: Sequence[int] | None = None,
    params_by_method: Mapping[str, Mapping[str, Any]] | None = None,
    seed: int = 0,
    height: int = 250,
    width: int = 400,
    noise: Any = None,
    progress: Progress = False,
) -> list[dict[str, Any]]:
    """Score methods on simulated scenes against exact ground truth.

    Parameters
    ----------
    methods : list of str or MethodSpec, str, or None
        Method specs (``"tfi"``, ``"tfp:window=32,mode=centred"``; see
        :func:`parse_method_spec`); a string is split by :func:`split_method_specs`; None means
        every registered method with its defaults. The same method may appear several times
        with different parameters.
    scenes : list of str, str, or None
        Scene names (:data:`cfsr.simulate.SCENES`); a comma-separated string; None for all.
    steps : int, keyword-only
        Steps simulated per scene (1 step = 25 us).
    times : list of int, optional
        Output steps (frame indices); default :func:`default_times` (3 steps mid-run).
    params_by_method : mapping, optional
        ``{method name or spec label: {param: value}}``, defaults under the spec's own values.
    seed : int
        Simulator seed (each scene is simulated once, shared by all methods).
    height, width : int
        Frame size in pixels.
    noise : optional
        Simulator noise (see :class:`cfsr.simulate.Noise`); default None: each scene's own
        (none, except the ``noisy`` scene's ``sensor`` preset); ``"none"`` turns it off.
    progress : bool or callable
        True: a tqdm bar on stderr; a callable receives a message per finished job.

    Returns
    -------
    list of dict
        One row per (method spec, scene), in scene-major order, with keys ``method`` (label),
        ``name``, ``params``, ``scene``, ``steps``, ``times``, ``rate_scale``, ``psnr_all``,
        ``psnr_motion``, ``ssim``, ``ssim_motion`` (dB / unitless, mean over ``times``;
        ``*_motion`` are None when the scene has no motion), ``iou_<mask>`` for every mask the
        method returns (mean IoU with the true motion mask), ``motion_fraction`` and
        ``ms_per_frame`` (wall time of ``reconstruct_outputs`` per output frame, window
        unpacking included; each method is called once untimed on the first scene, so JIT
        compilation is not counted).

    Notes
    -----
    Display conversion is the named step :func:`cfsr.to_display` with ``gain =
    sim.rate_scale`` for both the reconstruction and the ground truth, so a perfect rate
    estimate scores the quantisation limit of 8 bits. The ground truth is the rate of an ideal
    pixel (``sim.ideal_rate``: ``rate_scale`` times the scene intensity), not the noisy sensor's
    expected rate: with fixed-pattern noise (dark current, hot pixels, threshold and gain
    mismatch) a method is scored on how well it recovers the scene, not the noise. Without
    fixed-pattern noise the two are equal.
    """
    specs = _specs(methods, params_by_method)
    scene_names = _scene_names(scenes)
    steps = int(steps)
    ts = _sim_times(times, steps)

    update, close = _progress(progress, len(scene_names) * (1 + len(specs)), "evaluate")
    rows: list[dict[str, Any]] = []
    try:
        for scene in scene_names:
            rec, gts, masks, gain = _simulated(scene, steps, ts, seed, height, width, noise)
            motion = float(np.mean([m.mean() for m in masks]))
            update(f"simulated {scene}")
            for spec in specs:
                # JIT compile is not run time: warm up once, on the first scene
                outs, dt = _timed_outputs(rec, spec, ts, warm=scene == scene_names[0])
                row: dict[str, Any] = {
                    "method": spec.label,
                    "name": spec.name,
                    "params": resolve_params(get_method(spec.name), spec.params, spec.preset),
                    "scene": scene,
                    "steps": steps,
                    "times": list(ts),
                    "rate_scale": gain,
                    "motion_fraction": motion,
                }
                row.update(_score_frames(outs, gts, masks, gain))
                row["ms_per_frame"] = 1000.0 * dt / len(ts)
                rows.append(row)
                update(f"{spec.label} on {scene}")
    finally:
        close()
    return rows


# --------------------------------------------------------------------------- REDS


def find_reds_pairs(folder: str | os.PathLike) -> list[tuple[Path, Path]]:
    """(spike ``.dat``, ground-truth ``.png``) pairs in a REDS folder.

    Accepts ``FOLDER/spike/*.dat`` with ``FOLDER/gt/*.png`` (the Spike-Zoo layout) or
    ``FOLDER/*.dat`` with ``FOLDER/gt/*.png``; the PNG has the ``.dat``'s stem.
    """
    base = Path(folder)
    if not base.is_dir():
        raise ValueError(f"{base}: not a folder")
    dats = sorted((base / "spike").glob("*.dat")) or sorted(base.glob("*.dat"))
    if not dats:
        raise ValueError(f"{base}: no .dat files (looked in {base} and {base / 'spike'})")
    pairs = []
    missing = []
    for d in dats:
        png = base / "gt" / (d.stem + ".png")
        if png.exists():
            pairs.append((d, png))
        else:
            missing.append(png.name)
    if not pairs:
        raise ValueError(f"{base}: no ground-truth PNGs in {base / 'gt'} (wanted {missing[:3]})")
    return pairs


def evaluate_reds(
    folder: str | os.PathLike,
    methods: Sequence[str | MethodSpec] | str | None,
    *,
    params_by_method: Mapping[str, Mapping[str, Any]] | None = None,
    gain: float = REDS_GAIN,
    frame: int = REDS_FRAME,
    progress: Progress = False,
) -> list[dict[str, Any]]:
    """Score methods on REDS spike files whose ground truth is one frame.

    Parameters
    ----------
    folder : path
        See :func:`find_reds_pairs`.
    methods : as in :func:`evaluate`
    gain : float
        Firing rate shown as white: display = rate / gain * 255 (0.6 for REDS).
    frame : int
        Frame index of the ground truth (150, the centre of the 301 frames).

    Returns
    -------
    list of dict
        One row per (method, file) with ``scene`` = file stem, then one row per method with
        ``scene = "mean"`` (mean over files). Keys as in :func:`evaluate`; ``*_motion`` are
        None (REDS has no motion masks). Published anchors with this brightness rule
        (Spike-Zoo, 41-frame windows): TFI 25.1 dB, TFP 28.2 dB.
    """
    import cv2

    specs = _specs(methods, params_by_method)
    pairs = find_reds_pairs(folder)
    update, close = _progress(progress, len(pairs) * len(specs), "REDS")
    rows: list[dict[str, Any]] = []
    try:
        for i, (dat, png) in enumerate(pairs):
            rec = read_dat(dat)
            gt = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
            if gt is None:
                raise ValueError(f"{png}: unreadable PNG")
            if gt.shape != rec.shape[1:]:
                raise ValueError(f"{png}: shape {gt.shape} differs from spikes {rec.shape[1:]}")
            if not 0 <= frame < rec.n_frames:
                raise ValueError(f"{dat}: frame {frame} outside 0..{rec.n_frames - 1}")
            for spec in specs:
                # files are read-only maps, a type of their own to numba: warm up on the first
                outs, dt = _timed_outputs(rec, spec, [frame], warm=i == 0)
                row: dict[str, Any] = {
                    "method": spec.label,
                    "name": spec.name,
                    "params": resolve_params(get_method(spec.name), spec.params, spec.preset),
                    "scene": dat.stem,
                    "steps": rec.n_frames,
                    "times": [frame],
                    "rate_scale": gain,
                }
                row.update(_score_frames(outs, [gt], [None], gain))
                row["ms_per_frame"] = 1000.0 * dt
                rows.append(row)
                update(f"{spec.label} on {dat.stem}")
    finally:
        close()
    return rows + summarize(rows)


# --------------------------------------------------------------------------- tables


_NUMERIC = ("psnr_all", "psnr_motion", "ssim", "ssim_motion", "ms_per_frame")


def summarize(rows: Sequence[Mapping[str, Any]], *, scene: str = "mean") -> list[dict[str, Any]]:
    """One row per method: the mean of each metric over that method's rows (None ignored)."""
    order: list[str] = []
    groups: dict[str, list[Mapping[str, Any]]] = {}
    for r in rows:
        if r.get("scene") == scene:
            continue
        key = str(r["method"])
        if key not in groups:
            order.append(key)
        groups.setdefault(key, []).append(r)
    out = []
    for key in order:
        g = groups[key]
        keys = list(_NUMERIC) + sorted({k for r in g for k in r if k.startswith("iou_")})
        row: dict[str, Any] = {
            "method": key,
            "name": g[0].get("name"),
            "params": g[0].get("params"),
            "scene": scene,
            "n": len(g),
        }
        for k in keys:
            row[k] = _mean([r.get(k) for r in g])
        out.append(row)
    return out


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """A fixed-width text table: method, scene, PSNR/SSIM (all, motion), mask IoUs, ms/frame.

    Missing values (no motion in the scene, no such mask) print as ``-``.
    """
    if not rows:
        return "(no results)"
    iou_keys = sorted({k for r in rows for k in r if k.startswith("iou_")})
    cols: list[tuple[str, str, str]] = [
        ("method", "method", "s"),
        ("scene", "scene", "s"),
        ("psnr_all", "PSNR dB", ".2f"),
        ("psnr_motion", "PSNR mot", ".2f"),
        ("ssim", "SSIM", ".4f"),
        ("ssim_motion", "SSIM mot", ".4f"),
    ]
    cols += [(k, "IoU " + k[4:], ".3f") for k in iou_keys]
    cols += [("ms_per_frame", "ms/frame", ".1f")]

    def fmt(v: Any, spec: str) -> str:
        if v is None:
            return "-"
        if spec == "s":
            return str(v)
        try:
            fv = float(v)
        except (TypeError, ValueError):
            return str(v)
        return "inf" if math.isinf(fv) else format(fv, spec)

    cells = [[fmt(r.get(k), spec) for k, _, spec in cols] for r in rows]
    heads = [h for _, h, _ in cols]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, h in enumerate(heads)]
    left = {0, 1}

    def line(vals: Sequence[str]) -> str:
        return "  ".join(
            v.ljust(w) if i in left else v.rjust(w)
            for i, (v, w) in enumerate(zip(vals, widths, strict=True))
        ).rstrip()

    out = [line(heads), line(["-" * w for w in widths])]
    out += [line(c) for c in cells]
    return "\n".join(out)
