"""Stage-1 fit (docs/method.md §5): SDF surfels, bubble-guided tracking, metric velocities.

* :mod:`surfphase.fit.model` — :class:`~surfphase.fit.model.SurfelModel` and
  :func:`~surfphase.fit.model.sdf_to_opacity` (``o = 4e^{−γf}/(1+e^{−γf})²``);
* :mod:`surfphase.fit.losses` — L1, SSIM/D-SSIM, normal consistency, the ``L_γ`` hinge,
  the projection loss;
* :mod:`surfphase.fit.densify` — densification strategies
  (:class:`~surfphase.fit.densify.Densify2DGS`, :class:`~surfphase.fit.densify.NoDensify`);
* :mod:`surfphase.fit.init` — surfel seeds on the visual hull of the masks, scene extent;
* :mod:`surfphase.fit.binding` — binding surfels to bubbles, centroids, velocities,
  advection, bubble tracks through id changes and merges;
* :mod:`surfphase.fit.register` — one rigid translation per bubble fitted to the new
  frame after the advection;
* :mod:`surfphase.fit.stage` — :func:`~surfphase.fit.stage.run_fit`, the checkpointed
  per-frame loop, and :data:`~surfphase.fit.stage.DEFAULTS` (every hyperparameter);
* :mod:`surfphase.fit.params` — the stages' settings and defaults (``DEFAULTS``,
  ``STAGE2_DEFAULTS``, ``FIT_OVERRIDES``), importable without torch;
* :mod:`surfphase.fit.stage2` — :func:`~surfphase.fit.stage2.run_fit_stage2`, the same
  loop restarted from the stage-1 surfels with the refined orbit views as weighted
  extra supervision (docs/method.md §9); :mod:`surfphase.bench.fit_stage2` times its steps;
* :mod:`surfphase.fit.outputs` — ``surfels.npz`` (format table), ``bubbles.csv``,
  ``curves.csv``, ``summary.json``, ``renders/``.

The benchmark ``surfphase bench fit`` lives in :mod:`surfphase.bench.fit`; it imports
:mod:`surfphase.synth` to build its ground truth, which no module of this package does.
"""
