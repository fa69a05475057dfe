"""The localisers' names (DESIGN section 4), declared once: the core's factory, the API's
request models and the command line all take their lists from here.

=============  ==============================================================
mode           behaviour
=============  ==============================================================
hybrid         particle filter switching between global features and SIFT
global, sift   particle filter with one feature type only (Weiss's baselines)
hierarchical   Li: hue-histogram top-k candidates, then SIFT against each
retrieval      Flyphone: nearest map image under a chosen feature and measure
=============  ==============================================================

Nothing else is imported here, so a caller pays for no numerics to read the names.
"""

MODES = ("hybrid", "global", "sift", "hierarchical", "retrieval")
"""Every localiser a session may use, the default first."""
FILTER_MODES = ("hybrid", "global", "sift")
"""The particle filter's modes: the ones that take its parameters."""
