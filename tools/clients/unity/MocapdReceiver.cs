// mocapd WebSocket pose stream -> a Unity humanoid (protocol: docs/streaming.md, "WebSocket").
//
// Tested in mocapd's CI without Unity: compiled by Mono's mcs against a minimal stand-in for the UnityEngine types
// it uses and run under mono against the live daemon, every applied pose compared with the daemon's
// (tests/unity_client.py). Not run inside the Unity editor there; see README.md beside it for set-up.
//
// Asks for JSON frames in the "unity" convention (left-handed, +Y up, metres) and drives one subject onto a
// humanoid avatar. mocapd's local rotations are relative to its T-pose (facing +Z, every bone frame aligned with
// the world), so each avatar bone's world rotation is  root * G_bone * rest_bone,  where G_bone is the product of
// the received local rotations down the chain and rest_bone the avatar bone's rotation (relative to the avatar
// root) captured while the avatar stands in a T-pose facing +Z.
using System;
using System.Collections.Concurrent;
using System.Net.WebSockets;
using System.Text;
using System.Threading;
using System.Threading.Tasks;
using UnityEngine;

public class MocapdReceiver : MonoBehaviour
{
    [Tooltip("The daemon's WebSocket stream ([websocket] host and port in config.toml)")]
    public string url = "ws://127.0.0.1:8766/";
    [Tooltip("The daemon's [websocket] token, if it has one")]
    public string token = "";
    [Tooltip("Subject id to drive (e.g. suit:suit0); empty = the first subject of each frame")]
    public string subjectId = "";
    [Tooltip("Humanoid avatar, standing in a T-pose facing +Z when play starts")]
    public Animator avatar;
    [Tooltip("Move the hips to the received root position (metres), scaled by scaleRoot")]
    public bool applyRootPosition = true;
    public float scaleRoot = 1.0f;
    [Tooltip("At most this many frames per second (0 = every frame the daemon solves)")]
    public float rateHz = 0f;

    // mocapd bone order (DESIGN.md) and parents; the hello carries the same lists.
    static readonly int[] Parents = { -1, 0, 1, 2, 3, 4, 5, 4, 7, 8, 4, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19 };
    // mocapd bone -> Unity HumanBodyBones (Spine2 has no humanoid bone: its rotation flows on through Spine3).
    static readonly HumanBodyBones?[] ToHuman = {
        HumanBodyBones.Hips, HumanBodyBones.Spine, HumanBodyBones.Chest, null, HumanBodyBones.UpperChest,
        HumanBodyBones.Neck, HumanBodyBones.Head,
        HumanBodyBones.LeftUpperArm, HumanBodyBones.LeftLowerArm, HumanBodyBones.LeftHand,
        HumanBodyBones.RightUpperArm, HumanBodyBones.RightLowerArm, HumanBodyBones.RightHand,
        HumanBodyBones.LeftUpperLeg, HumanBodyBones.LeftLowerLeg, HumanBodyBones.LeftFoot, HumanBodyBones.LeftToes,
        HumanBodyBones.RightUpperLeg, HumanBodyBones.RightLowerLeg, HumanBodyBones.RightFoot, HumanBodyBones.RightToes,
    };

    [Serializable] class Envelope { public string type; }
    [Serializable] class Subject { public string id; public float[] root; public float[] rot; public float confidence; }
    [Serializable] class Frame { public string type; public long frame; public long t_solve_ns; public Subject[] subjects; }
    [Serializable] class ErrorMessage { public string code; public string message; }

    /// <summary>The daemon's counter of the frame applied last (-1 before the first): for a status display.</summary>
    public long AppliedFrame { get; private set; } = -1;

    readonly ConcurrentQueue<Frame> frames = new ConcurrentQueue<Frame>();
    readonly Transform[] bones = new Transform[21];
    readonly Quaternion[] rest = new Quaternion[21];
    CancellationTokenSource cancel;

    void Start()
    {
        for (int b = 0; b < 21; b++)
        {
            HumanBodyBones? hb = ToHuman[b];  // (not `is HumanBodyBones hb`: Mono's mcs cannot compile that pattern)
            if (hb.HasValue && avatar != null && (bones[b] = avatar.GetBoneTransform(hb.Value)) != null)
                rest[b] = Quaternion.Inverse(avatar.transform.rotation) * bones[b].rotation;
        }
        cancel = new CancellationTokenSource();
        Task.Run(() => ReceiveLoop(cancel.Token));
    }

    void OnDestroy() => cancel?.Cancel();

    async Task ReceiveLoop(CancellationToken ct)
    {
        var buffer = new byte[1 << 16];
        while (!ct.IsCancellationRequested)
        {
            using (var ws = new ClientWebSocket())
            {
                try
                {
                    var uri = new Uri(string.IsNullOrEmpty(token) ? url : $"{url}?token={Uri.EscapeDataString(token)}");
                    await ws.ConnectAsync(uri, ct);
                    string rate = rateHz > 0 ? $",\"rate_hz\":{rateHz.ToString(System.Globalization.CultureInfo.InvariantCulture)}" : "";
                    string subscribe = "{\"type\":\"subscribe\",\"encoding\":\"json\",\"convention\":\"unity\",\"globals\":false" + rate + "}";
                    await ws.SendAsync(new ArraySegment<byte>(Encoding.UTF8.GetBytes(subscribe)), WebSocketMessageType.Text, true, ct);
                    var message = new StringBuilder();
                    while (ws.State == WebSocketState.Open && !ct.IsCancellationRequested)
                    {
                        var r = await ws.ReceiveAsync(new ArraySegment<byte>(buffer), ct);
                        if (r.MessageType == WebSocketMessageType.Close) break;
                        if (r.MessageType == WebSocketMessageType.Binary) continue;  // the first hello is msgpack
                        message.Append(Encoding.UTF8.GetString(buffer, 0, r.Count));
                        if (!r.EndOfMessage) continue;
                        string json = message.ToString();
                        message.Clear();
                        string type = JsonUtility.FromJson<Envelope>(json).type;
                        if (type == "frame")
                        {
                            frames.Enqueue(JsonUtility.FromJson<Frame>(json));
                            while (frames.Count > 2) frames.TryDequeue(out _);  // only the newest matters
                        }
                        else if (type == "error")
                        {
                            var e = JsonUtility.FromJson<ErrorMessage>(json);
                            Debug.LogWarning($"mocapd: {e.code}: {e.message}");
                        }
                    }
                }
                catch (OperationCanceledException) { return; }
                catch (WebSocketException e) { Debug.Log($"mocapd: {e.Message}; reconnecting"); }
            }
            try { await Task.Delay(1000, ct); } catch (OperationCanceledException) { return; }
        }
    }

    void LateUpdate()
    {
        Frame latest = null;
        while (frames.TryDequeue(out var f)) latest = f;
        if (latest == null || avatar == null) return;
        Subject s = null;
        foreach (var c in latest.subjects)
            if (string.IsNullOrEmpty(subjectId) || c.id == subjectId) { s = c; break; }
        if (s == null || s.rot == null || s.rot.Length != 84) return;

        var global = new Quaternion[21];
        Quaternion root = avatar.transform.rotation;
        for (int b = 0; b < 21; b++)
        {
            // Wire order is w, x, y, z; Unity's constructor takes x, y, z, w.
            var q = new Quaternion(s.rot[4 * b + 1], s.rot[4 * b + 2], s.rot[4 * b + 3], s.rot[4 * b]);
            global[b] = Parents[b] < 0 ? q : global[Parents[b]] * q;
            if (bones[b] != null) bones[b].rotation = root * global[b] * rest[b];
        }
        if (applyRootPosition && bones[0] != null && s.root != null && s.root.Length == 3)
            bones[0].position = avatar.transform.TransformPoint(new Vector3(s.root[0], s.root[1], s.root[2]) * scaleRoot);
        AppliedFrame = latest.frame;
    }
}
