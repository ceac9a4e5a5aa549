"""Synthetic pool-boiling campaigns with exact ground truth (``surfphase synth``).

* :mod:`surfphase.synth.rig` — true cameras of the reference rig;
* :mod:`surfphase.synth.bubbles` — bubble life cycles and the scene's signed distance field;
* :mod:`surfphase.synth.shadowgraph` — sphere tracing of that field into backlit images;
* :mod:`surfphase.synth.groundtruth` — bubble table, volumes and meshes of the true field;
* :mod:`surfphase.synth.monoclips` — uncalibrated monocular clips for the video prior;
* :mod:`surfphase.synth.charuco` — ChArUco calibration images;
* :mod:`surfphase.synth.campaign` — a whole campaign on disk (``write_campaign``).

Nothing here uses the reconstruction's code (renderer, fit): the truth stays
independent of what it judges.
"""
