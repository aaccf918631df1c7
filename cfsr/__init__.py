"""cfsr: spike-camera reconstruction (CFSR and baselines), spike files, simulator and metrics.

Units: time is a step index (1 step = 25 us at 40 kHz); intensities are firing rates in spikes
per step (0..1); :func:`to_display` maps them to 0..255. This package imports nothing of the
camera stack (pyusb, FastAPI) and never imports ``driver``, ``replay`` or ``service``.
"""

from cfsr import methods  # the package, callable: cfsr.methods() describes every method
from cfsr.api import reconstruct, reconstruct_outputs
from cfsr.datfile import (
    DatWriter,
    SpikeFileError,
    read_dat,
    read_npz,
    read_sidecar,
    read_spikes,
    write_dat,
)
from cfsr.display import to_display
from cfsr.layout import DEFAULT_LAYOUT, STEP_RATE_HZ, Layout
from cfsr.methods import Output, get_method
from cfsr.spikes import SpikeRecording, as_recording
from cfsr.streaming import StreamingReconstructor

__version__ = "0.1.0"

__all__ = [
    "DEFAULT_LAYOUT",
    "STEP_RATE_HZ",
    "DatWriter",
    "Layout",
    "Output",
    "SpikeFileError",
    "SpikeRecording",
    "StreamingReconstructor",
    "as_recording",
    "get_method",
    "methods",
    "read_dat",
    "read_npz",
    "read_sidecar",
    "read_spikes",
    "reconstruct",
    "reconstruct_outputs",
    "to_display",
    "write_dat",
]
