// The members of Unity's UnityEngine and UnityEditor APIs that crowdbake's Unity import script uses, with
// their Unity signatures and no behaviour: enough for a C# compiler to check the script's names, types and
// calls (services/tests/test_engine_import.py). Nothing here runs.
using System;
using System.Collections;

namespace UnityEngine
{
    public class Object
    {
        public string name { get; set; }
        public static void DestroyImmediate(Object obj) { }
    }

    public class Component : Object
    {
        public T GetComponent<T>() { return default(T); }
    }

    public class Transform : Component, IEnumerable
    {
        public IEnumerator GetEnumerator() { return new Transform[0].GetEnumerator(); }
    }

    public class GameObject : Object
    {
        public Transform transform { get { return null; } }
    }

    public class Shader : Object
    {
        public static Shader Find(string name) { return null; }
    }

    public class Texture : Object { }
    public class Texture2D : Texture { }

    public class Material : Object
    {
        public Material(Shader shader) { }
        public Texture mainTexture { get; set; }
        public bool HasProperty(string name) { return false; }
        public void SetTexture(string name, Texture value) { }
        public void SetVector(string name, Vector4 value) { }
        public void SetFloat(string name, float value) { }
    }

    public class Renderer : Component
    {
        public Material sharedMaterial { get; set; }
    }

    public struct Vector4
    {
        public float x, y, z, w;
        public Vector4(float x, float y, float z, float w) { this.x = x; this.y = y; this.z = z; this.w = w; }
    }

    public enum FilterMode { Point, Bilinear, Trilinear }
    public enum TextureWrapMode { Repeat, Clamp, Mirror, MirrorOnce }

    public static class Application
    {
        public static string dataPath { get { return ""; } }
    }

    public static class JsonUtility
    {
        public static T FromJson<T>(string json) { return default(T); }
    }
}

namespace UnityEditor
{
    using UnityEngine;

    [AttributeUsage(AttributeTargets.Method, AllowMultiple = true)]
    public sealed class MenuItem : Attribute
    {
        public MenuItem(string itemName) { }
    }

    public static class EditorUtility
    {
        public static string OpenFilePanel(string title, string directory, string extension) { return ""; }
    }

    public static class AssetDatabase
    {
        public static T LoadAssetAtPath<T>(string assetPath) where T : Object { return null; }
        public static bool IsValidFolder(string path) { return false; }
        public static string CreateFolder(string parentFolder, string newFolderName) { return ""; }
        public static void CreateAsset(Object asset, string path) { }
        public static void SaveAssets() { }
    }

    public static class PrefabUtility
    {
        public static Object InstantiatePrefab(Object assetComponentOrGameObject) { return null; }
        public static GameObject SaveAsPrefabAsset(GameObject instanceRoot, string assetPath) { return null; }
    }

    public class AssetImporter : Object
    {
        public static AssetImporter GetAtPath(string path) { return null; }
        public void SaveAndReimport() { }
    }

    public enum TextureImporterType { Default, NormalMap, GUI, Sprite, Cursor, Cookie, Lightmap, SingleChannel }
    public enum TextureImporterNPOTScale { None, ToNearest, ToLarger, ToSmaller }
    public enum TextureImporterCompression { Uncompressed, Compressed, CompressedHQ, CompressedLQ }
    public enum TextureImporterFormat { Automatic, RGBA32, RGBA64 }

    public class TextureImporterPlatformSettings
    {
        public string name { get; set; }
        public bool overridden { get; set; }
        public TextureImporterFormat format { get; set; }
        public int maxTextureSize { get; set; }
        public TextureImporterCompression textureCompression { get; set; }
    }

    public class TextureImporter : AssetImporter
    {
        public TextureImporterType textureType { get; set; }
        public bool sRGBTexture { get; set; }
        public bool mipmapEnabled { get; set; }
        public FilterMode filterMode { get; set; }
        public TextureWrapMode wrapMode { get; set; }
        public TextureImporterNPOTScale npotScale { get; set; }
        public TextureImporterCompression textureCompression { get; set; }
        public int maxTextureSize { get; set; }
        public void SetPlatformTextureSettings(TextureImporterPlatformSettings platformSettings) { }
    }
}
