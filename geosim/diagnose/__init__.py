"""Mismatch diagnosis: where the paper's model and a real satellite scene differ, which
physics the model left out, and how much the fit improves once it is modelled.

Modules: :mod:`~geosim.diagnose.spectra` (Welch cross-spectra, transfer function,
coherence, spectral error), :mod:`~geosim.diagnose.coregister` (sub-pixel shift),
:mod:`~geosim.diagnose.effects` (the catalogue), :mod:`~geosim.diagnose.fit`
(joint Q + effects fit), :mod:`~geosim.diagnose.select` (evidence: block
cross-validation and effect size), :mod:`~geosim.diagnose.noise` (white noise floor),
:mod:`~geosim.diagnose.model` (typed forward model and claims),
:mod:`~geosim.diagnose.simulate` (the paper's model at any Q),
:mod:`~geosim.diagnose.locate` (maps and regions), :mod:`~geosim.diagnose.engine`
(the whole diagnosis on arrays; each stage in a ``stage_*`` module, see the code map in
``docs/diagnosis.md``), :mod:`~geosim.diagnose.report` (with ``report_figures``,
``report_markdown``, ``truth_compare``), :mod:`~geosim.diagnose.grids`,
:mod:`~geosim.diagnose.flights` and
:mod:`~geosim.diagnose.steps` (files).
"""
