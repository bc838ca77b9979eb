"""Engine-ready output from a bundle: glTF 2.0 + vertex-animation textures + KTX2 + reference shaders and
engine setups (Godot, Unity, Unreal).

`export_bundle(bundle_dir, out_dir)` (crowdbake.export.writer) writes the files docs/export.md
describes; the pure parts are `animations` (one per clip and per transition: the keys the glTF, the
VAT shaders and export.json share), `vat` (vertex-animation textures), `glb` (the glTF per LOD, quantized),
`cloth_bones` (a garment's loop as skinning bones, `--cloth-bones`), `ktx2` (the KTX 2.0 container,
zstd-supercompressed) and `textures` (bundle textures as texel arrays).
"""
