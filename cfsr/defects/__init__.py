"""Hot and dead pixels: found from the spike stream, corrected before any reconstruction.

* :class:`DefectMap`: the map (upright hot/dead masks), its JSON form for a sidecar or a
  calibration file (:func:`save_map`, :func:`load_map`).
* :class:`DefectEstimator`, :func:`classify`: the online estimate from spike counts.
* :class:`DefectCorrector`: learns and corrects blocks pushed into a
  :class:`~cfsr.streaming.StreamingReconstructor` (the live path).
* :func:`corrected`: a recording read through the correction (the offline path).
* :func:`calibrate`, :class:`GainMap`: a flat-field calibration, the map and every pixel's
  gain (threshold spread), which is divided out of every method's output.
* :func:`score_map`: precision and recall against a true map (the simulator's).
"""

from cfsr.defects.correct import (
    CorrectedRecording,
    DefectCorrector,
    DonorPlan,
    calibrate,
    correct_packed,
    corrected,
    estimate_map,
    in_buffer,
    map_of,
    plan_donors,
    with_defects,
)
from cfsr.defects.defect_map import (
    DEFECTS_KEY,
    DefectMap,
    load_map,
    save_map,
    write_to_sidecar,
)
from cfsr.defects.estimate import DefectEstimator, DefectParams, classify
from cfsr.defects.gain import GainMap, flatten, gain_from_counts
from cfsr.defects.score import score_map

__all__ = [
    "DEFECTS_KEY",
    "CorrectedRecording",
    "DefectCorrector",
    "DefectEstimator",
    "DefectMap",
    "DefectParams",
    "DonorPlan",
    "GainMap",
    "calibrate",
    "classify",
    "correct_packed",
    "corrected",
    "estimate_map",
    "flatten",
    "gain_from_counts",
    "in_buffer",
    "load_map",
    "map_of",
    "plan_donors",
    "save_map",
    "score_map",
    "with_defects",
    "write_to_sidecar",
]
