"""The particle filter of Weiss et al. 2008, section IV, split as nav2's AMCL splits it.

- :mod:`.config`: parameters in parts and the named configurations (``weiss2008``,
  ``default``)
- :mod:`.resampling`: pure ``weights -> indexes`` resamplers
- :mod:`.motion`: the motion model (Gaussian diffusion, pull towards the nearest map image,
  optional velocity), scaled by the time between frames
- :mod:`.measurement`: measurement models, what was measured -> particle log-likelihoods
- :mod:`.filter`: the particle arrays, one filter step, estimate statistics, serialisable state
- :mod:`.clusters`: the cloud's clusters and the heaviest one's position
- :mod:`.switching`: the hybrid rule (IV-B) choosing each step's feature type, as a pure policy
"""

from .config import CONFIGS, FilterConfig, config_from_params
from .filter import ParticleFilter

__all__ = ["CONFIGS", "FilterConfig", "ParticleFilter", "config_from_params"]
