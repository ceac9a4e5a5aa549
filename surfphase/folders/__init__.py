"""The folders passed between stages, each with its one reader and writer (the contract
between stages):

* :mod:`~surfphase.folders.ingest` — frame stacks, cameras, ``meta.json``;
* :mod:`~surfphase.folders.masks` — label stacks, instances, events, anchors;
* :mod:`~surfphase.folders.views` — rendered orbit views and refined views;
* :mod:`~surfphase.folders.fit` — readers of the fit's outputs (it writes them:
  :mod:`surfphase.fit.outputs`);
* :mod:`~surfphase.folders.frames` — stored frames → float32 in [0, 1], from their
  declared dtype or bit depth.

A reader validates its folder once; every error names the file and the session.
"""
