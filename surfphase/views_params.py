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
