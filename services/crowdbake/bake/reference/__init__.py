"""Test oracles and numpy twins: what the bake's shaders and crowdview's shader are tested against.

- impostor_maps: the impostor maps computed exactly per texel in float64 (the reference of
  crowdbake.render.map_shader);
- mesh_reference: the mesh shaded per sample and box-filtered (the reference of the shader's fidelity
  references);
- impostor_blend, impostor_warp: crowdview's impostor shader in numpy (view and frame blending, the
  reprojection warp), used by the tests and by the fidelity scores' pictures where no GL context draws them.

A real bake's maps come from crowdbake.render.map_shader and its pictures from crowdbake.render.runtime_shader.
"""
