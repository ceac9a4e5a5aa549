"""Bubble instance masks: segmentation backends, association across views and time.

* :mod:`surfphase.masks.classical` — the embedded default segmenter (background
  estimate, threshold, hole filling, watershed split, minimum area);
* :mod:`surfphase.masks.sam_onnx` — Segment Anything through ONNX Runtime, with the
  automatic mask generation post-processing of :mod:`surfphase.masks.amg`;
* :mod:`surfphase.masks.associate` — per-view tracking through time and association
  of tracks across views into bubble ids (0 = nucleation region at the heated plate);
* :mod:`surfphase.masks.stage` — the ``mask`` stage of one session;
* :mod:`surfphase.masks.overlay` — overlay pictures for the report.
"""
