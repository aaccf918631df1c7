"""CFSR, laid out by the paper's stages ("Coarse-to-Fine High-Speed Motion Scene Reconstruction
with Region-Adaptive-Based Spike Distinction"); registers the methods ``csr`` and ``cfsr``.

Read it in this order; :func:`cfsr.methods.cfsr.pipeline.fine_stage` runs the stages for one
output step t (rates in spikes per step, masks bool ``(H, W)``).

======================  ==============================================  ==========================
paper                   function                                        module
======================  ==============================================  ==========================
Eq. 3 TFI               :func:`cfsr.methods.tfi.tfi_rate`,              ``tfi`` (baseline),
                        :func:`~.history.tfi_at`                        ``history``
Eq. 4 TFP               :func:`cfsr.methods.tfp.tfp_rate`               ``tfp`` (baseline)
Eq. 5-6 coarse          :func:`~.distinction.distinct_isi_counts`,      ``distinction``
distinction             :func:`~.distinction.coarse_masks`
Eq. 5-7 CSR (coarse     :func:`~.coarse.csr_frames`,                    ``coarse``
reconstruction)         the history scan :func:`~.history.history_scan` ``history``
Eq. 7 ATSR              :func:`~.atsr.atsr_alpha`, :func:`~.atsr.atsr_fuse`  ``atsr``
Eq. 8-9 MOG objects     :func:`~.mog.mog_background`,                   ``mog``, ``fine_mask``
                        :func:`~.mog.mog_objects`,
                        :func:`~.fine_mask.moving_objects`
Eq. 10-14 DAISI edges   :func:`~.daisi.daisi_strength`,                 ``daisi``
                        :func:`~.daisi.daisi_from_times` (Eq. 12-13)
fine mask (cue union)   :func:`~.fine_mask.fine_mask`,                  ``fine_mask``
                        :func:`~.fine_mask.fine_region`
PatchMatch refinement   :func:`~.refinement.patchmatch_refine`,         ``refinement``,
                        :func:`~.patchmatch.patchmatch_fuse`,           ``patchmatch``,
                        :func:`~.patchmatch_frames.pm_frames`           ``patchmatch_frames``
fusion (Eq. 7 again)    :func:`~.fusion.refine_stage`                   ``fusion``
======================  ==============================================  ==========================

What this project adds beyond the paper, each in its own module: the steady-interval
distinction and static check (``steady_distinction``), the static gate and its tiles
(``static_gate``), still pixels (``still_pixels``), slow-motion windows (``slow_motion``),
two-sided Eq. 9 (``mog_two_sided``), carried work between close outputs (``carry``) and quality
tiers (``tiers``). The parameters are in ``params`` (the one source of defaults, units and
ranges), the typed settings every stage reads in ``settings``, the compiled scans in the
private ``_history_kernels`` and ``_patchmatch_kernels``.

Where our defaults differ from the paper (the ``paper`` preset restores the paper's; measured on
the simulator scenes and the REDS files, docs/methods.md):

==================  =============  ===============  ==============================================
setting             paper          our default      why
==================  =============  ===============  ==============================================
``distinction``     ``isi_set``    ``steady``       Eq. 6 counts distinct ISIs of a static pixel
                    (Eq. 5-6)                       as noise grows; the steady-interval test
                                                    tells a changed rate from jitter
``static_           ``tfp``        ``steady``       the TFP static estimate, kept only where t's
estimator``         (Eq. 4)                         own interval agrees (a mover the
                                                    distinction missed keeps its TFI)
``tfp_mode``        trailing       centred          a trailing span lags a slow drift by 80 steps
``mog_sides``       ``past``       ``both``         Eq. 9 against the past alone marks ghosts and
                                                    a mover's trail (two-sided Eq. 9)
``still_reach``     0 (none)       380 steps        proven-static pixels leave the fine mask and
                                                    take their exact rate (fan IoU 0.46 -> 0.93)
``slow_reach``      0 (none)       128 steps        slow movers get windows as long as their
                                                    motion allows
``pm_guide``,       TFI, no blur   TFA over 3       matching on raw TFI locks onto noise; a
``pm_sigma``                       intervals,       lightly smoothed guide matches, raw values
                                   sigma 1          are averaged
``pm_h``            0 (plain       0.015            non-local-means weights: wrong matches weigh
                    average)                        less (REDS +0.24 dB)
``pm_step``,        5 x 10         2 x 24           the same reach with more samples near t
``pm_count``                                        (REDS +0.23 dB)
``phi0``, ``phi``,  50, 4,         20, 0.75,        calibrated on the simulator: phi = 4 cannot
``daisi_span``      at t           t +- 5           fire with natural logs for realistic ISIs
``T``, ``theta``    400, 6         300, 8           Eq. 5-6 calibrated on the simulator scenes
==================  =============  ===============  ==============================================
"""

from cfsr.methods.cfsr import pipeline  # noqa: F401  (registers csr and cfsr)
