@tool
extends EditorScript
## crowdbake export -> Godot 4 scenes that play the cloth from vertex-animation textures (VATs).
##
## Copy the whole export folder into the project (res://), let Godot import the .glb files, open this
## file in the Script editor and run it (File > Run). For every LOD it writes, into crowdbake/ beside
## export.json: the VATs as float textures, one ShaderMaterial per part (shaders/crowdbake_vat.gdshader
## with every uniform set from export.json) and character_lod<k>.tscn, the .glb's scene with those
## materials on its parts. The scene root keeps export.json's `animations` as the metadata
## "crowdbake_animations", for game code that switches clip (set the range_* uniforms from one's `vat`).
##
## The VATs are read from their KTX2 files, not PNGs: Godot's PNG importer keeps 8 bits a channel
## (positions would step by millimetres), so the 16-bit texels go into RGBAF images, which hold every
## 16-bit value exactly.

## The animation the materials play: export.json animations[].name; "" plays the first (a clip).
const ANIMATION := ""
const OUT_FOLDER := "crowdbake"
const SHADER := "shaders/crowdbake_vat.gdshader"

# KTX 2.0 (Khronos KTX File Format Specification 2.0, section 3): byte offsets of the header fields read here.
const KTX2_VK_FORMAT := 12
const KTX2_WIDTH := 20
const KTX2_HEIGHT := 24
const KTX2_SUPERCOMPRESSION := 44
const KTX2_LEVEL0 := 80  # byteOffset, byteLength, uncompressedByteLength, 8 bytes each
const KTX2_ZSTD := 2
const VK_FORMAT_R16G16B16A16_UNORM := 91

# The VAT textures saved so far, by their .res path: LODs that read one file share one texture.
var saved_vats := {}


func _run() -> void:
	var root: String = get_script().resource_path.get_base_dir().get_base_dir()
	var sidecar := read_sidecar(root.path_join("export.json"))
	if sidecar.is_empty():
		return
	var animation := pick_animation(sidecar["animations"], ANIMATION)
	if animation.is_empty():
		push_error("crowdbake: no animation named '%s' in export.json" % ANIMATION)
		return
	var shader := load(root.path_join(SHADER)) as Shader
	if shader == null:
		push_error("crowdbake: %s does not load" % root.path_join(SHADER))
		return
	var out := root.path_join(OUT_FOLDER)
	DirAccess.make_dir_recursive_absolute(out)
	for lod in sidecar["lods"]:
		build_lod(root, out, lod, sidecar["animations"], animation, shader)
	EditorInterface.get_resource_filesystem().scan()


func read_sidecar(path: String) -> Dictionary:
	var parsed = JSON.parse_string(FileAccess.get_file_as_string(path))
	if not parsed is Dictionary or parsed.get("format") != "crowdbake-export":
		push_error("crowdbake: %s is not a crowdbake export.json" % path)
		return {}
	return parsed


func pick_animation(animations: Array, name: String) -> Dictionary:
	for animation in animations:
		if name == "" or animation["name"] == name:
			return animation
	return {}


## One LOD: each part's material and VATs, then the .glb's scene with them saved as character_lod<k>.tscn.
func build_lod(root: String, out: String, lod: Dictionary, animations: Array, animation: Dictionary, shader: Shader) -> void:
	var scene := load(root.path_join(lod["glb"])) as PackedScene
	if scene == null:
		push_error("crowdbake: %s is not imported yet (let the FileSystem dock import it, then run again)" % lod["glb"])
		return
	var character := scene.instantiate()
	character.set_meta("crowdbake_animations", animations)
	for part in lod["parts"]:
		var mesh := character.find_child(part["part"], true, false) as MeshInstance3D
		if mesh == null:
			push_error("crowdbake: %s has no mesh node named %s" % [lod["glb"], part["part"]])
			continue
		if not part.has("node"):  # exported with --cloth-bones: a skinned mesh that plays its own bones
			continue
		var stem := "%s_lod%d" % [part["part"], int(lod["lod"])]
		var material := vat_material(shader, part, animation)
		var vat: Dictionary = part["vat"]
		material.set_shader_parameter("vat_texture", save_vat(root, out, vat["texture"]["ktx2"]))
		if vat["kind"] == "skin":  # a skinned body: its joints' matrices per pose frame
			material.set_shader_parameter("vat_joints", save_vat(root, out, vat["joints"]["ktx2"]))
		var look := mesh.get_active_material(0) as BaseMaterial3D  # the glTF's own material: look_0's base colour
		if look != null:
			material.set_shader_parameter("albedo_texture", look.albedo_texture)
		ResourceSaver.save(material, out.path_join(stem + ".material.tres"), ResourceSaver.FLAG_CHANGE_PATH)
		mesh.material_override = material
	var packed := PackedScene.new()
	packed.pack(character)
	ResourceSaver.save(packed, out.path_join("character_lod%d.tscn" % int(lod["lod"])))
	character.free()


## A part's ShaderMaterial: its VAT layout (lods[].parts[].vat), its quantized mesh's node
## (lods[].parts[].node) and the range of pose frames the animation plays (animations[].vat).
func vat_material(shader: Shader, part: Dictionary, animation: Dictionary) -> ShaderMaterial:
	var vat: Dictionary = part["vat"]
	var node: Dictionary = part["node"]
	var played: Dictionary = animation["vat"]
	var material := ShaderMaterial.new()
	material.shader = shader
	material.set_shader_parameter("bounds_min", vector3(vat["bounds_min"]))
	material.set_shader_parameter("bounds_max", vector3(vat["bounds_max"]))
	material.set_shader_parameter("rows_per_frame", int(vat["rows_per_frame"]))
	material.set_shader_parameter("skinned", 1 if vat["kind"] == "skin" else 0)
	if vat["kind"] == "skin":
		var joints: Dictionary = vat["joints"]
		material.set_shader_parameter("joint_rows_per_frame", int(joints["rows_per_frame"]))
		material.set_shader_parameter("joint_min", vector4(joints["min"]))
		material.set_shader_parameter("joint_max", vector4(joints["max"]))
	material.set_shader_parameter("frames_per_second", float(vat["frames_per_second"]))
	material.set_shader_parameter("range_first", int(played["first_frame"]))
	material.set_shader_parameter("range_frames", int(played["frames"]))
	material.set_shader_parameter("range_loop", int(played["loop"]))
	material.set_shader_parameter("range_before", int(played["before_frame"]))
	material.set_shader_parameter("range_after", int(played["after_frame"]))
	material.set_shader_parameter("node_translation", vector3(node["translation"]))
	material.set_shader_parameter("node_scale", float(node["scale"]))
	return material


func vector3(values: Array) -> Vector3:
	return Vector3(values[0], values[1], values[2])


func vector4(values: Array) -> Vector4:
	return Vector4(values[0], values[1], values[2], values[3])


## The VAT at `path` (export.json's, relative to the export) as a texture saved in `out` under its own name
## (.res), once: LODs that read the same file share it. null (after an error) when it does not read.
func save_vat(root: String, out: String, path: String) -> ImageTexture:
	var target := out.path_join(path.get_file().get_basename() + ".res")
	if saved_vats.has(target):
		return saved_vats[target]
	var image := read_vat_ktx2(root.path_join(path))
	if image == null:
		return null
	var texture := ImageTexture.create_from_image(image)
	ResourceSaver.save(texture, target, ResourceSaver.FLAG_CHANGE_PATH)
	saved_vats[target] = texture
	return texture


## The one level of a crowdbake VAT KTX2 (zstd-supercompressed RGBA16 unorm) as an RGBAF Image: a 32-bit
## float holds each q / 65535 exactly (the shader reads the octahedral normal word and joint indices from them).
func read_vat_ktx2(path: String) -> Image:
	var data := FileAccess.get_file_as_bytes(path)
	if data.size() < KTX2_LEVEL0 + 24:
		push_error("crowdbake: %s is too short for a KTX2 file" % path)
		return null
	var width := data.decode_u32(KTX2_WIDTH)
	var height := data.decode_u32(KTX2_HEIGHT)
	var offset := data.decode_u64(KTX2_LEVEL0)
	var length := data.decode_u64(KTX2_LEVEL0 + 8)
	var texel_bytes := data.decode_u64(KTX2_LEVEL0 + 16)
	var level := data.slice(offset, offset + length)
	match data.decode_u32(KTX2_SUPERCOMPRESSION):
		0:
			pass
		KTX2_ZSTD:
			level = level.decompress(texel_bytes, FileAccess.COMPRESSION_ZSTD)
		var scheme:
			push_error("crowdbake: %s uses supercompression %d; crowdbake writes none or zstd" % [path, scheme])
			return null
	if level.size() != texel_bytes:
		push_error("crowdbake: %s holds %d bytes of texels, its header says %d" % [path, level.size(), texel_bytes])
		return null
	if data.decode_u32(KTX2_VK_FORMAT) != VK_FORMAT_R16G16B16A16_UNORM:
		push_error("crowdbake: %s is not an RGBA16 unorm VAT" % path)
		return null
	return Image.create_from_data(width, height, false, Image.FORMAT_RGBAF, unorm16_as_float32(level))


## Little-endian 16-bit unsigned normalised words -> the bytes of the same values as 32-bit floats.
func unorm16_as_float32(words: PackedByteArray) -> PackedByteArray:
	var values := PackedFloat32Array()
	values.resize(words.size() / 2)
	for i in values.size():
		values[i] = words.decode_u16(i * 2) / 65535.0
	return values.to_byte_array()
