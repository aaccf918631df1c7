"""CFSR, laid out by the paper's stages ("Coarse-to-Fine High-Speed Motion Scene Reconstruction
with Region-Adaptive-Based Spike Distinction"); registers the methods ``csr`` and ``cfsr``.

Read it in this order; :func:`cfsr.methods.cfsr.pipeline.fine_stage` runs the stages for one
output step t (rates in spikes per step, masks bool ``(H, W)``).

Paper equation -> function (module names relative to this package):

===============================  ==========================================================
paper                            function
===============================  ==========================================================
Eq. 3 TFI                        ``cfsr.methods.tfi.tfi_rate``; in CFSR ``history.tfi_at``
Eq. 4 TFP                        ``cfsr.methods.tfp.tfp_rate``
Eq. 5-6 coarse distinction       ``distinction.distinct_isi_counts``,
                                 ``distinction.coarse_masks``
Eq. 5-7 CSR (coarse stage)       ``coarse.csr_frames``; in CFSR ``history.history_scan``
Eq. 7 ATSR                       ``atsr.atsr_alpha``, ``atsr.atsr_fuse``,
                                 ``atsr.atsr_fuse_isi``
Eq. 8-9 MOG objects              ``mog.mog_background``, ``mog.mog_objects``,
                                 ``fine_mask.moving_objects``
Eq. 10-14 DAISI edges            ``daisi.daisi_strength``, ``daisi.daisi_from_times``
                                 (the three-ISI form, Eq. 12-13)
fine mask (union of the cues)    ``fine_mask.fine_mask``, ``fine_mask.fine_region``
PatchMatch refinement            ``refinement.patchmatch_refine``,
                                 ``patchmatch.patchmatch_fuse``,
                                 ``patchmatch_frames.pm_frames``
fusion (Eq. 7, the fine region)  ``fusion.refine_stage``
the whole method                 ``pipeline.fine_stage``
===============================  ==========================================================

What this project adds beyond the paper, each in its own module: the steady-interval
distinction and static check (``steady_distinction``), the static gate and its tiles
(``static_gate``), still pixels (``still_pixels``), slow-motion windows (``slow_motion_windows``),
two-sided Eq. 9 (``mog_two_sided``), carried work between close outputs (``carry``) and quality
tiers (``tiers``). The parameters are in ``params`` (the one source of defaults, units and
ranges), the typed settings every stage reads in ``settings``, the compiled scans in the
private ``_history_kernels`` and ``_patchmatch_kernels``.

Where our defaults differ from the paper (the ``paper`` preset restores the paper's; measured on
the simulator scenes and the REDS files, docs/methods.md):

====================  ===============  ===========  =============================================
setting               paper            our default  why
====================  ===============  ===========  =============================================
``distinction``       ``isi_set``      ``steady``   a dark static pixel shows more ISI lengths
                      (Eq. 5-6)                     than bright moving texture: no theta splits
                                                    them; the interval spread near t does
                                                    (coarse IoU disk 0.44 -> 0.67, fan 0.08 ->
                                                    0.68)
``static_estimator``  ``tfp`` (Eq. 4)  ``steady``   the span's first-to-last-spike rate (CFSR's
                                                    static scene 54.3 dB against 45.7 with the
                                                    TFP), kept only where t's own interval
                                                    agrees: a mover the masks missed keeps its
                                                    TFI
``tfp_mode``          trailing         centred      a trailing span lags a slow drift by 80 steps
``mog_sides``         ``past``         ``both``     Eq. 9 against the past alone marks ghosts and
                                                    a mover's trail (two-sided Eq. 9)
``still_reach``       0 (none)         380 steps    proven-static pixels leave the fine mask and
                                                    take their exact rate (fan IoU 0.46 -> 0.93)
``slow_reach``        0 (none)         128 steps    slow movers get windows as long as their
                                                    motion allows
``pm_guide``,         TFI, no blur     TFA over 3   matching on raw TFI locks onto noise; a
``pm_sigma``                           intervals,   lightly smoothed guide matches, raw values
                                       sigma 1      are averaged
``pm_h``              0 (plain         0.015        non-local-means weights: wrong matches weigh
                      average)                      less (REDS +0.24 dB)
``pm_step``,          5 x 10           2 x 24       the same reach with more samples near t
``pm_count``                                        (REDS +0.23 dB)
``phi0``, ``phi``,    50, 4, at t      20, 0.75,    calibrated on the simulator: phi = 4 cannot
``daisi_span``                         t +- 5       fire with natural logs for realistic ISIs
``T``, ``theta``      400, 6           300, 8       Eq. 5-6 calibrated on the simulator scenes
====================  ===============  ===========  =============================================
"""

from cfsr.methods.cfsr import pipeline  # noqa: F401  (registers csr and cfsr)
