"""crowdbake: bakes clothed characters into crowd-ready bundles.

Implements "Clothing the Masses: Real-Time Clothed Crowds With Variation"
(Dobbyn et al., 2006): cyclical cloth search, pose caches with two geometric
LODs, and UV-mapped impostors, published as verified, immutable bundles.
"""

__version__ = "0.1.0"
