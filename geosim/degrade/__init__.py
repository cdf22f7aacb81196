"""Satellite degradation of UAV tiles and its calibration against a real scene.

Modules
-------
core
    Pure kernels: ``degrade_array`` (I_sat = (I_uav ⊛ PSF(Q)) ↓φ, bicubic; methods
    ``"reference"`` and ``"fast"``), ``blur``, ``fill_invalid``, ``to_dtype``,
    ``SpectralDegrader`` (many Q on one image).
blur
    The paper's blur metric: ``PAPER_LAPLACIAN``, ``to_grey``, ``laplacian_variance``.
calibrate
    LV as a function of Q and the bracketed root finder: ``lv_of_degraded``,
    ``lv_curve``, ``calibrate_q``, ``solve_q``, ``build_blocked_lv``.
steps
    The pipeline steps (I/O): ``run_calibrate`` and ``run_degrade``.
plot
    ``calibration.png``.

The PSF itself is in :mod:`geosim.physics.psf`, its OTF in :mod:`geosim.physics.otf`.
"""
