"""The settings of the novel-view renders (``surfphase render-views``) and their
defaults, kept apart from :mod:`surfphase.views` so that they import without torch.
:mod:`surfphase.views` holds them as its ``DEFAULTS``; the workflow sets them from the
config's ``refine:`` block (``workflow/rules/views_common.smk``).
"""

from __future__ import annotations

DEFAULTS: dict = {
    "n_views": 11,  # orbit views orbit01 … orbitNN
    "step_deg": 30.0,  # azimuth step between consecutive views, degrees about lab +y
    "reference": None,  # input camera the orbit starts from (None: the fit's first)
}

#: The config's ``refine:`` block and its defaults (read by ``workflow/rules/views_common.smk``;
#: the schema holds only the types): the orbit views, the SDEdit strength of the views
#: near the input cameras and of the ``far_views`` (orbit numbers), and the seed.
REFINE_DEFAULTS: dict = {
    "enabled": False,  # True: views → prior → refine → stage-2 fit (needs prior.clips)
    "n_views": DEFAULTS["n_views"],
    "step_deg": DEFAULTS["step_deg"],
    "reference_camera": DEFAULTS["reference"],
    "strength_near": 0.2,
    "strength_far": 0.35,
    "far_views": [4, 5, 6, 7, 8],  # far from both input cameras (stage 2 weights them less)
    "seed": 0,
}
