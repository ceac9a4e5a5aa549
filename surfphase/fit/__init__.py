"""Stage-1 and stage-2 fits (docs/method.md §5, §9): SDF surfels, bubble-guided tracking,
metric velocities.

The entry points:

* :mod:`surfphase.fit.stage` — :func:`~surfphase.fit.stage.run_fit`, the stage-1 fit,
  and :data:`~surfphase.fit.stage.DEFAULTS` (every hyperparameter);
* :mod:`surfphase.fit.stage2` — :func:`~surfphase.fit.stage2.run_fit_stage2`, the same
  loop restarted from the stage-1 surfels with the refined orbit views as weighted
  extra supervision; :mod:`surfphase.bench.fit_stage2` times its steps;
* :mod:`surfphase.fit.params` — the stages' settings and defaults (``DEFAULTS``,
  ``STAGE2_DEFAULTS``, ``FIT_OVERRIDES``), importable without torch.

The frame loop both fits run, by topic:

* :mod:`surfphase.fit.loop` — :func:`~surfphase.fit.loop.run_frames`: per frame
  prepare → fit → finish, checkpointed;
* :mod:`surfphase.fit.session` — the session's frames, masks, cameras, merges, anchors;
* :mod:`surfphase.fit.viewset` — the views a frame is fitted to (inputs, or inputs plus
  refined views with their weights and sampler);
* :mod:`surfphase.fit.backgrounds` — the per-view background images;
* :mod:`surfphase.fit.seeding` — surfels on the visual hull (frame 0, new bubbles);
* :mod:`surfphase.fit.guidance` — advection, registration, merged bubbles re-seeded;
* :mod:`surfphase.fit.optimise` — one frame's Adam steps and the losses' sum;
* :mod:`surfphase.fit.bounds` — the depth bound along the poorly seen axis;
* :mod:`surfphase.fit.record` — the typed per-frame record, persistent surfel ids;
* :mod:`surfphase.fit.checkpoint` — per-frame checkpoints and the run key.

The pieces under them:

* :mod:`surfphase.fit.model` — :class:`~surfphase.fit.model.SurfelModel` and
  :func:`~surfphase.fit.model.sdf_to_opacity` (``o = 4e^{−γf}/(1+e^{−γf})²``);
* :mod:`surfphase.fit.losses` — L1, SSIM/D-SSIM, normal consistency, the ``L_γ`` hinge,
  the projection loss;
* :mod:`surfphase.fit.fused_losses` — the photometric term (L1 + D-SSIM per view), the
  normal consistency and the projection loss as numba kernels with hand-written
  backward passes, used on the CPU;
* :mod:`surfphase.fit.densify` — densification strategies, one
  :class:`~surfphase.fit.densify.Strategy` interface
  (:class:`~surfphase.fit.densify.Densify2DGS`, :class:`~surfphase.fit.densify.NoDensify`);
* :mod:`surfphase.fit.init` — surfel seeds on the visual hull of the masks, scene extent;
* :mod:`surfphase.fit.binding` — binding surfels to bubbles, centroids, velocities,
  advection, bubble tracks through id changes and merges;
* :mod:`surfphase.fit.register` — one rigid translation per bubble fitted to the new
  frame after the advection;
* :mod:`surfphase.fit.outputs` — ``surfels.npz`` (format table), ``bubbles.csv``,
  ``curves.csv``, ``summary.json``, ``renders/``.

The benchmark ``surfphase bench fit`` lives in :mod:`surfphase.bench.fit`; it imports
:mod:`surfphase.synth` to build its ground truth, which no module of this package does.
"""
