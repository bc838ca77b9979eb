// crowdbake export -> Unity materials and prefabs that play the cloth from vertex-animation textures (VATs).
//
// Export with --vat-png, copy the whole export folder under Assets/ (glTFast imports the .glb files), and
// once per project make the Shader Graph "CrowdbakeVat": a Custom Function node (Type File,
// shaders/unity_vat_custom_function.hlsl, Name CrowdbakeVat) fed by Blackboard properties whose Reference
// names are the constants below, Frame = Time * _FramesPerSecond. Then Tools > Crowdbake >
// Set Up Export... and pick export.json. For every LOD it writes, into crowdbake/ beside export.json, one
// material per part with every property set from export.json and character_lod<k>.prefab with them on its
// parts, and sets each VAT PNG's import settings: linear, uncompressed, point filtered, no mipmaps, 16-bit
// channels. The compile guard keeps the file out of player builds (and out of a Godot .NET project).
#if UNITY_EDITOR
using System;
using System.IO;
using UnityEditor;
using UnityEngine;

namespace Crowdbake
{
    public static class CrowdbakeUnityImport
    {
        const string ShaderName = "Shader Graphs/CrowdbakeVat";
        // The animation the materials play: export.json animations[].name; "" plays the first (a clip).
        static readonly string AnimationName = "";
        const string OutFolder = "crowdbake";
        // A VAT is one row per frame of up to 2048 texels: taller than the importer's default 2048 limit, which
        // would rescale it and mix up vertices. 16384 is the largest size Unity imports.
        const int MaxVatSize = 16384;

        const string VatMap = "_VatMap", JointMap = "_JointMap", BaseMap = "_BaseMap";
        const string BoundsMin = "_BoundsMin", BoundsMax = "_BoundsMax", RowsPerFrame = "_RowsPerFrame", FramesPerSecond = "_FramesPerSecond";
        // A skinned body (vat.kind "skin"): 1, and its joint matrices' layout and ranges (vat.joints).
        const string Skinned = "_Skinned", JointRowsPerFrame = "_JointRowsPerFrame", JointMin = "_JointMin", JointMax = "_JointMax";
        // first_frame, frames, loop, before_frame: the Custom Function's Range input.
        const string Range = "_Range", RangeAfter = "_RangeAfter";
        const string NodeTranslation = "_NodeTranslation", NodeScale = "_NodeScale";
        static readonly string[] Properties =
        {
            VatMap, JointMap, BaseMap, BoundsMin, BoundsMax, RowsPerFrame, FramesPerSecond, Skinned, JointRowsPerFrame, JointMin, JointMax, Range,
            RangeAfter, NodeTranslation, NodeScale,
        };

        // export.json, as much of it as the setup reads. JsonUtility fills the fields by their JSON names, which
        // the compiler cannot see (warning 0649: never assigned).
#pragma warning disable 0649
        [Serializable] class VatFile { public string png; }
        [Serializable] class Joints { public string png; public int rows_per_frame; public int height; public float[] min; public float[] max; }
        [Serializable] class Vat
        {
            public string kind; public VatFile texture; public Joints joints; public float[] bounds_min; public float[] bounds_max;
            public int rows_per_frame; public float frames_per_second; public int height;
        }
        [Serializable] class QuantizedNode { public float[] translation; public float scale; }
        [Serializable] class Part { public string part; public Vat vat; public QuantizedNode node; }
        [Serializable] class Lod { public int lod; public string glb; public Part[] parts; }
        [Serializable] class FrameRange { public int first_frame; public int frames; public int loop; public int before_frame; public int after_frame; }
        [Serializable] class AnimationEntry { public string name; public FrameRange vat; }
        [Serializable] class Sidecar { public string format; public AnimationEntry[] animations; public Lod[] lods; }
#pragma warning restore 0649

        [MenuItem("Tools/Crowdbake/Set Up Export...")]
        static void SetUpExport()
        {
            string chosen = EditorUtility.OpenFilePanel("crowdbake export.json", Application.dataPath, "json");
            if (string.IsNullOrEmpty(chosen))
                return;
            SetUp(ToAssetPath(chosen));
        }

        /// <summary>Sets up the export whose export.json is at `sidecarPath` (a path under Assets/).</summary>
        public static void SetUp(string sidecarPath)
        {
            Sidecar sidecar = JsonUtility.FromJson<Sidecar>(File.ReadAllText(sidecarPath));
            if (sidecar == null || sidecar.format != "crowdbake-export")
                throw new InvalidDataException(sidecarPath + " is not a crowdbake export.json");
            AnimationEntry animation = Array.Find(sidecar.animations, a => AnimationName == "" || a.name == AnimationName);
            if (animation == null)
                throw new InvalidDataException("export.json has no animation named " + AnimationName);
            Shader shader = Shader.Find(ShaderName);
            if (shader == null)
                throw new InvalidOperationException("no shader " + ShaderName + ": make the CrowdbakeVat Shader Graph first");
            string root = Path.GetDirectoryName(sidecarPath).Replace('\\', '/');
            string outFolder = root + "/" + OutFolder;
            if (!AssetDatabase.IsValidFolder(outFolder))
                AssetDatabase.CreateFolder(root, OutFolder);
            foreach (Lod lod in sidecar.lods)
                SetUpLod(root, outFolder, lod, animation.vat, shader);
            AssetDatabase.SaveAssets();
        }

        static void SetUpLod(string root, string outFolder, Lod lod, FrameRange played, Shader shader)
        {
            GameObject model = AssetDatabase.LoadAssetAtPath<GameObject>(root + "/" + lod.glb);
            if (model == null)
                throw new InvalidOperationException(lod.glb + " is not imported as a model (is glTFast installed?)");
            GameObject character = (GameObject)PrefabUtility.InstantiatePrefab(model);
            try
            {
                foreach (Part part in lod.parts)
                {
                    if (part.node == null || part.node.translation == null || part.node.translation.Length != 3)
                        continue;  // exported with --cloth-bones: a skinned mesh that plays its own bones
                    Transform node = FindDeep(character.transform, part.part);
                    Renderer renderer = node != null ? node.GetComponent<Renderer>() : null;
                    if (renderer == null)
                        throw new InvalidOperationException(lod.glb + " has no mesh named " + part.part);
                    Material material = VatMaterial(shader, root, part, played, renderer.sharedMaterial);
                    AssetDatabase.CreateAsset(material, outFolder + "/" + part.part + "_lod" + lod.lod + ".mat");
                    renderer.sharedMaterial = material;
                }
                PrefabUtility.SaveAsPrefabAsset(character, outFolder + "/character_lod" + lod.lod + ".prefab");
            }
            finally
            {
                UnityEngine.Object.DestroyImmediate(character);
            }
        }

        // A part's material: its VAT layout (lods[].parts[].vat), its quantized mesh's node (lods[].parts[].node)
        // and the range of pose frames the animation plays (animations[].vat). Values stay in glTF's axes: the
        // Custom Function turns its result into Unity's.
        static Material VatMaterial(Shader shader, string root, Part part, FrameRange played, Material look)
        {
            Vat vat = part.vat;
            bool skinned = vat.kind == "skin";
            if (vat.texture == null || vat.texture.png == null || (skinned && (vat.joints == null || vat.joints.png == null)))
                throw new InvalidDataException("the export has no VAT PNGs: export it with --vat-png");
            if (vat.height > MaxVatSize || (skinned && vat.joints.height > MaxVatSize))
                throw new InvalidDataException(part.part + "'s VAT is taller than Unity's " + MaxVatSize + " texels");
            var material = new Material(shader);
            foreach (string property in Properties)
                if (!material.HasProperty(property))
                    throw new InvalidOperationException(ShaderName + " has no property " + property);
            material.SetTexture(VatMap, ImportVat(root + "/" + vat.texture.png));
            material.SetFloat(Skinned, skinned ? 1f : 0f);
            if (skinned)
            {
                material.SetTexture(JointMap, ImportVat(root + "/" + vat.joints.png));
                material.SetFloat(JointRowsPerFrame, vat.joints.rows_per_frame);
                material.SetVector(JointMin, Vector4Of(vat.joints.min));
                material.SetVector(JointMax, Vector4Of(vat.joints.max));
            }
            if (look != null)
                material.SetTexture(BaseMap, look.mainTexture);
            material.SetVector(BoundsMin, Vector3Of(vat.bounds_min));
            material.SetVector(BoundsMax, Vector3Of(vat.bounds_max));
            material.SetFloat(RowsPerFrame, vat.rows_per_frame);
            material.SetFloat(FramesPerSecond, vat.frames_per_second);
            material.SetVector(Range, new Vector4(played.first_frame, played.frames, played.loop, played.before_frame));
            material.SetFloat(RangeAfter, played.after_frame);
            material.SetVector(NodeTranslation, Vector3Of(part.node.translation));
            material.SetFloat(NodeScale, part.node.scale);
            return material;
        }

        // A VAT PNG imported as data: linear, uncompressed, point sampled, no mipmaps, never rescaled, RGBA64
        // (every VAT holds 16 bits a channel). The Default platform only takes Automatic formats, so the format
        // is set as the Standalone override. LODs that read the same file import it once, the same settings.
        static Texture2D ImportVat(string path)
        {
            var importer = AssetImporter.GetAtPath(path) as TextureImporter;
            if (importer == null)
                throw new InvalidOperationException(path + " is not imported as a texture");
            importer.textureType = TextureImporterType.Default;
            importer.sRGBTexture = false;
            importer.mipmapEnabled = false;
            importer.filterMode = FilterMode.Point;
            importer.wrapMode = TextureWrapMode.Clamp;
            importer.npotScale = TextureImporterNPOTScale.None;
            importer.textureCompression = TextureImporterCompression.Uncompressed;
            importer.maxTextureSize = MaxVatSize;
            importer.SetPlatformTextureSettings(new TextureImporterPlatformSettings
            {
                name = "Standalone", overridden = true, format = TextureImporterFormat.RGBA64, maxTextureSize = MaxVatSize,
                textureCompression = TextureImporterCompression.Uncompressed,
            });
            importer.SaveAndReimport();
            return AssetDatabase.LoadAssetAtPath<Texture2D>(path);
        }

        static Vector4 Vector4Of(float[] values)
        {
            if (values == null || values.Length != 4)
                throw new InvalidDataException("export.json: expected 4 numbers");
            return new Vector4(values[0], values[1], values[2], values[3]);
        }

        static Vector4 Vector3Of(float[] values)
        {
            if (values == null || values.Length != 3)
                throw new InvalidDataException("export.json: expected 3 numbers");
            return new Vector4(values[0], values[1], values[2], 0f);
        }

        static Transform FindDeep(Transform parent, string name)
        {
            if (parent.name == name)
                return parent;
            foreach (Transform child in parent)
            {
                Transform found = FindDeep(child, name);
                if (found != null)
                    return found;
            }
            return null;
        }

        static string ToAssetPath(string absolute)
        {
            string project = Path.GetFullPath(Path.Combine(Application.dataPath, "..")).Replace('\\', '/') + "/";
            string full = Path.GetFullPath(absolute).Replace('\\', '/');
            if (!full.StartsWith(project + "Assets/", StringComparison.Ordinal))
                throw new ArgumentException(absolute + " is not inside this project's Assets folder");
            return full.Substring(project.Length);
        }
    }
}
#endif
