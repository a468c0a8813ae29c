// Runs tools/clients/unity/MocapdReceiver.cs outside Unity, as Unity's player loop would: Start() once, then
// LateUpdate() every 1/60 s (both found by reflection: Unity calls these private methods by name), OnDestroy() at
// the end. After each LateUpdate that applied a new frame it prints one line for tests/test_unity_client.py:
//   frame <n> hips <x> <y> <z> <Bone> <x> <y> <z> <w> ...   (world position and rotations, Unity's frame)
// Usage: mono harness.exe URL SUBJECT FRAMES TIMEOUT_S
using System;
using System.Diagnostics;
using System.Globalization;
using System.Reflection;
using System.Text;
using System.Threading;
using UnityEngine;

public static class Harness
{
    static void Call(object target, string method) =>
        target.GetType().GetMethod(method, BindingFlags.Instance | BindingFlags.NonPublic | BindingFlags.Public)
            .Invoke(target, null);

    static string F(float v) => v.ToString("R", CultureInfo.InvariantCulture);

    public static int Main(string[] args)
    {
        var receiver = new MocapdReceiver { url = args[0], subjectId = args[1], avatar = new Animator() };
        int wanted = int.Parse(args[2], CultureInfo.InvariantCulture);
        double timeout = double.Parse(args[3], CultureInfo.InvariantCulture);
        Call(receiver, "Start");
        var clock = Stopwatch.StartNew();
        long last = -1;
        int printed = 0;
        while (printed < wanted && clock.Elapsed.TotalSeconds < timeout)
        {
            Thread.Sleep(16);
            Call(receiver, "LateUpdate");
            if (receiver.AppliedFrame == last) continue;
            last = receiver.AppliedFrame;
            var hips = receiver.avatar.GetBoneTransform(HumanBodyBones.Hips).position;
            var line = new StringBuilder($"frame {last} hips {F(hips.x)} {F(hips.y)} {F(hips.z)}");
            foreach (HumanBodyBones b in Enum.GetValues(typeof(HumanBodyBones)))
            {
                if (b == HumanBodyBones.LastBone) continue;
                var q = receiver.avatar.GetBoneTransform(b).rotation;
                line.Append($" {b} {F(q.x)} {F(q.y)} {F(q.z)} {F(q.w)}");
            }
            Console.WriteLine(line);
            printed++;
        }
        Call(receiver, "OnDestroy");
        return printed == wanted ? 0 : 1;
    }
}
