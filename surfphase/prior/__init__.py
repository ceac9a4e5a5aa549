"""Video diffusion priors and SDEdit refinement of novel-view videos.

Backends: ``embedded`` (a small rectified-flow video U-Net trained from scratch on the
campaign's monocular clips, :mod:`.embedded`) and ``wan`` (Wan 2.1 through diffusers,
LoRA fine-tuned, :mod:`.wan`), behind :class:`.interface.VideoPrior`.
"""

from surfphase.prior.interface import VideoPrior, check_video, load_prior, new_prior

__all__ = ["VideoPrior", "check_video", "load_prior", "new_prior"]
