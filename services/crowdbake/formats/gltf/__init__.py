"""Skinned, animated glTF 2.0 characters: read (.glb, .gltf) and write (.glb).

The document model is pygltflib's (typed dataclasses for nodes, accessors, materials...); compressed
geometry is decoded by DracoPy (KHR_draco_mesh_compression) and meshoptimizer
(EXT_meshopt_compression, its vertex, index and filter decoders); images by Pillow, KTX2
(KHR_texture_basisu) by Basis Universal's `basisu` tool. This module does
the parts no library does: checked accessor reads into numpy, the skin and its hierarchy, the
animation, and merging materials into what the bake consumes.

What is read (`load_character`):
  * every triangle primitive of every mesh node that uses the chosen skin, merged into one mesh (a mesh
    used by several nodes with that skin is read once: for a skinned mesh the node transform does not
    apply, so the copies would coincide); a mesh node *without* a skin that hangs under a joint (a hat
    under the head) is attached rigidly to that joint; other meshes are left out with a warning;
  * the skin's joints in `skin.joints` order (so JOINTS_0 indices are joint indices), their parents,
    rest TRS and inverse bind matrices;
  * one animation, chosen by index or name (`animation=`), its channels that target joints
    (translation / rotation / scale, LINEAR, STEP or CUBICSPLINE samplers);
  * each mesh's morph targets (POSITION and NORMAL displacements, named by extras.targetNames), the
    mesh's default weights and the animation's "weights" channels (crowdbake.formats.gltf.morphs);
    posing adds them to the bind pose before skinning (crowdbake.bake.skinning.pose_at_times);
  * every material the merged mesh uses: `Character.materials` (name, baseColorFactor, base colour
    texture) and `Character.vertex_materials` (index per vertex). `Character.texture` is what the bake
    samples: the one base colour texture times its factor when one material (or one texture and factor)
    covers the mesh, else an atlas of every material (texture times factor, or a flat tile of the
    factor's colour) with the UVs moved into each material's tile. None when nothing is textured and
    every factor is white (the bake's default colour then).

A required extension this reader cannot honour is refused by name (KHR_texture_basisu too where
`basisu` is not installed, see crowdbake.formats.basisu). Extensions that are only *used* are ignored.

Transforms, as the glTF spec defines skinning: a skinned vertex is
``sum_k w_k * world(joint_k) @ inverseBind(joint_k) @ p``; the transform of the node that holds the
mesh is ignored, but the transforms of nodes *above* the skeleton (CesiumMan's Z-up to Y-up root,
for instance) are part of world(joint). `Character.joint_parent_transforms[j]` holds the static product
of the non-joint nodes between joint j and its parent joint (or the scene root), so
``world(j) = world(parent(j)) @ joint_parent_transforms[j] @ local(j)``. Animations of non-joint nodes
are not followed (a warning says so).

Texture coordinates are kept in glTF's convention: (0, 0) is the top-left of the image, v grows down.

Every offset and length in the file is checked before it is used (accessor extents against their
bufferView before anything is allocated, decompressed sizes against MAX_DECODED_VIEW_BYTES), so
truncated or garbled files raise ValueError naming the file and the problem. The node hierarchy is
walked once (linear in the node count: a 16,000-node chain loads in milliseconds).

The package, by job: document (GLB/JSON container, buffers, limits), accessors (typed accessor reads),
compression (Draco, meshopt), scene (node hierarchy, TRS matrices), meshes (primitives merged into one
mesh), morphs (morph targets and their weights), materials (base colour, atlas), animation (channels),
model (the dataclasses), reader (load_character and the skin), writer (encode_character, write_character).
"""
from crowdbake.formats.gltf.accessors import COMPONENT_TYPES, TYPE_WIDTHS
from crowdbake.formats.gltf.animation import INTERPOLATIONS, PATH_WIDTHS
from crowdbake.formats.gltf.compression import DRACO, MAX_DECODED_VIEW_BYTES, MESHOPT
from crowdbake.formats.gltf.document import (
    BASISU,
    CHUNK_BIN,
    CHUNK_JSON,
    GLB_MAGIC,
    GLB_VERSION,
    READABLE_REQUIRED_EXTENSIONS,
    _Document,
    parse_glb,
)
from crowdbake.formats.gltf.materials import ATLAS_GUTTER, FLAT_TILE, merge_material_textures, tinted_texture
from crowdbake.formats.gltf.meshes import (
    MIN_WEIGHT_SUM,
    MODE_TRIANGLE_FAN,
    MODE_TRIANGLE_STRIP,
    MODE_TRIANGLES,
    NORMAL_LENGTH_TOLERANCE,
    WEIGHT_SUM_TOLERANCE,
)
from crowdbake.formats.gltf.model import AnimationChannel, Character, Material, MorphTarget, WeightsChannel
from crowdbake.formats.gltf.reader import load_character
from crowdbake.formats.gltf.scene import decompose_matrix, matrix_to_quaternion, trs_matrix
from crowdbake.formats.gltf.writer import encode_character, write_character

__all__ = [
    "ATLAS_GUTTER",
    "BASISU",
    "CHUNK_BIN",
    "CHUNK_JSON",
    "COMPONENT_TYPES",
    "DRACO",
    "FLAT_TILE",
    "GLB_MAGIC",
    "GLB_VERSION",
    "INTERPOLATIONS",
    "MAX_DECODED_VIEW_BYTES",
    "MESHOPT",
    "MIN_WEIGHT_SUM",
    "MODE_TRIANGLES",
    "MODE_TRIANGLE_FAN",
    "MODE_TRIANGLE_STRIP",
    "NORMAL_LENGTH_TOLERANCE",
    "PATH_WIDTHS",
    "READABLE_REQUIRED_EXTENSIONS",
    "TYPE_WIDTHS",
    "WEIGHT_SUM_TOLERANCE",
    "AnimationChannel",
    "Character",
    "Material",
    "MorphTarget",
    "WeightsChannel",
    "_Document",
    "decompose_matrix",
    "encode_character",
    "load_character",
    "matrix_to_quaternion",
    "merge_material_textures",
    "parse_glb",
    "tinted_texture",
    "trs_matrix",
    "write_character",
]
