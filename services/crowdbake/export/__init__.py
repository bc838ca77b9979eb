"""Engine-ready output from a bundle: glTF 2.0 + vertex-animation textures + KTX2 + reference shaders.

`export_bundle(bundle_dir, out_dir)` (crowdbake.export.writer) writes the files docs/export.md
describes; the pure parts are `vat` (vertex-animation textures), `glb` (the glTF per LOD), `ktx2`
(the KTX 2.0 container) and `textures` (bundle textures as texel arrays).
"""
