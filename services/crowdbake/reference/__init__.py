"""Test oracles and numpy twins: what the bake's shaders and crowdview's shader are tested against, never
what a bake ships (no module outside this package imports it; services/tests/test_reference_isolation.py).
It sits above the modules it mirrors (bake, render, stages) and imports them; none imports it.

- triangle_ids: pyrender's visibility buffer, which triangle covers each texel centre (drawn with GL);
- coverage: those triangle-id renders resolved exactly in float64, and the per-texel interpolation
  built on it;
- impostor_maps: the impostor maps computed exactly per texel in float64 (the reference of
  crowdbake.render.map_shader);
- mesh_reference: the mesh shaded per sample and box-filtered (the reference of the shader's fidelity
  references);
- impostor_blend, impostor_warp: crowdview's impostor shader in numpy (blending the views and frames
  crowdbake.bake.view_blend chooses, the reprojection warp);
- runtime_picture: a bundle's maps decoded and drawn by impostor_blend and impostor_warp (the reference of
  crowdbake.render.runtime_shader).

A real bake's maps come from crowdbake.render.map_shader and its pictures from crowdbake.render.runtime_shader.
"""
