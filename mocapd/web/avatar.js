// mocapd live viewer: the avatar view (issue 44). Loaded by viewer.js on demand (the "Avatar" button, ?avatar=1)
// as an ES module; three.js and @pixiv/three-vrm come through the page's import map from /lib/ (fetched from npm by
// setup/steps/33-viewer-libs.sh into the cache, never committed). Without them the import fails and the viewer
// keeps drawing skeletons.
//
// Every shown subject gets its own copy of the VRM at /avatar.vrm (mocapd's generated mannequin,
// mocapd/protocols/vrm_avatar.py, or the VRM 0.x or 1.0 file of [websocket] avatar), drawn on a transparent WebGL
// canvas over the 2D one, with the 2D view's camera.
//
// Retargeting. mocapd's bone frames are the world's axes at rest (the T-pose facing +Z, +Y up, the person's left
// +X: DESIGN.md), and so are the normalized humanoid bones of three-vrm in VRM 1.0 (VRM 0.x models face -Z: three-vrm
// turns them round, and a rotation is turned with them, q -> (w, -x, y, -z)). So each VRM bone that has a mocapd bone
// (BODY_VRM, the fingers by name) takes mocapd's global rotation G from forward kinematics, and its normalized local
// rotation is inv(G of its nearest present VRM ancestor) * G; a VRM bone without one (shoulders, a missing
// upperChest) keeps its rest rotation relative to its parent. Global rotations are what is carried over, so a VRM
// hierarchy that differs from mocapd's (three spine bones against four) changes nothing but where a bone starts. The
// Hips go to the subject's root, the model scaled by the ratio of the subject's leg (thigh + shank) to the model's.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { VRMLoaderPlugin, VRMUtils } from "@pixiv/three-vrm";

// mocapd body bone (index into hello.bones) of each VRM 1.0 humanoid bone; mocapd's Spine1 has no VRM bone.
export const BODY_VRM = {
  hips: 0, spine: 1, chest: 3, upperChest: 4, neck: 5, head: 6,
  leftUpperArm: 7, leftLowerArm: 8, leftHand: 9, rightUpperArm: 10, rightLowerArm: 11, rightHand: 12,
  leftUpperLeg: 13, leftLowerLeg: 14, leftFoot: 15, leftToes: 16,
  rightUpperLeg: 17, rightLowerLeg: 18, rightFoot: 19, rightToes: 20,
};
const FINGERS = ["Thumb", "Index", "Middle", "Ring", "Little"];

// The VRM 1.0 humanoid's name of a finger bone's Unity name (LeftThumbProximal -> leftThumbMetacarpal: VRM 1.0
// calls the thumb's bones Metacarpal, Proximal, Distal; mocapd/core/hand_skeleton.py VRM1_NAMES).
export function vrm1Name(unity) {
  const side = unity.startsWith("Left") ? "left" : "right", rest = unity.slice(side.length);
  if (!rest.startsWith("Thumb")) return side + rest;
  const seg = { Proximal: "Metacarpal", Intermediate: "Proximal", Distal: "Distal" }[rest.slice(5)];
  return side + "Thumb" + seg;
}

// VRM 1.0 humanoid parents (the specification's hierarchy), parents before children.
const VRM_PARENT = (() => {
  const p = { hips: null, spine: "hips", chest: "spine", upperChest: "chest", neck: "upperChest", head: "neck" };
  for (const s of ["left", "right"]) {
    Object.assign(p, { [s + "Shoulder"]: "upperChest", [s + "UpperArm"]: s + "Shoulder",
                       [s + "LowerArm"]: s + "UpperArm", [s + "Hand"]: s + "LowerArm",
                       [s + "UpperLeg"]: "hips", [s + "LowerLeg"]: s + "UpperLeg", [s + "Foot"]: s + "LowerLeg",
                       [s + "Toes"]: s + "Foot" });
  }
  for (const s of ["left", "right"]) {
    for (const f of FINGERS) {
      const segs = f === "Thumb" ? ["Metacarpal", "Proximal", "Distal"] : ["Proximal", "Intermediate", "Distal"];
      segs.forEach((g, i) => { p[s + f + g] = i === 0 ? s + "Hand" : s + f + segs[i - 1]; });
    }
  }
  return p;
})();
const VRM_ORDER = Object.keys(VRM_PARENT);

function qmul(a, b) {
  return [a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3], a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
          a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1], a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]];
}
const qinv = (q) => [q[0], -q[1], -q[2], -q[3]];
const ID = [1, 0, 0, 0];

// mocapd's global rotations (w, x, y, z) of every VRM bone that has a mocapd bone, by VRM name.
function mocapdGlobals(s, hello, bodyFK) {
  const glob = bodyFK(s).glob, out = {};
  if (!glob.length) return out;
  for (const [name, b] of Object.entries(BODY_VRM)) out[name] = glob[b];
  const names = hello.finger_bones;
  if (!names) return out;
  for (let side = 0; side < 2; side++) {
    const hand = glob[side === 0 ? 9 : 12];
    let g = null;
    for (let b = 0; b < 15; b++) {
      const local = s.hands ? s.hands.rot.slice(60 * side + 4 * b, 60 * side + 4 * b + 4) : ID;
      g = qmul(b % 3 === 0 ? hand : g, local);
      out[vrm1Name(names[15 * side + b])] = g;
    }
  }
  return out;
}

export async function createAvatarView(api) {
  // api: canvas (the WebGL canvas), hello() (the newest hello), bodyFK(subject), colourOf(id), url (the model),
  // redraw() (ask for a draw), failed(message) (a subject's avatar could not be made: its skeleton stays).
  const renderer = new THREE.WebGLRenderer({ canvas: api.canvas, alpha: true, antialias: true });
  renderer.setClearColor(0x000000, 0);
  const scene = new THREE.Scene(), camera = new THREE.PerspectiveCamera(50, 1, 0.05, 200);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x30363f, 2.2));
  const sun = new THREE.DirectionalLight(0xffffff, 1.6);
  sun.position.set(2, 4, 3);
  scene.add(sun);
  const response = await fetch(api.url || "avatar.vrm");
  if (!response.ok) throw new Error(`avatar model: HTTP ${response.status}`);
  const model = await response.arrayBuffer();
  const loader = new GLTFLoader();
  loader.register((parser) => new VRMLoaderPlugin(parser));
  const avatars = new Map();  // subject id -> { vrm, vrm0, scale, leg }

  async function load(id) {
    const gltf = await loader.parseAsync(model.slice(0), "");
    const vrm = gltf.userData.vrm;
    if (!vrm || !vrm.humanoid) throw new Error("avatar model: not a VRM humanoid");
    const vrm0 = vrm.meta && vrm.meta.metaVersion === "0";
    if (vrm0) VRMUtils.rotateVRM0(vrm);
    vrm.scene.traverse((o) => { o.frustumCulled = false; });
    if (vrm.meta && (vrm.meta.name || vrm.meta.title) === "mocapd mannequin") {  // tinted with the subject's colour
      const tint = new THREE.Color(api.colourOf(id)).lerp(new THREE.Color(0xffffff), 0.45);
      vrm.scene.traverse((o) => { if (o.isMesh) { o.material = o.material.clone(); o.material.color = tint; } });
    }
    vrm.scene.updateMatrixWorld(true);
    const at = (n) => vrm.humanoid.getRawBoneNode(n).getWorldPosition(new THREE.Vector3());
    const leg = at("leftUpperLeg").distanceTo(at("leftLowerLeg")) + at("leftLowerLeg").distanceTo(at("leftFoot"));
    scene.add(vrm.scene);
    return { vrm, vrm0, leg, scale: 1 };
  }

  function pose(a, s, hello) {
    // The subject's pose on its avatar (see the header).
    const sk = hello.skeletons[s.skeleton];
    const off = (b) => Math.hypot(sk.offsets[3 * b], sk.offsets[3 * b + 1], sk.offsets[3 * b + 2]);
    a.scale = (off(14) + off(15)) / a.leg;
    a.vrm.scene.scale.setScalar(a.scale);
    const g = mocapdGlobals(s, hello, api.bodyFK), eff = {};
    const turn = (q) => (a.vrm0 ? [q[0], -q[1], q[2], -q[3]] : q);
    for (const name of VRM_ORDER) {
      const node = a.vrm.humanoid.getNormalizedBoneNode(name);
      let parent = VRM_PARENT[name];
      while (parent && !(parent in eff)) parent = VRM_PARENT[parent];  // the nearest present ancestor
      const pg = parent ? eff[parent] : ID;
      if (!node) continue;
      const mine = g[name] ? turn(g[name]) : pg;
      eff[name] = mine;
      const q = qmul(qinv(pg), mine);
      node.quaternion.set(q[1], q[2], q[3], q[0]);
    }
    const hips = a.vrm.humanoid.getNormalizedBoneNode("hips"), r = s.root, k = 1 / a.scale;
    if (a.vrm0) hips.position.set(-r[0] * k, r[1] * k, -r[2] * k);
    else hips.position.set(r[0] * k, r[1] * k, r[2] * k);
    a.vrm.update(0);
  }

  let generation = 0;
  const view = {
    avatars,
    // Pose every shown subject's avatar and draw them from the 2D view's camera (basis: eye, fwd; target; w x h CSS
    // pixels, focal length 0.9 min(w, h) as viewer.js's project()). Returns the ids drawn (their skeletons are not).
    render(subjects, b, target, w, h) {
      const hello = api.hello(), drawn = new Set(), gen = ++generation;
      const dpr = window.devicePixelRatio || 1;
      if (api.canvas.width !== Math.round(w * dpr) || api.canvas.height !== Math.round(h * dpr)) {
        renderer.setPixelRatio(dpr);
        renderer.setSize(w, h, false);
      }
      for (const s of subjects) {
        let a = avatars.get(s.id);
        if (a === undefined) {  // a new subject: its avatar loads, its skeleton is drawn meanwhile
          avatars.set(s.id, null);
          load(s.id).then((x) => { avatars.set(s.id, x); api.redraw(); })
            .catch((e) => { view.error = String(e); if (api.failed) api.failed(view.error); api.redraw(); });
          continue;
        }
        if (a === null || !hello || !hello.skeletons[s.skeleton]) continue;
        pose(a, s, hello);
        a.vrm.scene.visible = true;
        a.shown = gen;
        drawn.add(s.id);
      }
      for (const [id, a] of avatars) {  // subjects gone: their avatars go
        if (a && a.shown !== gen) { scene.remove(a.vrm.scene); VRMUtils.deepDispose(a.vrm.scene); avatars.delete(id); }
      }
      const f = 0.9 * Math.min(w, h);
      camera.fov = (2 * Math.atan(h / 2 / f) * 180) / Math.PI;
      camera.aspect = w / h;
      camera.position.set(b.eye[0], b.eye[1], b.eye[2]);
      camera.up.set(0, 1, 0);
      camera.lookAt(target[0], target[1], target[2]);
      camera.updateProjectionMatrix();
      renderer.render(scene, camera);
      return drawn;
    },
    clear() {
      for (const a of avatars.values()) if (a) { scene.remove(a.vrm.scene); VRMUtils.deepDispose(a.vrm.scene); }
      avatars.clear();
      renderer.clear();
    },
    // For tests: per humanoid bone of subject id's avatar, its normalized local rotation q (w, x, y, z) and its raw
    // bone's world position p (metres, the viewer's world); null before its avatar is loaded.
    bones(id) {
      const a = avatars.get(id);
      if (!a) return null;
      a.vrm.scene.updateMatrixWorld(true);
      const out = {};
      for (const name of VRM_ORDER) {
        const n = a.vrm.humanoid.getNormalizedBoneNode(name), raw = a.vrm.humanoid.getRawBoneNode(name);
        if (!n || !raw) continue;
        const p = raw.getWorldPosition(new THREE.Vector3()), q = n.quaternion;
        out[name] = { q: [q.w, q.x, q.y, q.z], p: [p.x, p.y, p.z] };
      }
      return out;
    },
    vrm1Name,
    error: null,
  };
  return view;
}
