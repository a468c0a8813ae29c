// A minimal stand-in for the few UnityEngine types tools/clients/unity/MocapdReceiver.cs uses, so that the receiver
// compiles and runs under Mono in CI (tests/test_unity_client.py) exactly as written for Unity. Semantics follow
// Unity's documentation: Quaternion(x, y, z, w) with the Hamilton product and Inverse = conjugate (unit
// quaternions); Transform.rotation/position are world values (no hierarchy is needed here: the receiver sets every
// bone's world rotation itself); TransformPoint = position + rotation * point (unit scale); JsonUtility.FromJson
// fills the public fields of a [Serializable] class and ignores other keys (here through the .NET JSON reader).
using System;
using System.IO;
using System.Runtime.Serialization.Json;
using System.Text;

namespace UnityEngine
{
    public struct Vector3
    {
        public float x, y, z;
        public Vector3(float x, float y, float z) { this.x = x; this.y = y; this.z = z; }
        public static Vector3 operator *(Vector3 v, float s) => new Vector3(v.x * s, v.y * s, v.z * s);
        public static Vector3 operator +(Vector3 a, Vector3 b) => new Vector3(a.x + b.x, a.y + b.y, a.z + b.z);
    }

    public struct Quaternion
    {
        public float x, y, z, w;
        public Quaternion(float x, float y, float z, float w) { this.x = x; this.y = y; this.z = z; this.w = w; }
        public static Quaternion identity => new Quaternion(0f, 0f, 0f, 1f);
        public static Quaternion Inverse(Quaternion q) => new Quaternion(-q.x, -q.y, -q.z, q.w);
        public static Quaternion operator *(Quaternion a, Quaternion b) => new Quaternion(
            a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
            a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x,
            a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w,
            a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z);
        public static Vector3 operator *(Quaternion q, Vector3 v)
        {
            var p = q * new Quaternion(v.x, v.y, v.z, 0f) * Inverse(q);
            return new Vector3(p.x, p.y, p.z);
        }
    }

    public class Transform
    {
        public Vector3 position;
        public Quaternion rotation = Quaternion.identity;
        public Vector3 TransformPoint(Vector3 p) => position + rotation * p;
    }

    public class Component
    {
        public Transform transform = new Transform();
    }

    public class Behaviour : Component { }

    public class MonoBehaviour : Behaviour { }

    // Unity's HumanBodyBones, the part the receiver uses (names as Unity's; values need not be Unity's).
    public enum HumanBodyBones
    {
        Hips, LeftUpperLeg, RightUpperLeg, LeftLowerLeg, RightLowerLeg, LeftFoot, RightFoot, Spine, Chest, Neck,
        Head, LeftShoulder, RightShoulder, LeftUpperArm, RightUpperArm, LeftLowerArm, RightLowerArm, LeftHand,
        RightHand, LeftToes, RightToes, UpperChest, LastBone,
    }

    public class Animator : Behaviour
    {
        readonly Transform[] bones = new Transform[(int)HumanBodyBones.LastBone];

        // A humanoid whose bones all stand at the identity in its T-pose (the receiver's rest rotations).
        public Animator() { for (int i = 0; i < bones.Length; i++) bones[i] = new Transform(); }

        public Transform GetBoneTransform(HumanBodyBones bone) => bones[(int)bone];
    }

    public static class Debug
    {
        public static void Log(object message) => Console.Error.WriteLine(message);
        public static void LogWarning(object message) => Console.Error.WriteLine("warning: " + message);
    }

    public static class JsonUtility
    {
        public static T FromJson<T>(string json)
        {
            using (var stream = new MemoryStream(Encoding.UTF8.GetBytes(json)))
                return (T)new DataContractJsonSerializer(typeof(T)).ReadObject(stream);
        }
    }

    [AttributeUsage(AttributeTargets.Field)]
    public class TooltipAttribute : Attribute
    {
        public TooltipAttribute(string tooltip) { }
    }
}
