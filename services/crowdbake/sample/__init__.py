"""Procedural sample content: a clothed walking character made entirely by code.

It stands in for what users bring (a skinned character from a DCC tool, cloth from an offline
simulator) and goes through the same input formats: glTF 2.0 (.glb), PC2 + OBJ, PNG textures.

    regions    colour-region codes carried in texture alpha (alpha = 17 * code)
    humanoid   skeleton, body mesh with UVs and skin weights, for each build (standard, heavy, slim)
    colliders  the collision capsules fitted inside the body, and their motion
    walk       the walk- and run-in-place cycles as glTF keyframe channels
    idle       standing idle: a weight shift and a breath, as glTF keyframe channels
    clips      a sequence of clips blended one into the next, and its timeline.json
    garments   the loose and the tight skirt: cut, UVs, pinned waistband
    cloth_sim  the position-based cloth simulator and its measures (settling, stretch, penetration)
    textures   8 diffuse variations and the outfit colour map
    generate   simulate_sample, simulate_clips_sample (in memory) and generate_sample (writes the files)

The command line is `crowdbake sample OUT_DIR` (crowdbake.cli.sample).
"""
