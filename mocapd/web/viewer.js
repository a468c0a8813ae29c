// mocapd live viewer. Connects to the WebSocket pose stream of the daemon that served this page, asks for JSON
// frames in mocapd's native convention (right-handed, +Y up, metres) with global joint positions and status
// messages, and draws every subject's skeleton on a 2D canvas with its own small perspective camera.
// Reconnects by itself when the daemon goes away and comes back. State for tests: window.mocapdViewer.
// The 3D view fits the people: it aims at the middle of every shown subject's joints, from the distance at which
// their bounding sphere fills FIT_FILL of the canvas's smaller side, and follows them (smoothed over FIT_TAU_S)
// until the user orbits or zooms; double-click fits again. The floor grid is drawn around the point looked at.
// Camera views (the "Camera views" button, or ?cameras=1): one panel per camera with its latest frame, the 2D
// detections (white dots) and every solved subject reprojected through that camera's calibration (lines in the
// subject's colour), with the reprojection error and detection rate; the server sends them only while asked.
// Fingers (issue 44): a subject whose frame carries "hands" also gets its finger bones drawn, thinner, from each
// hand's wrist through the finger joints to the fingertips (the hands' global joints, or forward kinematics from
// the hand's rotation, the fingers' local rotations and their offsets).
// Avatar (the "Avatar" button, or ?avatar=1; issue 44): avatar.js, loaded on demand, puts a VRM humanoid on every
// subject, body and fingers, drawn on a WebGL canvas over this one with the same camera; a subject's skeleton is
// drawn only until its avatar is there. Without the libraries (set-up not run) the skeletons stay, and the panel
// says why. State for tests: window.mocapdViewer.avatar.
"use strict";

(function () {
  const PALETTE = ["#ff3b30", "#30d158", "#0a84ff", "#ffd60a", "#bf5af2", "#ff9f0a", "#64d2ff", "#ff375f"];
  const canvas = document.getElementById("view");
  const ctx = canvas.getContext("2d");
  const params = new URLSearchParams(location.search);
  const token = params.get("token");
  const CAM_GAP = 6, CAM_CAPTION = 18;  // CSS px between panels and under each canvas

  const state = {
    connected: false, connects: 0, hellos: 0, frames: 0, statusMessages: 0, errors: 0,
    hello: null, frame: null, shown: null, paused: false, status: null, colours: {}, rate: 0, lastError: null,
    camerasOn: params.get("cameras") === "1", cameraMessages: 0, cams: {}, headingResets: 0, headingAsked: false,
    avatarOn: params.get("avatar") === "1",
  };
  // The avatar view: its module's view once loaded, the error that stopped it, whether it is loading.
  const avatar = { view: null, error: null, loading: false };
  const cam = { yaw: 0.6, pitch: 0.35, dist: 7.0, target: [0, 0.9, 0] };
  const FIT_FILL = 0.8, FIT_MIN_RADIUS = 1.0, FIT_TAU_S = 0.4, MIN_DIST = 1.0, MAX_DIST = 40.0;
  // auto: the view follows the people (until the user moves it); fitted: it has aimed at them once (no fly-in).
  const view = { auto: true, fitted: false, last: 0 };
  let socket = null, retryMs = 250, drawPending = false, frameTimes = [];

  // ------------------------------------------------------------------------------------------ camera
  function basis() {
    // Camera position on a sphere around the target; returns eye and the right/up/forward axes.
    const cp = Math.cos(cam.pitch), sp = Math.sin(cam.pitch), cy = Math.cos(cam.yaw), sy = Math.sin(cam.yaw);
    const fwd = [-cp * sy, -sp, -cp * cy];  // from the eye towards the target
    const eye = [cam.target[0] - fwd[0] * cam.dist, cam.target[1] - fwd[1] * cam.dist,
                 cam.target[2] - fwd[2] * cam.dist];
    // right = fwd x up(0,1,0), normalised; up = right x fwd
    let right = [-fwd[2], 0, fwd[0]];
    const n = Math.hypot(right[0], right[2]) || 1;
    right = [right[0] / n, 0, right[2] / n];
    const up = [right[1] * fwd[2] - right[2] * fwd[1], right[2] * fwd[0] - right[0] * fwd[2],
                right[0] * fwd[1] - right[1] * fwd[0]];
    return { eye, right, up, fwd };
  }

  function project(p, b) {
    // World point (metres) -> canvas CSS pixels, or null behind the camera.
    b = b || basis();
    const d = [p[0] - b.eye[0], p[1] - b.eye[1], p[2] - b.eye[2]];
    const z = d[0] * b.fwd[0] + d[1] * b.fwd[1] + d[2] * b.fwd[2];
    if (z < 0.05) return null;
    const x = d[0] * b.right[0] + d[1] * b.right[1] + d[2] * b.right[2];
    const y = d[0] * b.up[0] + d[1] * b.up[1] + d[2] * b.up[2];
    const w = canvas.clientWidth, h = canvas.clientHeight, f = 0.9 * Math.min(w, h);
    return [w / 2 + f * x / z, h / 2 - f * y / z];
  }

  // ------------------------------------------------------------------------------------------ drawing
  function colourOf(id) {
    if (!(id in state.colours)) state.colours[id] = PALETTE[Object.keys(state.colours).length % PALETTE.length];
    return state.colours[id];
  }

  function jointsOf(s) {
    // Global joints from the frame, or forward kinematics from root + local quaternions + rest offsets.
    if (s.joints) {
      const out = [];
      for (let i = 0; i < s.joints.length; i += 3) out.push([s.joints[i], s.joints[i + 1], s.joints[i + 2]]);
      return out;
    }
    return bodyFK(s).pos;
  }
  function bodyFK(s) {
    // Joint positions and global rotations of the body by forward kinematics (empty without the skeleton).
    const sk = state.hello && state.hello.skeletons[s.skeleton], pos = [], glob = [];
    if (!sk) return { pos, glob };
    for (let b = 0; b < sk.parents.length; b++) {
      const q = s.rot.slice(4 * b, 4 * b + 4), p = sk.parents[b];
      if (p < 0) { glob.push(q); pos.push(s.root.slice()); continue; }
      const o = sk.offsets.slice(3 * b, 3 * b + 3), r = rotate(glob[p], o);
      glob.push(qmul(glob[p], q));
      pos.push([pos[p][0] + r[0], pos[p][1] + r[1], pos[p][2] + r[2]]);
    }
    return { pos, glob };
  }
  const HANDS = [9, 12];  // the body's LeftHand and RightHand
  function fingersOf(s) {
    // Per hand: its wrist, the 15 finger joints and the 5 fingertips (world), from the frame's "hands" (none: []).
    const h = s.hands;
    if (!h) return [];
    const pts = (a) => {
      const o = [];
      for (let i = 0; i < a.length; i += 3) o.push([a[i], a[i + 1], a[i + 2]]);
      return o;
    };
    const body = h.joints ? null : bodyFK(s), wrists = h.joints ? jointsOf(s) : body.pos;
    const out = [];
    for (let side = 0; side < 2; side++) {
      const wrist = wrists[HANDS[side]];
      if (!wrist) continue;
      if (h.joints) {
        out.push({ wrist, joints: pts(h.joints.slice(45 * side, 45 * side + 45)),
                   tips: pts(h.tip_joints.slice(15 * side, 15 * side + 15)) });
        continue;
      }
      // Forward kinematics: each finger's three bones from the hand, then its tip in the distal bone.
      const joints = [], tips = [], glob = [];
      for (let b = 0; b < 15; b++) {
        const q = h.rot.slice(60 * side + 4 * b, 60 * side + 4 * b + 4);
        const o = h.offsets.slice(45 * side + 3 * b, 45 * side + 3 * b + 3);
        const pg = b % 3 === 0 ? body.glob[HANDS[side]] : glob[b - 1], pp = b % 3 === 0 ? wrist : joints[b - 1];
        const r = rotate(pg, o);
        joints.push([pp[0] + r[0], pp[1] + r[1], pp[2] + r[2]]);
        glob.push(qmul(pg, q));
        if (b % 3 === 2) {
          const t = rotate(glob[b], h.tip_offsets.slice(15 * side + b - 2, 15 * side + b + 1));
          tips.push([joints[b][0] + t[0], joints[b][1] + t[1], joints[b][2] + t[2]]);
        }
      }
      out.push({ wrist, joints, tips });
    }
    return out;
  }
  function qmul(a, b) {
    return [a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3], a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
            a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1], a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]];
  }
  function rotate(q, v) {
    const r = qmul(qmul(q, [0, v[0], v[1], v[2]]), [q[0], -q[1], -q[2], -q[3]]);
    return [r[1], r[2], r[3]];
  }

  function fitOf(subjects) {
    // Where to look from to see every joint of ``subjects``: the middle of their bounding box, at the distance
    // at which the sphere around it (at least FIT_MIN_RADIUS) spans FIT_FILL of the canvas's smaller side.
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    const pts = [];
    for (const s of subjects) for (const p of jointsOf(s)) if (p.every(Number.isFinite)) pts.push(p);
    if (!pts.length) return null;
    for (const p of pts) for (let i = 0; i < 3; i++) { lo[i] = Math.min(lo[i], p[i]); hi[i] = Math.max(hi[i], p[i]); }
    const target = [0, 1, 2].map((i) => (lo[i] + hi[i]) / 2);
    let r = FIT_MIN_RADIUS;
    for (const p of pts) r = Math.max(r, Math.hypot(p[0] - target[0], p[1] - target[1], p[2] - target[2]));
    // Projected radius f r / d with f = 0.9 min(w, h) (project()): FIT_FILL min(w, h) / 2 when d = 1.8 r / FIT_FILL.
    const dist = Math.max(MIN_DIST, Math.min(MAX_DIST, 1.8 * r / FIT_FILL));
    return { target, dist };
  }

  function followPeople(now) {
    // One step of the auto view towards the shown subjects' fit (the first one there at once).
    if (!view.auto || state.paused || !state.shown || !state.hello) { view.last = now; return; }
    const f = fitOf(state.shown.subjects);
    if (!f) { view.last = now; return; }
    const a = view.fitted ? 1 - Math.exp(-Math.max(0, now - view.last) / 1000 / FIT_TAU_S) : 1;
    view.fitted = true; view.last = now;
    for (let i = 0; i < 3; i++) cam.target[i] += a * (f.target[i] - cam.target[i]);
    cam.dist += a * (f.dist - cam.dist);
  }

  function line(a, b, colour, width) {
    if (!a || !b) return;
    ctx.strokeStyle = colour; ctx.lineWidth = width;
    ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke();
  }

  function draw() {
    drawPending = false;
    const dpr = window.devicePixelRatio || 1, w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
    }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#111418"; ctx.fillRect(0, 0, w, h);
    followPeople(performance.now());  // a step per drawn frame: no redraws of its own (the page stays as cheap)
    const b = basis();
    // Floor grid, 1 m, around the point looked at; the world's x = 0 and z = 0 lines brighter.
    const gx = Math.round(cam.target[0]), gz = Math.round(cam.target[2]), n = Math.max(5, Math.ceil(cam.dist));
    for (let k = -n; k <= n; k++) {
      line(project([gx + k, 0, gz - n], b), project([gx + k, 0, gz + n], b), gx + k === 0 ? "#3b4350" : "#262b33", 1);
      line(project([gx - n, 0, gz + k], b), project([gx + n, 0, gz + k], b), gz + k === 0 ? "#3b4350" : "#262b33", 1);
    }
    const f = state.shown, parents = state.hello ? state.hello.parents : null;
    const avatars = state.avatarOn && avatar.view && state.hello  // the subjects drawn as avatars
      ? avatar.view.render(f ? f.subjects : [], b, cam.target, w, h) : new Set();
    if (f && parents) {
      ctx.lineCap = "round";
      for (const s of f.subjects) {
        const colour = colourOf(s.id), pts = jointsOf(s).map((p) => project(p, b));
        ctx.fillStyle = colour;
        if (!avatars.has(s.id)) {
          for (let i = 1; i < pts.length; i++) line(pts[parents[i]], pts[i], colour, 4);
          for (const p of pts) if (p) { ctx.beginPath(); ctx.arc(p[0], p[1], 3.5, 0, 2 * Math.PI); ctx.fill(); }
        }
        for (const hand of avatars.has(s.id) ? [] : fingersOf(s)) {  // each finger: wrist, its three joints, its tip
          const w = project(hand.wrist, b), j = hand.joints.map((p) => project(p, b));
          const t = hand.tips.map((p) => project(p, b));
          for (let f = 0; f < 5; f++) {
            const chain = [w, j[3 * f], j[3 * f + 1], j[3 * f + 2], t[f]];
            for (let k = 1; k < chain.length; k++) line(chain[k - 1], chain[k], colour, 2);
          }
        }
        const head = pts[6];
        if (head) { ctx.font = "12px system-ui, sans-serif"; ctx.fillText(s.id, head[0] + 8, head[1] - 8); }
      }
    }
    ctx.fillStyle = "#8a94a3"; ctx.font = "12px system-ui, sans-serif";
    const mode = view.auto ? "view follows the people" : "view moved by hand · double-click: follow the people";
    ctx.fillText(f ? `frame ${f.frame} · ${state.rate.toFixed(0)} Hz received · ${mode}` : "no frames yet", 10, h - 10);
  }

  function scheduleDraw() {
    if (drawPending) return;
    drawPending = true;
    // requestAnimationFrame pauses in hidden tabs; the timer keeps the state current for screenshots anyway.
    requestAnimationFrame(draw);
    setTimeout(() => { if (drawPending) draw(); }, 100);
  }

  // ------------------------------------------------------------------------------------------ panel
  function rows(id, entries) {
    const t = document.getElementById(id);
    t.innerHTML = "";
    for (const [k, v, cls] of entries) {
      const tr = t.insertRow(), a = tr.insertCell(), c = tr.insertCell();
      if (k instanceof Node) a.appendChild(k); else a.textContent = k;
      c.textContent = v; c.className = "v " + (cls || "");
    }
  }
  const fmt = (x, d = 1) => (x === null || x === undefined ? "–" : Number(x).toFixed(d));

  // The landmark model that runs (issue 40): "full every 3 · cam01 2.0/6.1 Hz" (landmark / detection passes).
  function landmarkText(lm) {
    const cams = Object.entries(lm.cameras || {}).map(([n, r]) => `${n} ${r.landmark_hz.toFixed(1)}/${r.detect_hz.toFixed(1)} Hz`);
    return [`${lm.running}${lm.running !== "off" && lm.every > 1 ? ` every ${lm.every}` : ""}`, ...cams].join(" · ");
  }

  function updatePanel() {
    const conn = document.getElementById("conn");
    conn.textContent = state.connected ? `connected · ${state.frames} frames${state.paused ? " · paused" : ""}`
      : "disconnected · reconnecting…";
    conn.className = state.connected ? "ok" : "bad";
    const subjects = state.frame ? state.frame.subjects : [];
    rows("subjects", subjects.map((s) => {
      const label = document.createElement("span"), sw = document.createElement("span");
      sw.className = "swatch"; sw.style.background = colourOf(s.id);
      label.appendChild(sw); label.appendChild(document.createTextNode(s.id));
      return [label, `${fmt(s.confidence, 2)} · ${s.views} cams · ${s.imus} IMUs`];
    }));
    const st = state.status;
    if (!st) return;
    const o = st.output || {};
    rows("output", [["rate (Hz)", `${o.achieved_hz ?? "–"} / ${o.configured_hz ?? "–"}`],
                    ["frames", o.frames ?? "–"], ["missed ticks", o.missed_ticks ?? "–", o.missed_ticks ? "bad" : ""],
                    ...(st.governor ? [["shed", st.governor.shed, st.governor.step ? "bad" : "ok"]] : []),
                    ...(st.landmarks ? [["landmarks", landmarkText(st.landmarks)]] : []),
                    ["uptime (s)", fmt(st.uptime_s, 0)],
                    ["stream clients", st.stream ? st.stream.clients : "–"],
                    ["dropped (this page)", st.stream ? st.stream.dropped : "–"]]);
    rows("latency", Object.entries(st.latency_ms || {}).map(([k, v]) => [k, `${fmt(v.p50)} / ${fmt(v.p95)}`]));
    // The bumped-camera watch (issue 43): a camera in doubt is marked; "moved?" while suspect, "moved" once bumped.
    const moved = { suspect: "moved?", bumped: "moved" };
    rows("cameras", (st.cameras || []).map((c) => [c.name, `${c.frames} frames${moved[c.watch] ? " · " + moved[c.watch] : ""}`,
                                                   moved[c.watch] ? "bad" : ""]));
    const imus = st.imus || [];
    rows("imus", imus.length ? imus.map((d) => [d.path.split("/").pop(), d.streaming ? "streaming" : "down",
                                                d.streaming ? "ok" : "bad"]) : [["none", ""]]);
  }

  // ------------------------------------------------------------------------------------------ camera panels
  function cameraPanel(m) {
    // The panel of camera m.camera (created on its first message): a canvas sized to the camera's aspect ratio.
    let p = state.cams[m.camera];
    if (p) return p;
    const div = document.createElement("div"), canvas = document.createElement("canvas"),
      cap = document.createElement("div");
    div.className = "cam"; cap.className = "cap";
    canvas.dataset.aspect = m.width / m.height;
    div.appendChild(canvas); div.appendChild(cap);
    const list = document.getElementById("cams"), after = [...list.children].find((c) => +c.dataset.camera > m.camera);
    div.dataset.camera = m.camera;
    list.insertBefore(div, after || null);
    p = state.cams[m.camera] = { canvas, cap, msg: null, shown: null, img: null, pending: null, messages: 0 };
    layoutCameras();
    return p;
  }

  function layoutCameras() {
    // The largest panel height with which every panel fits in the width, in at most half the window's height.
    const panels = Object.values(state.cams);
    if (!panels.length) return;
    const W = document.getElementById("main").clientWidth - CAM_GAP, H = 0.5 * window.innerHeight;
    const aspect = Math.max(...panels.map((p) => +p.canvas.dataset.aspect));
    let best = 0;
    for (let cols = 1; cols <= panels.length; cols++) {
      const rows = Math.ceil(panels.length / cols);
      best = Math.max(best, Math.min((W / cols - CAM_GAP) / aspect, H / rows - CAM_GAP - CAM_CAPTION));
    }
    const h = Math.max(40, Math.floor(best));
    for (const p of panels) {
      p.canvas.style.height = h + "px"; p.canvas.style.width = Math.floor(h * p.canvas.dataset.aspect) + "px";
      if (p.shown) drawCamera(p);
    }
  }

  function onCamera(m) {
    state.cameraMessages += 1;
    const p = cameraPanel(m);
    p.msg = m; p.messages += 1;
    if (state.paused) return;
    showCamera(p, m);
  }

  function showCamera(p, m) {
    // Decode the JPEG (if any), then draw the frame and its overlays together.
    if (m.image) {
      const img = new Image();
      img.onload = () => { if (p.pending === m) { p.img = img; p.shown = m; p.pending = null; drawCamera(p); } };
      p.pending = m;
      img.src = "data:image/jpeg;base64," + m.image;
    } else { p.img = null; p.shown = m; drawCamera(p); }
  }

  function drawCamera(p) {
    const m = p.shown, c = p.canvas, g = c.getContext("2d"), dpr = window.devicePixelRatio || 1;
    const w = c.clientWidth, h = c.clientHeight;
    if (c.width !== Math.round(w * dpr) || c.height !== Math.round(h * dpr)) {
      c.width = Math.round(w * dpr); c.height = Math.round(h * dpr);
    }
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.fillStyle = "#000"; g.fillRect(0, 0, w, h);
    if (!m) return;
    const sx = w / m.width, sy = h / m.height;  // full-resolution pixel -> CSS pixel
    if (p.img) g.drawImage(p.img, 0, 0, w, h);
    const parents = state.hello ? state.hello.parents : [];
    g.lineCap = "round";
    for (const subj of m.subjects) {
      const colour = colourOf(subj.id), j = subj.joints, pt = (i) => (j[2 * i] === null || j[2 * i + 1] === null
        ? null : [j[2 * i] * sx, j[2 * i + 1] * sy]);
      g.strokeStyle = colour; g.lineWidth = 2.5;
      for (let i = 1; i < parents.length; i++) {
        const a = pt(parents[i]), b = pt(i);
        if (a && b) { g.beginPath(); g.moveTo(a[0], a[1]); g.lineTo(b[0], b[1]); g.stroke(); }
      }
      g.fillStyle = colour;
      for (let i = 0; i < j.length / 2; i++) {
        const a = pt(i);
        if (a) { g.beginPath(); g.arc(a[0], a[1], 2.5, 0, 2 * Math.PI); g.fill(); }
      }
    }
    g.fillStyle = "#ffffff"; g.strokeStyle = "#000000"; g.lineWidth = 1;
    for (const d of m.detections) {
      for (let k = 0; k + 2 < d.length; k += 3) {
        if (d[k] === null || d[k + 2] < 0.3) continue;
        g.beginPath(); g.arc(d[k] * sx, d[k + 1] * sy, 2, 0, 2 * Math.PI); g.fill(); g.stroke();
      }
    }
    const rep = m.reprojection_px === null ? "–" : m.reprojection_px.toFixed(1);
    p.cap.textContent = `${m.name} · reprojection ${rep} px · detections ${m.detection_hz.toFixed(1)} Hz`;
  }

  function setCameras(on) {
    state.camerasOn = on;
    document.getElementById("cams").className = on ? "on" : "";
    document.getElementById("camsButton").className = on ? "on" : "";
    if (!on) { document.getElementById("cams").innerHTML = ""; state.cams = {}; }
    if (socket && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify({ type: "subscribe", cameras: on }));
    scheduleDraw();
  }
  document.getElementById("camsButton").addEventListener("click", () => setCameras(!state.camerasOn));

  // ------------------------------------------------------------------------------------------ avatar view
  function avatarSaid(text, cls) {
    const m = document.getElementById("avatarMsg");
    m.textContent = text; m.className = cls;
  }
  function setAvatar(on) {
    state.avatarOn = on;
    document.getElementById("avatarButton").className = on ? "on" : "";
    document.getElementById("avatarView").className = on ? "on" : "";
    if (!on) {
      if (avatar.view) avatar.view.clear();
      avatarSaid(avatar.error ? `avatar unavailable: ${avatar.error}` : "", avatar.error ? "bad" : "dim");
      scheduleDraw();
      return;
    }
    if (!avatar.view && !avatar.loading) {
      avatar.loading = true;
      avatarSaid("avatar: loading…", "dim");
      import("./avatar.js")
        .then((m) => m.createAvatarView({ canvas: document.getElementById("avatarView"), hello: () => state.hello,
                                          bodyFK, colourOf, redraw: scheduleDraw, url: "avatar.vrm",
                                          failed: (e) => avatarSaid(`avatar unavailable: ${e}`, "bad") }))
        .then((v) => { avatar.view = v; avatar.error = null; avatarSaid("avatar: VRM humanoid, body and fingers", "ok"); })
        .catch((e) => {
          // Most likely set-up has not fetched three.js and three-vrm (setup/steps/33-viewer-libs.sh): /lib/ is 404.
          avatar.error = String(e && e.message ? e.message : e);
          setAvatar(false);
        })
        .finally(() => { avatar.loading = false; scheduleDraw(); });
    }
    scheduleDraw();
  }
  document.getElementById("avatarButton").addEventListener("click", () => setAvatar(!state.avatarOn));

  // Heading reset (docs/imu.md "Heading without cameras"): the daemon's WebSocket request, its answer said here.
  function resetHeading() {
    const msg = document.getElementById("headingMsg");
    if (!socket || socket.readyState !== WebSocket.OPEN) {
      msg.textContent = "not connected"; msg.className = "bad"; return;
    }
    state.headingAsked = true;
    socket.send(JSON.stringify({ type: "reset_heading" }));
    msg.textContent = "resetting…"; msg.className = "dim";
  }
  function onHeadingReset(m) {
    state.headingResets += 1; state.headingAsked = false;
    const said = Object.entries(m.suits || {}).map(([suit, r]) => {
      const c = Object.values(r.corrections_deg || {}).map((d) => Math.abs(d));
      const stale = (r.no_recent_sample || []).length;
      return `${suit}: ${c.length} sensors turned, up to ${c.length ? Math.max(...c).toFixed(1) : "0"}°` +
        (stale ? `, ${stale} without a recent sample` : "");
    });
    const msg = document.getElementById("headingMsg");
    msg.textContent = said.length ? `heading reset · ${said.join(" · ")}` : "heading reset: no suit";
    msg.className = said.length ? "ok" : "bad";
  }
  document.getElementById("headingButton").addEventListener("click", resetHeading);

  // ------------------------------------------------------------------------------------------ stream
  function connect() {
    const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/` +
      (token ? `?token=${encodeURIComponent(token)}` : "");
    const ws = new WebSocket(url);
    socket = ws;
    ws.binaryType = "arraybuffer";
    ws.onopen = () => {
      state.connected = true; state.connects += 1; retryMs = 250;
      ws.send(JSON.stringify({ type: "subscribe", encoding: "json", convention: "native", globals: true,
                               status: true }));
      if (state.camerasOn) setCameras(true);
      updatePanel();
    };
    ws.onmessage = (ev) => {
      if (typeof ev.data !== "string") return;  // the first hello comes in the server's default (msgpack)
      const m = JSON.parse(ev.data);
      if (m.type === "hello") { state.hello = m; state.hellos += 1; }
      else if (m.type === "frame") {
        state.frame = m; state.frames += 1;
        if (!state.paused) state.shown = m;
        const now = performance.now();
        frameTimes.push(now);
        while (frameTimes.length && frameTimes[0] < now - 1000) frameTimes.shift();
        state.rate = frameTimes.length;
        scheduleDraw();
      } else if (m.type === "camera") { onCamera(m); }
      else if (m.type === "status") { state.status = m; state.statusMessages += 1; updatePanel(); }
      else if (m.type === "heading_reset") { onHeadingReset(m); }
      else if (m.type === "error") {
        state.errors += 1; state.lastError = m.message;
        if (state.headingAsked) {  // the answer to the reset: no suit, or a server without a daemon
          state.headingAsked = false;
          const msg = document.getElementById("headingMsg");
          msg.textContent = `heading reset: ${m.message}`; msg.className = "bad";
        }
      }
    };
    ws.onclose = () => {
      if (socket !== ws) return;
      state.connected = false; state.frame = null; state.shown = null;
      updatePanel(); scheduleDraw();
      setTimeout(connect, retryMs);
      retryMs = Math.min(2000, retryMs * 2);
    };
  }

  // ------------------------------------------------------------------------------------------ input
  let drag = null;
  canvas.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY]; canvas.style.cursor = "grabbing"; });
  window.addEventListener("mouseup", () => { drag = null; canvas.style.cursor = "grab"; });
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    view.auto = false;  // the user has taken the view
    cam.yaw -= (e.clientX - drag[0]) * 0.01;
    cam.pitch = Math.max(-1.4, Math.min(1.4, cam.pitch + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY];
    scheduleDraw();
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    view.auto = false;
    cam.dist = Math.max(MIN_DIST, Math.min(MAX_DIST, cam.dist * Math.exp(e.deltaY * 0.001)));
    scheduleDraw();
  }, { passive: false });
  canvas.addEventListener("dblclick", () => {  // the default angle, fitted to the people again
    Object.assign(cam, { yaw: 0.6, pitch: 0.35 });
    Object.assign(view, { auto: true, fitted: false });
    scheduleDraw();
  });
  window.addEventListener("resize", () => { layoutCameras(); scheduleDraw(); });
  function pause(on) {
    state.paused = on;
    if (!on) {
      state.shown = state.frame;
      for (const p of Object.values(state.cams)) if (p.msg) showCamera(p, p.msg);
    }
    scheduleDraw(); updatePanel();
  }
  window.addEventListener("keydown", (e) => { if (e.key === " ") { e.preventDefault(); pause(!state.paused); } });

  window.mocapdViewer = {
    state, cam, view, palette: PALETTE,
    fitOf: (subjects) => fitOf(subjects),
    project: (p) => project(p),
    pause,
    // What is on screen: per subject its colour and the canvas pixels of its joints.
    drawn: () => (state.shown && state.hello ? state.shown.subjects.map((s) => ({
      id: s.id, colour: colourOf(s.id), points: jointsOf(s).map((p) => project(p)),
      fingers: fingersOf(s).map((h) => ({ joints: h.joints.map((p) => project(p)), tips: h.tips.map((p) => project(p)),
                                          world: h.joints.concat(h.tips) })) })) : []),
    fingersOf: (s) => fingersOf(s),
    colourOf,
    setAvatar,
    // The avatar view: on, loaded, its error, and per subject its bones (avatar.js bones()).
    avatar: {
      get on() { return state.avatarOn; }, get ready() { return !!avatar.view; },
      get error() { return avatar.error || (avatar.view && avatar.view.error); },
      bones: (id) => (avatar.view ? avatar.view.bones(id) : null),
      vrm1Name: (n) => (avatar.view ? avatar.view.vrm1Name(n) : null),
    },
    get frames() { return state.frames; }, get connects() { return state.connects; },
    get connected() { return state.connected; },
    resetHeading,
    setCameras,
    // Camera panels on screen: per camera the message drawn (and whether its image is drawn) and where its
    // canvas is (CSS px), so a test can map full-resolution pixels to the screen: x_css = left + x * scale_x.
    cameraPanels: () => Object.values(state.cams).filter((p) => p.shown).map((p) => {
      const r = p.canvas.getBoundingClientRect(), m = p.shown;
      return { camera: m.camera, name: m.name, frame: m.frame, t_solve_ns: m.t_solve_ns, left: r.left, top: r.top,
               scale_x: r.width / m.width, scale_y: r.height / m.height, width: r.width, height: r.height,
               image: !!p.img,
               subjects: m.subjects.map((s) => ({ id: s.id, colour: colourOf(s.id), joints: s.joints })),
               detections: m.detections, caption: p.cap.textContent };
    }),
  };
  if (state.camerasOn) setCameras(true);
  if (state.avatarOn) setAvatar(true);
  connect();
  scheduleDraw();
})();
