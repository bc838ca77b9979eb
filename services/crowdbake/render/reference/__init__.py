"""Test oracles that draw with GL: what the bake's shaders are tested against, never what a bake ships.

- triangle_ids: pyrender's visibility buffer (which triangle covers each texel centre), from which
  crowdbake.bake.reference resolves the exact float64 maps and references.
"""
