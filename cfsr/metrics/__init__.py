"""Image-quality metrics for reconstructions (skimage.metrics style: pure functions).

Full-reference (against simulator ground truth): :func:`psnr`, :func:`ssim` (whole frame or
inside a mask, e.g. the true motion region), :func:`mask_iou` for dynamic-pixel masks.
No-reference (real data, CFSR paper Table 1): :func:`std_metric` (grey-level standard
deviation, a contrast measure) and :func:`cpbd` (Narvekar & Karam 2011). Both no-reference
metrics reward noise; report them beside PSNR/SSIM.

Images are in display units (grey levels 0..255) unless a ``data_range`` says otherwise.
"""

from cfsr.metrics.noref import cpbd, std_metric
from cfsr.metrics.reference import mask_iou, psnr, ssim

__all__ = ["cpbd", "mask_iou", "psnr", "ssim", "std_metric"]
