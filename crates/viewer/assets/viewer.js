// dsgs view: renders the scene's Gaussians with WebGL2 (EWA splatting, SH colour,
// back-to-front premultiplied blending) and drives the style API.
import { sortBackToFront, newScratch } from "./sort-worker.js";

const params = new URLSearchParams(location.search);
const FPS_MODE = params.get("fps") === "1";
const BARE = params.get("ui") === "0";
// ?size=native shows a scene camera at its own pixel size instead of fitted to the window.
const NATIVE = params.get("size") === "native";
// ?stylize=1 stylizes the first view with the first painting once the scene is shown (a link
// that opens on a stylized view).
const STYLIZE_AT_START = params.get("stylize") === "1";
const PREVIEW_SIDE = 192;

const $ = (id) => document.getElementById(id);
const canvas = $("canvas");
const stage = $("stage");

window.dsgsReady = false;
window.dsgsFps = 0;
if (BARE) document.body.classList.add("bare");
if (FPS_MODE) document.body.classList.add("fps");

// ---------------------------------------------------------------- math
// 3x3 matrices are row-major arrays of 9 numbers.

const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const cross = (a, b) => [
  a[1] * b[2] - a[2] * b[1],
  a[2] * b[0] - a[0] * b[2],
  a[0] * b[1] - a[1] * b[0],
];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const normalize = (a) => {
  const n = norm(a);
  return n > 0 ? scale(a, 1 / n) : [0, 0, 0];
};
const row = (m, i) => [m[3 * i], m[3 * i + 1], m[3 * i + 2]];

function mul3(a, b) {
  const r = new Array(9);
  for (let i = 0; i < 3; i++) {
    for (let j = 0; j < 3; j++) {
      r[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
    }
  }
  return r;
}

const transpose3 = (m) => [m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8]];
const mulVec = (m, v) => [dot(row(m, 0), v), dot(row(m, 1), v), dot(row(m, 2), v)];

// Rotation by angle (radians) about a unit axis.
function axisAngle(k, angle) {
  const c = Math.cos(angle);
  const s = Math.sin(angle);
  const t = 1 - c;
  const [x, y, z] = k;
  return [
    t * x * x + c, t * x * y - s * z, t * x * z + s * y,
    t * x * y + s * z, t * y * y + c, t * y * z - s * x,
    t * x * z - s * y, t * y * z + s * x, t * z * z + c,
  ];
}

// Keeps the forward row and rebuilds right and down as an exact rotation (OpenCV axes).
function orthonormalize(R) {
  const z = normalize(row(R, 2));
  const x = normalize(cross(row(R, 1), z));
  const y = cross(z, x);
  return [...x, ...y, ...z];
}

// ---------------------------------------------------------------- view state

const view = {
  mode: "fit", // "camera": a scene camera's size and intrinsics; "fit": the window
  camIndex: -1,
  width: 320,
  height: 240,
  fx: 300,
  fy: 300,
  cx: 160,
  cy: 120,
  R: [1, 0, 0, 0, 1, 0, 0, 0, 1], // world to camera rotation
  C: [0, 0, -3], // camera centre in the world
  target: [0, 0, 0],
  exact: null, // a scene camera's camera_from_world while the view is unchanged
  ref: { width: 800, height: 600, fx: 700, fy: 700 }, // intrinsics the fit mode scales
};

const world = {
  up: [0, -1, 0],
  centre: [0, 0, 0],
  scale: 1,
};

function viewT() {
  if (view.exact) return [view.exact[3], view.exact[7], view.exact[11]];
  return scale(mulVec(view.R, view.C), -1);
}

function cameraFromWorld() {
  if (view.exact) return view.exact.slice();
  const R = view.R;
  const t = viewT();
  return [R[0], R[1], R[2], t[0], R[3], R[4], R[5], t[1], R[6], R[7], R[8], t[2], 0, 0, 0, 1];
}

function cameraJson() {
  const cam = view.exact && view.camIndex >= 0 ? scene.info.cameras[view.camIndex] : null;
  return {
    name: cam ? cam.name : "",
    width: view.width,
    height: view.height,
    fx: view.fx,
    fy: view.fy,
    cx: view.cx,
    cy: view.cy,
    camera_from_world: cameraFromWorld(),
  };
}
window.dsgsCamera = cameraJson;

// The pose changed by navigation: drop the exact scene camera.
function poseChanged() {
  view.exact = null;
  view.R = orthonormalize(view.R);
  markCameraList();
  requestDraw();
}

function setPose(R, C, keepTarget) {
  view.R = R;
  view.C = C;
  if (!keepTarget) {
    const f = row(R, 2);
    const toCentre = sub(world.centre, C);
    let d = dot(toCentre, f);
    if (!(d > 0.05 * world.scale)) d = Math.max(norm(toCentre), 0.05 * world.scale);
    view.target = add(C, scale(f, d));
  }
}

function selectCamera(i) {
  const cams = scene.info.cameras;
  if (!(i >= 0 && i < cams.length)) return;
  const cam = cams[i];
  const m = cam.camera_from_world.map(Number);
  view.mode = "camera";
  view.camIndex = i;
  view.width = Math.max(1, Math.round(cam.width));
  view.height = Math.max(1, Math.round(cam.height));
  view.fx = cam.fx;
  view.fy = cam.fy;
  view.cx = cam.cx;
  view.cy = cam.cy;
  view.ref = { width: view.width, height: view.height, fx: cam.fx, fy: cam.fy };
  const R = [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]];
  const t = [m[3], m[7], m[11]];
  setPose(R, scale(mulVec(transpose3(R), t), -1), false);
  view.exact = m;
  applySize();
  markCameraList();
  requestDraw();
}

// Fill the stage, scaling the reference intrinsics (same vertical field of view).
function fitWindow() {
  view.mode = "fit";
  applySize();
  markCameraList();
}

// The room for the view: the stage, or half of it when the result is shown beside.
function viewRoom() {
  const beside = !resultBeside.hidden;
  let w = stage.clientWidth;
  if (beside) w = (w - 8) / 2;
  return [Math.max(1, Math.floor(w)), Math.max(1, Math.floor(stage.clientHeight))];
}

function applySize() {
  if (view.mode === "camera" && !NATIVE) {
    // The scene camera scaled to fit the room: its pose and field of view, scaled intrinsics.
    const cam = scene.info.cameras[view.camIndex];
    const [rw, rh] = viewRoom();
    const s = Math.min(rw / cam.width, rh / cam.height);
    view.width = Math.max(1, Math.floor(cam.width * s));
    view.height = Math.max(1, Math.floor(cam.height * s));
    const sx = view.width / cam.width;
    const sy = view.height / cam.height;
    view.fx = cam.fx * sx;
    view.fy = cam.fy * sy;
    view.cx = cam.cx * sx;
    view.cy = cam.cy * sy;
  } else if (view.mode === "fit") {
    const beside = !resultBeside.hidden;
    let w = stage.clientWidth;
    if (beside) w = (w - 8) / 2;
    const w1 = Math.max(1, Math.floor(w));
    const h1 = Math.max(1, Math.floor(stage.clientHeight));
    const r = view.ref;
    view.width = w1;
    view.height = h1;
    view.fy = (r.fy * h1) / r.height;
    view.fx = (view.fy * r.fx) / r.fy;
    view.cx = w1 / 2;
    view.cy = h1 / 2;
    view.exact = null;
  }
  if (canvas.width !== view.width) canvas.width = view.width;
  if (canvas.height !== view.height) canvas.height = view.height;
  canvas.style.width = `${view.width}px`;
  canvas.style.height = `${view.height}px`;
  $("view-size").textContent =
    `${view.width} x ${view.height} px, f ${view.fx.toFixed(1)}, ` +
    (view.mode === "camera" ? `camera ${view.camIndex}` : "fitted to the window");
  sizeResult();
  requestDraw();
}

// ---------------------------------------------------------------- navigation

function orbit(dx, dy) {
  const a = -dx * 0.005;
  const b = -dy * 0.005;
  let M = axisAngle(world.up, a);
  // Pitch about the camera's right axis first, then yaw; pitch only while the view stays
  // off the up axis.
  const both = mul3(M, axisAngle(normalize(row(view.R, 0)), b));
  if (Math.abs(dot(mulVec(both, row(view.R, 2)), world.up)) < 0.995) M = both;
  const off = mulVec(M, sub(view.C, view.target));
  view.C = add(view.target, off);
  view.R = mul3(view.R, transpose3(M));
  poseChanged();
}

function look(dx, dy) {
  const dist = Math.max(norm(sub(view.target, view.C)), 1e-6 * world.scale);
  let M = axisAngle(world.up, -dx * 0.003);
  const both = mul3(M, axisAngle(normalize(row(view.R, 0)), -dy * 0.003));
  if (Math.abs(dot(mulVec(both, row(view.R, 2)), world.up)) < 0.995) M = both;
  view.R = mul3(view.R, transpose3(M));
  view.target = add(view.C, scale(normalize(row(view.R, 2)), dist));
  poseChanged();
}

function pan(dx, dy) {
  const dist = norm(sub(view.target, view.C));
  const s = dist / view.fy;
  const move = add(scale(row(view.R, 0), -dx * s), scale(row(view.R, 1), -dy * s));
  view.C = add(view.C, move);
  view.target = add(view.target, move);
  poseChanged();
}

function zoom(delta) {
  const f = normalize(row(view.R, 2));
  const dist = norm(sub(view.target, view.C));
  const d = Math.max(dist * Math.exp(delta * 0.0015), 1e-3 * world.scale);
  view.C = sub(view.target, scale(f, d));
  poseChanged();
}

const keys = new Set();
const MOVE_KEYS = ["KeyW", "KeyA", "KeyS", "KeyD", "KeyQ", "KeyE"];
const movementHeld = () => MOVE_KEYS.some((k) => keys.has(k));

function fly(dt) {
  if (!movementHeld()) return;
  const speed = world.scale * 0.5 * (keys.has("ShiftLeft") || keys.has("ShiftRight") ? 4 : 1);
  const f = row(view.R, 2);
  const r = row(view.R, 0);
  let m = [0, 0, 0];
  if (keys.has("KeyW")) m = add(m, f);
  if (keys.has("KeyS")) m = sub(m, f);
  if (keys.has("KeyD")) m = add(m, r);
  if (keys.has("KeyA")) m = sub(m, r);
  if (keys.has("KeyE")) m = add(m, world.up);
  if (keys.has("KeyQ")) m = sub(m, world.up);
  if (norm(m) === 0) return;
  const step = scale(normalize(m), speed * dt);
  view.C = add(view.C, step);
  view.target = add(view.target, step);
  poseChanged();
}

let drag = null;
canvas.tabIndex = 0;
canvas.addEventListener("contextmenu", (e) => e.preventDefault());
canvas.addEventListener("pointerdown", (e) => {
  canvas.focus();
  canvas.setPointerCapture(e.pointerId);
  let kind = "orbit";
  if (e.button === 2 || e.button === 1 || e.shiftKey) kind = "pan";
  else if ($("fly").checked || movementHeld()) kind = "look";
  drag = { kind, x: e.clientX, y: e.clientY, id: e.pointerId };
  canvas.classList.add("dragging");
});
canvas.addEventListener("pointermove", (e) => {
  if (drag && e.pointerId === drag.id) {
    const dx = e.clientX - drag.x;
    const dy = e.clientY - drag.y;
    drag.x = e.clientX;
    drag.y = e.clientY;
    if (dx === 0 && dy === 0) return;
    const kind = drag.kind === "orbit" && movementHeld() ? "look" : drag.kind;
    if (kind === "orbit") orbit(dx, dy);
    else if (kind === "look") look(dx, dy);
    else pan(dx, dy);
  } else if (!drag && movementHeld() && (e.movementX || e.movementY)) {
    look(e.movementX, e.movementY);
  }
});
const endDrag = (e) => {
  if (drag && e.pointerId === drag.id) {
    drag = null;
    canvas.classList.remove("dragging");
  }
};
canvas.addEventListener("pointerup", endDrag);
canvas.addEventListener("pointercancel", endDrag);
canvas.addEventListener(
  "wheel",
  (e) => {
    e.preventDefault();
    const unit = e.deltaMode === 1 ? 16 : e.deltaMode === 2 ? 400 : 1;
    zoom(e.deltaY * unit);
  },
  { passive: false },
);

const typing = (el) =>
  el && (el.tagName === "TEXTAREA" || el.tagName === "SELECT" ||
    (el.tagName === "INPUT" && !["checkbox", "range", "button", "file"].includes(el.type)));

window.addEventListener("keydown", (e) => {
  if (typing(e.target) || e.ctrlKey || e.metaKey || e.altKey) return;
  if (MOVE_KEYS.includes(e.code) || e.code.startsWith("Shift")) {
    keys.add(e.code);
    if (MOVE_KEYS.includes(e.code)) e.preventDefault();
  } else if (e.code === "KeyF") {
    $("fly").checked = !$("fly").checked;
  } else if (e.code === "BracketLeft" || e.code === "BracketRight") {
    const n = scene.info ? scene.info.cameras.length : 0;
    if (n > 0) {
      const step = e.code === "BracketRight" ? 1 : -1;
      const from = view.camIndex < 0 ? (step > 0 ? -1 : 0) : view.camIndex;
      selectCamera((from + step + n) % n);
    }
  }
});
window.addEventListener("keyup", (e) => keys.delete(e.code));
window.addEventListener("blur", () => keys.clear());

// ---------------------------------------------------------------- WebGL2 renderer

const SPLAT_VS = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
precision highp usampler2D;

uniform sampler2D uData;   // per Gaussian: mean+opacity, covariance (2 texels), SH
uniform usampler2D uOrder; // Gaussian indices, back to front
uniform int uTexW;
uniform int uStride;       // texels per Gaussian
uniform int uDegree;
uniform mat3 uRot;         // world to camera rotation
uniform vec3 uTrans;
uniform vec3 uCamPos;
uniform vec4 uIntr;        // fx, fy, cx, cy
uniform vec2 uSize;        // width, height

flat out vec2 vMean;
flat out vec3 vConic;
flat out vec4 vColour;

const float SH_C0 = 0.28209479177387814;
const float SH_C1 = 0.4886025119029199;
const float SH_C2[5] = float[5](1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
  -1.0925484305920792, 0.5462742152960396);
const float SH_C3[7] = float[7](-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
  0.3731763325901154, -0.4570457994644658, 1.445305721320277, -0.5900435899266435);

vec4 fetch(int k) {
  return texelFetch(uData, ivec2(k % uTexW, k / uTexW), 0);
}

void cull() {
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);
}

// View-dependent colour from the SH floats (3 per coefficient, 4 per texel from texel b).
vec3 shColour(int b, vec3 d) {
  vec4 s0 = fetch(b);
  vec3 c = SH_C0 * s0.xyz;
  if (uDegree > 0) {
    vec4 s1 = fetch(b + 1), s2 = fetch(b + 2);
    float x = d.x, y = d.y, z = d.z;
    c += -SH_C1 * y * vec3(s0.w, s1.xy) + SH_C1 * z * vec3(s1.zw, s2.x) - SH_C1 * x * s2.yzw;
    if (uDegree > 1) {
      vec4 s3 = fetch(b + 3), s4 = fetch(b + 4), s5 = fetch(b + 5), s6 = fetch(b + 6);
      float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
      c += SH_C2[0] * xy * s3.xyz + SH_C2[1] * yz * vec3(s3.w, s4.xy)
        + SH_C2[2] * (2.0 * zz - xx - yy) * vec3(s4.zw, s5.x)
        + SH_C2[3] * xz * s5.yzw + SH_C2[4] * (xx - yy) * s6.xyz;
      if (uDegree > 2) {
        vec4 s7 = fetch(b + 7), s8 = fetch(b + 8), s9 = fetch(b + 9);
        vec4 s10 = fetch(b + 10), s11 = fetch(b + 11);
        c += SH_C3[0] * y * (3.0 * xx - yy) * vec3(s6.w, s7.xy)
          + SH_C3[1] * xy * z * vec3(s7.zw, s8.x)
          + SH_C3[2] * y * (4.0 * zz - xx - yy) * s8.yzw
          + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * s9.xyz
          + SH_C3[4] * x * (4.0 * zz - xx - yy) * vec3(s9.w, s10.xy)
          + SH_C3[5] * z * (xx - yy) * vec3(s10.zw, s11.x)
          + SH_C3[6] * x * (xx - 3.0 * yy) * s11.yzw;
      }
    }
  }
  return max(c + 0.5, 0.0);
}

void main() {
  // Four vertices per quad (no instancing: software GL runs instances one by one).
  int slot = gl_VertexID >> 2;
  int corner = gl_VertexID & 3;
  vec2 aCorner = vec2((corner & 1) == 1 ? 1.0 : -1.0, (corner & 2) == 2 ? 1.0 : -1.0);
  int index = int(texelFetch(uOrder, ivec2(slot % uTexW, slot / uTexW), 0).r);
  int base = index * uStride;
  vec4 t0 = fetch(base);
  vec4 t1 = fetch(base + 1);
  vec4 t2 = fetch(base + 2);
  vec3 mean = t0.xyz;
  vec3 t = uRot * mean + uTrans;
  if (t.z <= 0.01) { cull(); return; }

  float fx = uIntr.x, fy = uIntr.y, cx = uIntr.z, cy = uIntr.w;
  // Jacobian at the position clamped to 1.3x the field of view.
  float tanX = 0.5 * uSize.x / fx;
  float tanY = 0.5 * uSize.y / fy;
  float tx = clamp(t.x / t.z, -(cx / fx + 0.3 * tanX), (uSize.x - cx) / fx + 0.3 * tanX) * t.z;
  float ty = clamp(t.y / t.z, -(cy / fy + 0.3 * tanY), (uSize.y - cy) / fy + 0.3 * tanY) * t.z;
  float iz = 1.0 / t.z;
  // Column-major: J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]].
  mat3 J = mat3(fx * iz, 0.0, 0.0,
                0.0, fy * iz, 0.0,
                -fx * tx * iz * iz, -fy * ty * iz * iz, 0.0);
  mat3 V = mat3(t1.x, t1.y, t1.z,
                t1.y, t1.w, t2.x,
                t1.z, t2.x, t2.y);
  mat3 T = J * uRot;
  mat3 cov = T * V * transpose(T);
  float a = cov[0][0] + 0.3;
  float b = cov[1][0];
  float c = cov[1][1] + 0.3;
  float det = a * c - b * b;
  if (det <= 0.0) { cull(); return; }
  vec3 conic = vec3(c, -b, a) / det;
  vec2 mean2d = vec2(fx * t.x * iz + cx, fy * t.y * iz + cy);
  // Alpha reaches 1/255 where sigma = log(255 opacity): an ellipse with semi-axes
  // sqrt(2 log(255 opacity) lambda) along the eigenvectors of cov2d. The quad covers it
  // exactly, inside the rasterizer's box of ceil(3.33 sqrt(cov2d_xx)) by ceil(3.33 sqrt(cov2d_yy)).
  float level = log(255.0 * t0.w);
  if (!(level > 0.0)) { cull(); return; }
  float mid = 0.5 * (a + c);
  float rad = sqrt(max(0.25 * (a - c) * (a - c) + b * b, 0.0));
  float l1 = mid + rad;
  float l2 = max(mid - rad, 0.0);
  vec2 e1 = abs(b) > 1e-12 * mid ? normalize(vec2(b, l1 - a)) : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  vec2 e2 = vec2(-e1.y, e1.x);
  float k = sqrt(2.0 * level) * 1.001;
  vec2 p = mean2d + aCorner.x * (k * sqrt(l1)) * e1 + aCorner.y * (k * sqrt(l2)) * e2;
  gl_Position = vec4(2.0 * p.x / uSize.x - 1.0, 1.0 - 2.0 * p.y / uSize.y, 0.0, 1.0);
  vMean = mean2d;
  vConic = conic;
  vColour = vec4(shColour(base + 3, normalize(mean - uCamPos)), t0.w);
}
`;

const SPLAT_FS = `#version 300 es
precision highp float;
uniform float uHeight;
flat in vec2 vMean;
flat in vec3 vConic;
flat in vec4 vColour;
out vec4 outColour;
void main() {
  // Pixel centre in image coordinates (y down).
  vec2 d = vMean - vec2(gl_FragCoord.x, uHeight - gl_FragCoord.y);
  float sigma = 0.5 * (vConic.x * d.x * d.x + vConic.z * d.y * d.y) + vConic.y * d.x * d.y;
  if (sigma < 0.0) discard;
  float alpha = min(0.999, vColour.a * exp(-sigma));
  if (alpha < 1.0 / 255.0) discard;
  outColour = vec4(vColour.rgb * alpha, alpha);
}
`;

const BLIT_VS = `#version 300 es
void main() {
  vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}
`;

const BLIT_FS = `#version 300 es
precision highp float;
uniform highp sampler2D uImage;
out vec4 outColour;
void main() {
  vec3 c = texelFetch(uImage, ivec2(gl_FragCoord.xy), 0).rgb;
  outColour = vec4(clamp(c, 0.0, 1.0), 1.0);
}
`;

class Renderer {
  constructor(canvasEl) {
    const gl = canvasEl.getContext("webgl2", {
      alpha: false,
      antialias: false,
      depth: false,
      stencil: false,
      premultipliedAlpha: true,
      preserveDrawingBuffer: false,
      powerPreference: "high-performance",
    });
    if (!gl) throw new Error("WebGL2 is not available in this browser.");
    this.gl = gl;
    this.maxTex = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    // A float target keeps colours above 1 until the end, as the reference does.
    const cbf = gl.getExtension("EXT_color_buffer_float");
    const blend32 = cbf && gl.getExtension("EXT_float_blend");
    this.targetFormat = cbf ? (blend32 ? gl.RGBA32F : gl.RGBA16F) : null;
    this.splat = this.program(SPLAT_VS, SPLAT_FS);
    this.blit = this.program(BLIT_VS, BLIT_FS);
    this.u = {};
    for (const name of ["uData", "uOrder", "uTexW", "uStride", "uDegree", "uRot", "uTrans",
      "uCamPos", "uIntr", "uSize", "uHeight"]) {
      this.u[name] = gl.getUniformLocation(this.splat, name);
    }
    this.uImage = gl.getUniformLocation(this.blit, "uImage");

    this.vao = gl.createVertexArray();
    this.quadIndices = gl.createBuffer();
    this.quadCapacity = 0;
    this.orderTex = null;
    this.emptyVao = gl.createVertexArray();

    this.dataTex = null;
    this.count = 0;
    this.target = null;
  }

  program(vsSource, fsSource) {
    const gl = this.gl;
    const shader = (type, src) => {
      const s = gl.createShader(type);
      gl.shaderSource(s, src);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) {
        throw new Error(`shader compilation failed: ${gl.getShaderInfoLog(s)}`);
      }
      return s;
    };
    const p = gl.createProgram();
    gl.attachShader(p, shader(gl.VERTEX_SHADER, vsSource));
    gl.attachShader(p, shader(gl.FRAGMENT_SHADER, fsSource));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) {
      throw new Error(`shader link failed: ${gl.getProgramInfoLog(p)}`);
    }
    return p;
  }

  // Uploads packed Gaussians (see packGaussians).
  setData(packed) {
    const gl = this.gl;
    if (this.dataTex) gl.deleteTexture(this.dataTex);
    this.dataTex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.dataTex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, packed.texW, packed.rows, 0, gl.RGBA, gl.FLOAT,
      packed.data);
    // The draw order, one index per texel.
    if (this.orderTex) gl.deleteTexture(this.orderTex);
    this.orderTex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.orderTex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.R32UI, packed.texW, Math.max(1, Math.ceil(packed.n / packed.texW)));
    gl.bindTexture(gl.TEXTURE_2D, null);
    // Two triangles per quad, vertex k of quad q at 4 q + k.
    if (packed.n > this.quadCapacity) {
      const idx = new Uint32Array(6 * packed.n);
      for (let q = 0, o = 0; q < packed.n; q++, o += 6) {
        const v = 4 * q;
        idx[o] = v; idx[o + 1] = v + 1; idx[o + 2] = v + 2;
        idx[o + 3] = v + 1; idx[o + 4] = v + 3; idx[o + 5] = v + 2;
      }
      gl.bindVertexArray(this.vao);
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.quadIndices);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, idx, gl.STATIC_DRAW);
      gl.bindVertexArray(null);
      this.quadCapacity = packed.n;
    }
    this.packed = { n: packed.n, texW: packed.texW, stride: packed.stride,
      shTexels: packed.shTexels, degree: packed.degree };
    this.count = 0;
  }

  setOrder(indices, count) {
    const gl = this.gl;
    this.count = count;
    if (count === 0) return;
    const w = this.packed.texW;
    const full = Math.floor(count / w);
    const rest = count - full * w;
    gl.bindTexture(gl.TEXTURE_2D, this.orderTex);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
    if (full > 0) {
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, w, full, gl.RED_INTEGER, gl.UNSIGNED_INT, indices, 0);
    }
    if (rest > 0) {
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, full, rest, 1, gl.RED_INTEGER, gl.UNSIGNED_INT, indices,
        full * w);
    }
    gl.bindTexture(gl.TEXTURE_2D, null);
  }

  ensureTarget(w, h) {
    const gl = this.gl;
    if (!this.targetFormat) return null;
    if (this.target && this.target.w === w && this.target.h === h) return this.target;
    if (this.target) {
      gl.deleteFramebuffer(this.target.fbo);
      gl.deleteTexture(this.target.tex);
    }
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texStorage2D(gl.TEXTURE_2D, 1, this.targetFormat, w, h);
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
    const ok = gl.checkFramebufferStatus(gl.FRAMEBUFFER) === gl.FRAMEBUFFER_COMPLETE;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.bindTexture(gl.TEXTURE_2D, null);
    if (!ok) {
      gl.deleteFramebuffer(fbo);
      gl.deleteTexture(tex);
      this.target = null;
      this.targetFormat = null;
      return null;
    }
    this.target = { w, h, tex, fbo };
    return this.target;
  }

  draw(v, background) {
    const gl = this.gl;
    const w = v.width;
    const h = v.height;
    const target = this.ensureTarget(w, h);
    gl.bindFramebuffer(gl.FRAMEBUFFER, target ? target.fbo : null);
    gl.viewport(0, 0, w, h);
    gl.disable(gl.DEPTH_TEST);
    gl.clearColor(background[0], background[1], background[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    if (this.dataTex && this.count > 0) {
      const p = this.packed;
      const u = this.u;
      gl.useProgram(this.splat);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.dataTex);
      gl.uniform1i(u.uData, 0);
      gl.activeTexture(gl.TEXTURE1);
      gl.bindTexture(gl.TEXTURE_2D, this.orderTex);
      gl.uniform1i(u.uOrder, 1);
      gl.uniform1i(u.uTexW, p.texW);
      gl.uniform1i(u.uStride, p.stride);
      gl.uniform1i(u.uDegree, p.degree);
      gl.uniformMatrix3fv(u.uRot, false, transpose3(v.R)); // column-major
      gl.uniform3fv(u.uTrans, v.t);
      gl.uniform3fv(u.uCamPos, v.C);
      gl.uniform4f(u.uIntr, v.fx, v.fy, v.cx, v.cy);
      gl.uniform2f(u.uSize, w, h);
      gl.uniform1f(u.uHeight, h);
      gl.enable(gl.BLEND);
      gl.blendEquation(gl.FUNC_ADD);
      gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
      gl.bindVertexArray(this.vao);
      gl.drawElements(gl.TRIANGLES, 6 * this.count, gl.UNSIGNED_INT, 0);
      gl.bindVertexArray(null);
      gl.disable(gl.BLEND);
    }
    if (target) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.viewport(0, 0, w, h);
      gl.useProgram(this.blit);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, target.tex);
      gl.uniform1i(this.uImage, 0);
      gl.bindVertexArray(this.emptyVao);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      gl.bindVertexArray(null);
    }
  }
}

// Packs the API's records into one RGBA32F texture, `stride` texels per Gaussian:
// (mean, opacity), (cov xx, xy, xz, yy), (cov yz, zz, -, -), then the SH floats
// (3 per coefficient, padded to whole texels).
function packGaussians(buffer, degree, floatsPer, maxTex) {
  const K = (degree + 1) * (degree + 1);
  if (floatsPer !== 11 + 3 * K) {
    throw new Error(`the Gaussians have ${floatsPer} floats each; SH degree ${degree} needs ${11 + 3 * K}`);
  }
  if (buffer.byteLength % (4 * floatsPer) !== 0) {
    throw new Error(`the Gaussian data (${buffer.byteLength} bytes) is not a whole number of records`);
  }
  const src = new Float32Array(buffer);
  const n = src.length / floatsPer;
  const shTexels = Math.ceil((3 * K) / 4);
  const stride = 3 + shTexels;
  const texW = Math.min(4096, maxTex);
  const rows = Math.max(1, Math.ceil((n * stride) / texW));
  if (rows > maxTex) {
    throw new Error(`${n} Gaussians do not fit this GPU's textures (at most ${maxTex} x ${maxTex})`);
  }
  const data = new Float32Array(texW * rows * 4);
  const means = new Float32Array(3 * n);
  for (let i = 0; i < n; i++) {
    const s = i * floatsPer;
    const o = i * stride * 4;
    const x = src[s], y = src[s + 1], z = src[s + 2];
    means[3 * i] = x;
    means[3 * i + 1] = y;
    means[3 * i + 2] = z;
    const sx = src[s + 3], sy = src[s + 4], sz = src[s + 5];
    let qw = src[s + 6], qx = src[s + 7], qy = src[s + 8], qz = src[s + 9];
    const qn = Math.hypot(qw, qx, qy, qz) || 1;
    qw /= qn; qx /= qn; qy /= qn; qz /= qn;
    // Rotation matrix of (w, x, y, z), times diag(scale).
    const m00 = (1 - 2 * (qy * qy + qz * qz)) * sx;
    const m01 = 2 * (qx * qy - qw * qz) * sy;
    const m02 = 2 * (qx * qz + qw * qy) * sz;
    const m10 = 2 * (qx * qy + qw * qz) * sx;
    const m11 = (1 - 2 * (qx * qx + qz * qz)) * sy;
    const m12 = 2 * (qy * qz - qw * qx) * sz;
    const m20 = 2 * (qx * qz - qw * qy) * sx;
    const m21 = 2 * (qy * qz + qw * qx) * sy;
    const m22 = (1 - 2 * (qx * qx + qy * qy)) * sz;
    data[o] = x;
    data[o + 1] = y;
    data[o + 2] = z;
    data[o + 3] = src[s + 10];
    // Sigma = M M^T.
    data[o + 4] = m00 * m00 + m01 * m01 + m02 * m02;
    data[o + 5] = m00 * m10 + m01 * m11 + m02 * m12;
    data[o + 6] = m00 * m20 + m01 * m21 + m02 * m22;
    data[o + 7] = m10 * m10 + m11 * m11 + m12 * m12;
    data[o + 8] = m10 * m20 + m11 * m21 + m12 * m22;
    data[o + 9] = m20 * m20 + m21 * m21 + m22 * m22;
    data.set(src.subarray(s + 11, s + floatsPer), o + 12);
  }
  return { n, degree, stride, shTexels, texW, rows, data, means };
}

// Robust centre and size of the scene, from a sample of the means and the cameras.
function measureWorld(means, n, cameras) {
  const step = Math.max(1, Math.floor(n / 20000));
  const xs = [], ys = [], zs = [];
  for (let i = 0; i < n; i += step) {
    xs.push(means[3 * i]);
    ys.push(means[3 * i + 1]);
    zs.push(means[3 * i + 2]);
  }
  const median = (a) => {
    if (a.length === 0) return 0;
    a.sort((p, q) => p - q);
    return a[a.length >> 1];
  };
  const centre = n > 0 ? [median(xs), median(ys), median(zs)] : [0, 0, 0];
  const centres = cameras.map((c) => {
    const m = c.camera_from_world;
    const R = [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]];
    return scale(mulVec(transpose3(R), [m[3], m[7], m[11]]), -1);
  });
  let size = median(centres.map((c) => norm(sub(c, centre))));
  if (!(size > 0)) {
    const d = [];
    for (let i = 0; i < n; i += step) {
      d.push(norm(sub([means[3 * i], means[3 * i + 1], means[3 * i + 2]], centre)));
    }
    size = 2 * (median(d) || 1);
  }
  return { centre, scale: size };
}

function upFromCameras(cameras) {
  let u = [0, 0, 0];
  for (const c of cameras) {
    const m = c.camera_from_world;
    u = sub(u, [m[4], m[5], m[6]]); // image up is -y
  }
  return norm(u) > 1e-6 ? normalize(u) : [0, -1, 0];
}

// ---------------------------------------------------------------- depth sort

class Sorter {
  constructor(onSorted) {
    this.onSorted = onSorted;
    this.gen = 0;
    this.seq = 0;
    this.busy = false;
    this.pending = null;
    this.spare = null;
    this.means = null;
    this.n = 0;
    this.scratch = null;
    try {
      this.worker = new Worker(new URL("./sort-worker.js", import.meta.url), { type: "module" });
      this.worker.onmessage = (e) => this.received(e.data);
      this.worker.onerror = (e) => {
        e.preventDefault();
        this.fallBack();
      };
    } catch {
      this.worker = null;
    }
  }

  fallBack() {
    if (!this.worker) return;
    this.worker.terminate();
    this.worker = null;
    const row = this.inFlight || this.pending;
    this.busy = false;
    this.inFlight = null;
    if (row) this.request(row);
  }

  setScene(means, n) {
    this.gen++;
    this.means = means;
    this.n = n;
    this.busy = false;
    this.pending = null;
    this.inFlight = null;
    this.spare = null;
    // The first order is computed here, so the first frame needs no round trip (and
    // headless screenshots under virtual time see it).
    this.syncNext = true;
    if (this.worker) this.worker.postMessage({ type: "scene", means, n, gen: this.gen });
  }

  request(row) {
    if (this.busy) {
      this.pending = row;
      return;
    }
    this.busy = true;
    this.inFlight = row;
    const seq = ++this.seq;
    if (this.worker && !this.syncNext) {
      const msg = { type: "sort", row, gen: this.gen, seq };
      const transfer = [];
      if (this.spare) {
        msg.buffer = this.spare;
        transfer.push(this.spare);
        this.spare = null;
      }
      this.worker.postMessage(msg, transfer);
    } else {
      this.syncNext = false;
      const t0 = performance.now();
      if (!this.scratch) this.scratch = newScratch();
      const out = new Uint32Array(Math.max(this.n, 1));
      const count = sortBackToFront(this.means, this.n, row, out, this.scratch);
      const ms = performance.now() - t0;
      this.received({ gen: this.gen, seq, count, ms, indices: out });
      // The worker keeps its own scratch; free this one.
      if (this.worker) this.scratch = null;
    }
  }

  received(msg) {
    if (msg.gen !== this.gen) return;
    const row = this.inFlight;
    this.busy = false;
    this.inFlight = null;
    this.onSorted(msg.indices, msg.count, row, msg.ms);
    this.spare = msg.indices.buffer;
    if (this.pending) {
      const next = this.pending;
      this.pending = null;
      this.request(next);
    }
  }
}

// ---------------------------------------------------------------- scene and frames

const scene = {
  info: null,
  loaded: false, // Gaussians uploaded
  source: "original", // or "baked"
  bakedUrl: null,
  n: 0,
};

let renderer = null;
let sorter = null;
let sortedRow = null; // the depth row of the uploaded order
let requestedRow = null;
let needsDraw = true;
let ready = false; // the first complete frame is drawn
const frameTimes = [];
let lastSortMs = 0;

function requestDraw() {
  needsDraw = true;
}

function depthRow() {
  const t = viewT();
  return [view.R[6], view.R[7], view.R[8], t[2]];
}

const sameRow = (a, b) => a && b && a[0] === b[0] && a[1] === b[1] && a[2] === b[2] && a[3] === b[3];

function drawNow() {
  const C = view.exact ? scale(mulVec(transpose3(view.R), viewT()), -1) : view.C;
  renderer.draw(
    { width: view.width, height: view.height, fx: view.fx, fy: view.fy, cx: view.cx, cy: view.cy,
      R: view.R, t: viewT(), C },
    scene.info.background || [0, 0, 0],
  );
}

// Draws the current view and returns the canvas as a PNG data URL.
window.dsgsSnapshot = () => {
  if (!renderer || !scene.info) return null;
  drawNow();
  return canvas.toDataURL("image/png");
};

let lastTime = performance.now();
function frame(now) {
  requestAnimationFrame(frame);
  const dt = Math.min(0.1, Math.max(0, (now - lastTime) / 1000));
  lastTime = now;
  if (!renderer || !scene.info) return;
  fly(dt);
  if (scene.loaded) {
    const r = depthRow();
    if (!sameRow(r, requestedRow)) {
      requestedRow = r;
      sorter.request(r);
    }
  }
  if (!(needsDraw || FPS_MODE)) return;
  needsDraw = false;
  drawNow();
  frameTimes.push(now);
  if (!ready && scene.loaded && sameRow(sortedRow, depthRow())) {
    // The first complete frame: wait for the GPU so that it is there to be captured.
    renderer.gl.finish();
    ready = true;
    document.title = `dsgs view: ${scene.info.name}`;
    window.dsgsReady = true;
  }
}

// Frames drawn over the last second; with continuous redraw slower than 2 frames a second,
// the rate of the last frame interval.
function updateFps() {
  const now = performance.now();
  while (frameTimes.length > 2 && frameTimes[0] < now - 1000) frameTimes.shift();
  const recent = frameTimes.filter((t) => t >= now - 1000).length;
  let fps = recent;
  if (FPS_MODE && recent < 2 && frameTimes.length === 2 && frameTimes[0] >= now - 5000) {
    fps = Math.round(10000 / (frameTimes[1] - frameTimes[0])) / 10;
  }
  window.dsgsFps = fps;
  const text = !FPS_MODE && recent === 0 ? "idle" : `${fps} fps`;
  $("fps").textContent = text;
  $("fps-float").textContent = `${fps} fps`;
  $("sort-info").textContent = scene.loaded
    ? `· sort ${lastSortMs.toFixed(0)} ms · ${renderer ? renderer.count.toLocaleString() : 0} drawn`
    : "";
}
setInterval(updateFps, 250);

function showMessage(text) {
  const m = $("message");
  m.textContent = text;
  m.hidden = !text;
}

async function errorText(res) {
  const body = await res.text().catch(() => "");
  try {
    const j = JSON.parse(body);
    if (j && typeof j.error === "string") return j.error;
  } catch {
    // not JSON
  }
  if (res.status === 413) return "the file is too large";
  return `${res.status} ${res.statusText}${body ? `: ${body.slice(0, 200)}` : ""}`;
}

async function fetchJson(url, init) {
  const res = await fetch(url, init);
  if (!res.ok) throw new Error(`${url}: ${await errorText(res)}`);
  return res.json();
}

// Fetches a binary body with progress. XMLHttpRequest keeps the request pending until the
// body is complete, which headless Chromium's virtual time waits for (a streamed fetch is not).
function fetchBytes(url, expected, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("GET", url);
    xhr.responseType = "arraybuffer";
    xhr.onprogress = (e) => {
      const total = expected || (e.lengthComputable ? e.total : 0);
      if (total) onProgress(Math.min(1, e.loaded / total));
    };
    xhr.onload = () => {
      const body = xhr.response;
      if (xhr.status < 200 || xhr.status >= 300) {
        let msg = `${xhr.status} ${xhr.statusText}`;
        try {
          const j = JSON.parse(new TextDecoder().decode(body));
          if (j && typeof j.error === "string") msg = j.error;
        } catch {
          // not JSON
        }
        reject(new Error(`${url}: ${msg}`));
      } else if (expected && body.byteLength !== expected) {
        reject(new Error(`${url}: expected ${expected} bytes, received ${body.byteLength}`));
      } else {
        resolve(body);
      }
    };
    xhr.onerror = () => reject(new Error(`${url}: the request failed`));
    xhr.send();
  });
}

async function loadGaussians(url, degree, floatsPer, count) {
  const label = $("scene-info");
  const expected = count != null ? count * floatsPer * 4 : 0;
  const buffer = await fetchBytes(url, expected, (p) => {
    label.textContent = `loading Gaussians ${Math.round(100 * p)}%`;
  });
  const packed = packGaussians(buffer, degree, floatsPer, renderer.maxTex);
  renderer.setData(packed);
  sortedRow = null;
  requestedRow = null;
  scene.n = packed.n;
  sorter.setScene(packed.means, packed.n);
  scene.loaded = true;
  requestDraw();
  return packed;
}

function describeScene() {
  const i = scene.info;
  const parts = [
    `${scene.n.toLocaleString()} Gaussians`,
    `SH degree ${scene.source === "baked" ? 3 : i.sh_degree}`,
  ];
  if (i.variant) parts.push(i.variant);
  if (scene.source === "baked") parts.push("baked style");
  $("scene-info").textContent = parts.join(" · ");
}

function buildCameraList() {
  const list = $("cameras");
  list.textContent = "";
  scene.info.cameras.forEach((c, i) => {
    const o = document.createElement("option");
    o.value = String(i);
    o.textContent = `${i}: ${c.name || "camera"} (${c.width} x ${c.height})`;
    list.appendChild(o);
  });
  list.addEventListener("change", () => {
    selectCamera(Number(list.value));
    canvas.focus();
  });
}

function markCameraList() {
  const list = $("cameras");
  const i = view.exact ? view.camIndex : -1;
  if (i >= 0) list.value = String(i);
  else list.selectedIndex = -1;
}

async function start() {
  try {
    scene.info = await fetchJson("/api/scene");
  } catch (e) {
    showMessage(`Could not load the scene: ${e.message}`);
    return;
  }
  const info = scene.info;
  $("scene-name").textContent = info.name;
  document.title = `dsgs view: loading ${info.name}`;
  buildCameraList();
  setupStyles();
  try {
    renderer = new Renderer(canvas);
  } catch (e) {
    showMessage(e.message);
    return;
  }
  sorter = new Sorter((indices, count, row, ms) => {
    renderer.setOrder(indices, count);
    sortedRow = row;
    lastSortMs = ms;
    requestDraw();
  });

  // The first view: ?camera=K (index or name) fitted to the window (at its own size with
  // ?size=native), else camera 0's view filling the window.
  world.up = upFromCameras(info.cameras);
  const wanted = params.get("camera");
  let camIndex = -1;
  if (wanted !== null) {
    camIndex = /^\d+$/.test(wanted) ? Number(wanted) : info.cameras.findIndex((c) => c.name === wanted);
    if (!(camIndex >= 0 && camIndex < info.cameras.length)) {
      showMessage(`No camera ${wanted}: the scene has ${info.cameras.length} (0 to ${info.cameras.length - 1}).`);
      camIndex = -1;
    }
  }
  requestAnimationFrame(frame);

  let packed;
  try {
    packed = await loadGaussians("/api/gaussians", info.sh_degree, info.stride, info.gaussians);
  } catch (e) {
    showMessage(`Could not load the Gaussians: ${e.message}`);
    return;
  }
  Object.assign(world, measureWorld(packed.means, packed.n, info.cameras));
  if (camIndex >= 0) {
    selectCamera(camIndex);
  } else if (info.cameras.length > 0) {
    selectCamera(0);
    fitWindow();
  } else {
    // No cameras: look at the centre across the up axis.
    view.ref = { width: 800, height: 600, fx: 700, fy: 700 };
    let z = cross(world.up, [1, 0, 0]);
    if (norm(z) < 1e-3) z = cross(world.up, [0, 0, 1]);
    z = normalize(z);
    const x = normalize(cross(scale(world.up, -1), z));
    setPose([...x, ...cross(z, x), ...z], sub(world.centre, scale(z, 2 * world.scale)), false);
    fitWindow();
  }
  describeScene();
  if (STYLIZE_AT_START) {
    if (scene.info.stylize && styles.first !== null) stylizeView();
    else showMessage("?stylize=1 needs a bundle and a painting given with --style.");
  }
}

new ResizeObserver(() => {
  if (scene.info && (view.mode === "fit" || (view.mode === "camera" && !NATIVE))) applySize();
}).observe(stage);

$("fit").addEventListener("click", () => {
  // Keep the pose, drop the camera's size.
  if (view.exact) {
    const t = viewT();
    view.C = scale(mulVec(transpose3(view.R), t), -1);
  }
  fitWindow();
});
$("fly").addEventListener("change", () => canvas.focus());

// ---------------------------------------------------------------- styles

const styles = { list: [], first: null, second: "" };

function thumbUrl(id) {
  return `/api/styles/${encodeURIComponent(id)}/thumbnail.png`;
}

function setupStyles() {
  const on = !!scene.info.stylize;
  $("style-on").hidden = !on;
  $("style-off").hidden = on;
  if (!on) return;
  styles.list = (scene.info.styles || []).slice();
  styles.first = styles.list.length ? styles.list[0].id : null;
  renderStyles();

  const alpha = $("alpha");
  alpha.addEventListener("input", () => {
    $("alpha-out").textContent = Number(alpha.value).toFixed(2);
  });
  $("second").addEventListener("change", () => {
    styles.second = $("second").value;
    renderStyles();
  });
  $("mix").addEventListener("input", updateMixLabel);
  $("upload").addEventListener("change", upload);
  $("stylize").addEventListener("click", stylizeView);
  $("stylize-cancel").addEventListener("click", () => stylizeRun && stylizeRun.cancel());
  $("overlay").addEventListener("change", placeResult);
  $("result-close").addEventListener("click", hideResult);
  $("bake").addEventListener("click", bake);
  $("show-original").addEventListener("click", () => switchScene("original"));
  $("show-baked").addEventListener("click", () => switchScene("baked"));
}

function updateMixLabel() {
  const w = Number($("mix").value);
  $("mix-out").textContent = styles.second
    ? `first ${w.toFixed(2)}, second ${(1 - w).toFixed(2)}`
    : "needs a second style";
}

function renderStyles() {
  const box = $("styles");
  box.textContent = "";
  if (styles.list.length === 0) {
    const p = document.createElement("p");
    p.className = "muted";
    p.textContent = "No styles yet: upload an image.";
    box.appendChild(p);
  }
  for (const s of styles.list) {
    const b = document.createElement("button");
    b.type = "button";
    b.className = "style";
    if (s.id === styles.first) b.classList.add("selected");
    else if (s.id === styles.second) b.classList.add("second");
    b.title = s.name;
    const img = document.createElement("img");
    img.src = thumbUrl(s.id);
    img.alt = s.name;
    img.loading = "lazy";
    const span = document.createElement("span");
    span.textContent = s.name;
    b.append(img, span);
    b.addEventListener("click", () => {
      styles.first = s.id;
      if (styles.second === s.id) styles.second = "";
      renderStyles();
    });
    box.appendChild(b);
  }
  const second = $("second");
  second.textContent = "";
  const none = document.createElement("option");
  none.value = "";
  none.textContent = "none";
  second.appendChild(none);
  for (const s of styles.list) {
    if (s.id === styles.first) continue;
    const o = document.createElement("option");
    o.value = s.id;
    o.textContent = s.name;
    second.appendChild(o);
  }
  if (styles.second === styles.first) styles.second = "";
  second.value = styles.second;
  $("mix").disabled = !styles.second;
  updateMixLabel();
  const any = !!styles.first;
  $("stylize").disabled = !any;
  $("bake").disabled = !any || !!bakeJob;
}

function chosenStyles() {
  if (!styles.first) return null;
  if (!styles.second) return [{ id: styles.first, weight: 1 }];
  const w = Number($("mix").value);
  return [
    { id: styles.first, weight: w },
    { id: styles.second, weight: 1 - w },
  ];
}

function setStatus(id, text, error) {
  const el = $(id);
  el.textContent = text;
  el.classList.toggle("error", !!error);
}

async function upload() {
  const input = $("upload");
  const file = input.files && input.files[0];
  if (!file) return;
  const name = file.name.replace(/\.[^.]*$/, "") || file.name;
  setStatus("upload-status", `uploading ${file.name}...`);
  try {
    const res = await fetch(`/api/styles?name=${encodeURIComponent(name)}`, {
      method: "POST",
      headers: { "Content-Type": file.type || "application/octet-stream" },
      body: file,
    });
    if (!res.ok) {
      setStatus("upload-status", `${file.name}: ${await errorText(res)}`, true);
      return;
    }
    const style = await res.json();
    styles.list.push(style);
    styles.first = style.id;
    renderStyles();
    setStatus("upload-status", `added ${style.name}`);
  } catch (e) {
    setStatus("upload-status", `${file.name}: ${e.message}`, true);
  } finally {
    input.value = "";
  }
}

// ---------------------------------------------------------------- stylize

const resultBeside = $("result-beside");
let stylizeRun = null;
let resultUrl = null;

async function stylizeView() {
  const chosen = chosenStyles();
  if (!chosen) {
    setStatus("stylize-status", "Choose a style first.", true);
    return;
  }
  if (stylizeRun) stylizeRun.cancel();
  const camera = cameraJson();
  const body = {
    camera,
    styles: chosen,
    alpha: Number($("alpha").value),
    preserve_colour: $("preserve").checked,
  };
  const stages = Math.max(camera.width, camera.height) > PREVIEW_SIDE
    ? [["preview", PREVIEW_SIDE], ["full size", null]]
    : [["full size", null]];
  const controller = new AbortController();
  let timer = 0;
  const run = {
    cancel() {
      controller.abort();
      clearInterval(timer);
      setStatus("stylize-status", "cancelled");
      finish();
    },
  };
  const finish = () => {
    if (stylizeRun === run) {
      stylizeRun = null;
      $("stylize-cancel").hidden = true;
    }
  };
  stylizeRun = run;
  $("stylize-cancel").hidden = false;
  try {
    for (const [label, maxSide] of stages) {
      const t0 = performance.now();
      const tick = () => {
        const s = (performance.now() - t0) / 1000;
        setStatus("stylize-status", `stylizing ${label}... ${s.toFixed(0)} s`);
      };
      tick();
      timer = setInterval(tick, 250);
      const res = await fetch("/api/stylize", {
        method: "POST",
        headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ ...body, max_side: maxSide }),
        signal: controller.signal,
      });
      if (!res.ok) {
        clearInterval(timer);
        setStatus("stylize-status", `stylizing ${label} failed: ${await errorText(res)}`, true);
        return;
      }
      const blob = await res.blob();
      clearInterval(timer);
      if (controller.signal.aborted) return;
      const secs = (performance.now() - t0) / 1000;
      showResult(blob, `${label}, ${secs.toFixed(1)} s`, camera);
      setStatus("stylize-status", `${label} done in ${secs.toFixed(1)} s`);
    }
  } catch (e) {
    clearInterval(timer);
    if (!controller.signal.aborted) setStatus("stylize-status", `stylizing failed: ${e.message}`, true);
  } finally {
    finish();
  }
}

function showResult(blob, caption, camera) {
  if (resultUrl) URL.revokeObjectURL(resultUrl);
  resultUrl = URL.createObjectURL(blob);
  for (const img of [$("result-img"), $("result-over")]) img.src = resultUrl;
  resultSize = [camera.width, camera.height];
  $("result-caption").textContent = `Result: ${caption} (${camera.width} x ${camera.height} view)`;
  const save = $("result-save");
  save.href = resultUrl;
  save.hidden = false;
  $("result-close").hidden = false;
  showingResult = true;
  placeResult();
}

let showingResult = false;
// The pixel size of the result shown.
let resultSize = [1, 1];

// The result beside the view fits the other half of the stage (its aspect kept); over the
// view it covers the view.
function sizeResult() {
  const [rw, rh] = viewRoom();
  const s = Math.min(rw / resultSize[0], rh / resultSize[1]);
  const img = $("result-img");
  img.style.width = `${Math.max(1, Math.floor(resultSize[0] * s))}px`;
  img.style.height = `${Math.max(1, Math.floor(resultSize[1] * s))}px`;
  const over = $("result-over");
  over.style.width = `${view.width}px`;
  over.style.height = `${view.height}px`;
}

function placeResult() {
  const over = $("overlay").checked;
  $("result-over").hidden = !showingResult || !over;
  const beside = showingResult && !over;
  if (resultBeside.hidden !== !beside) {
    resultBeside.hidden = !beside;
    applySize();
  }
  sizeResult();
}

function hideResult() {
  showingResult = false;
  $("result-close").hidden = true;
  $("result-save").hidden = true;
  $("result-caption").textContent = "";
  placeResult();
}

// ---------------------------------------------------------------- bake

let bakeJob = null;

async function bake() {
  const chosen = chosenStyles();
  if (!chosen) {
    setStatus("bake-status", "Choose a style first.", true);
    return;
  }
  const iterations = Math.round(Number($("iterations").value));
  if (!(iterations >= 0 && iterations <= 100000)) {
    setStatus("bake-status", "Iterations must be 0 (the colour solve alone) to 100000.", true);
    return;
  }
  $("bake").disabled = true;
  setStatus("bake-status", "starting the bake...");
  let job;
  try {
    const res = await fetch("/api/bake", {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ styles: chosen, alpha: Number($("alpha").value), iterations }),
    });
    if (!res.ok) throw new Error(await errorText(res));
    job = (await res.json()).job;
  } catch (e) {
    setStatus("bake-status", `bake failed: ${e.message}`, true);
    $("bake").disabled = false;
    return;
  }
  bakeJob = job;
  const progress = $("bake-progress");
  progress.hidden = false;
  progress.removeAttribute("value");
  const t0 = performance.now();
  for (;;) {
    await new Promise((r) => setTimeout(r, 1000));
    let info;
    try {
      info = await fetchJson(`/api/jobs/${encodeURIComponent(job)}`);
    } catch (e) {
      setStatus("bake-status", `bake: ${e.message}`, true);
      break;
    }
    const secs = ((performance.now() - t0) / 1000).toFixed(0);
    if (info.total > 0) {
      progress.max = info.total;
      progress.value = info.done;
    }
    if (info.state === "running") {
      setStatus("bake-status", `${info.message || "baking"}: ${info.done} / ${info.total} (${secs} s)`);
      continue;
    }
    if (info.state === "done") {
      scene.bakedUrl = `/api/jobs/${encodeURIComponent(job)}/gaussians`;
      setStatus("bake-status", `baked in ${secs} s; loading the baked scene...`);
      await switchScene("baked");
      if (scene.source === "baked") setStatus("bake-status", `baked in ${secs} s`);
    } else {
      setStatus("bake-status", `bake failed: ${info.message}`, true);
    }
    break;
  }
  progress.hidden = true;
  bakeJob = null;
  $("bake").disabled = !styles.first;
}

let switching = false;
async function switchScene(which) {
  if (switching || !renderer) return;
  if (which === "baked" && !scene.bakedUrl) return;
  switching = true;
  try {
    if (which === "baked") {
      await loadGaussians(scene.bakedUrl, 3, 11 + 48, null);
    } else {
      const i = scene.info;
      await loadGaussians("/api/gaussians", i.sh_degree, i.stride, i.gaussians);
    }
    scene.source = which;
  } catch (e) {
    setStatus("bake-status", `could not load the ${which} scene: ${e.message}`, true);
  } finally {
    switching = false;
  }
  $("scene-source").hidden = !scene.bakedUrl;
  $("show-original").classList.toggle("active", scene.source === "original");
  $("show-baked").classList.toggle("active", scene.source === "baked");
  $("scene-source-info").textContent =
    scene.source === "baked" ? "showing the baked scene" : "showing the original scene";
  describeScene();
}

start();
