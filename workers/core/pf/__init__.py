"""The particle filter of Weiss et al. 2008, section IV-A, split as nav2's AMCL splits it.

- :mod:`.config`: parameters and the named configurations (``weiss2008``, ``default``)
- :mod:`.resampling`: pure ``weights -> indexes`` resamplers
- :mod:`.motion`: the motion model (Gaussian diffusion, pull towards the nearest map image,
  optional velocity), scaled by the time between frames
- :mod:`.measurement`: similarities -> particle likelihoods
- :mod:`.filter`: the particle arrays, one filter step, estimate statistics, serialisable state
"""

from .config import CONFIGS, FilterConfig, config_from_params
from .filter import ParticleFilter

__all__ = ["CONFIGS", "FilterConfig", "ParticleFilter", "config_from_params"]
