// fsjax splat viewer: a small self-contained WebGL 1 renderer for the 32-byte .splat layout
// (3 x f32 position, 3 x f32 linear scale, 4 x u8 RGBA, 4 x u8 quaternion w,x,y,z as 128 q + 128).
// Camera: OpenCV convention (x right, y down, z forward), pose world_from_camera (R row-major, t),
// pinhole intrinsics fx, fy, cx, cy in pixels; pixel centres on integers.
// Per frame: EWA projection of every splat on the CPU (Sigma_2d = J W Sigma W^T J^T + 0.3 px^2),
// back-to-front sort by camera depth, one quad per splat (3-sigma box), Gaussian falloff in the
// fragment shader, premultiplied "over" blending.
// Near plane: a splat is culled only when its whole 3-sigma depth extent is in front of the near
// plane (z + 3 sigma_z < near); one that straddles it is drawn at depth max(z, near).
// cull: "extent" (default) or "centre" (the common viewer rule, which drops ground splats under a
// low camera: kept only to demonstrate the defect). mode: "color" or "alpha" (white splats on black:
// the pixel value is the accumulated opacity).
"use strict";

function decodeSplat(buf) {
  const n = Math.floor(buf.byteLength / 32);
  const f = new Float32Array(buf, 0, n * 8);
  const u = new Uint8Array(buf);
  const s = { n: n, pos: new Float32Array(3 * n), cov: new Float32Array(6 * n), rgba: new Float32Array(4 * n) };
  for (let i = 0; i < n; i++) {
    const o = 8 * i;
    s.pos[3 * i] = f[o]; s.pos[3 * i + 1] = f[o + 1]; s.pos[3 * i + 2] = f[o + 2];
    const sx = f[o + 3], sy = f[o + 4], sz = f[o + 5];
    for (let c = 0; c < 4; c++) s.rgba[4 * i + c] = u[32 * i + 24 + c] / 255;
    let w = (u[32 * i + 28] - 128) / 128, x = (u[32 * i + 29] - 128) / 128;
    let y = (u[32 * i + 30] - 128) / 128, z = (u[32 * i + 31] - 128) / 128;
    const qn = Math.hypot(w, x, y, z) || 1; w /= qn; x /= qn; y /= qn; z /= qn;
    const R = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
               2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
               2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)];
    const M = [R[0] * sx, R[1] * sy, R[2] * sz, R[3] * sx, R[4] * sy, R[5] * sz, R[6] * sx, R[7] * sy, R[8] * sz];
    // Sigma = M M^T (symmetric: xx, xy, xz, yy, yz, zz)
    const d = (a, b) => M[3 * a] * M[3 * b] + M[3 * a + 1] * M[3 * b + 1] + M[3 * a + 2] * M[3 * b + 2];
    s.cov.set([d(0, 0), d(0, 1), d(0, 2), d(1, 1), d(1, 2), d(2, 2)], 6 * i);
  }
  return s;
}

const VS = `
attribute vec2 a_px; attribute vec2 a_off; attribute vec3 a_conic; attribute vec4 a_rgba;
uniform vec2 u_size; varying vec2 v_off; varying vec3 v_conic; varying vec4 v_rgba;
void main() {
  vec2 p = a_px + a_off;  // pixel coordinates, centres on integers
  vec2 ndc = vec2((p.x + 0.5) / u_size.x * 2.0 - 1.0, 1.0 - (p.y + 0.5) / u_size.y * 2.0);
  gl_Position = vec4(ndc, 0.0, 1.0); v_off = a_off; v_conic = a_conic; v_rgba = a_rgba;
}`;
const FS = `
precision highp float; varying vec2 v_off; varying vec3 v_conic; varying vec4 v_rgba;
uniform float u_alpha_mode;
void main() {
  float q = v_conic.x * v_off.x * v_off.x + 2.0 * v_conic.y * v_off.x * v_off.y + v_conic.z * v_off.y * v_off.y;
  float a = min(0.99, v_rgba.a * exp(-0.5 * q));
  if (a < 1.0 / 255.0) discard;
  vec3 c = mix(v_rgba.rgb, vec3(1.0), u_alpha_mode);
  gl_FragColor = vec4(c * a, a);
}`;

function renderSplats(canvas, splat, cam, opts) {
  const cull = (opts && opts.cull) || "extent";
  const alphaMode = (opts && opts.mode) === "alpha" ? 1.0 : 0.0;
  const W = cam.width, H = cam.height, near = cam.near;
  canvas.width = W; canvas.height = H;
  const gl = canvas.getContext("webgl", { preserveDrawingBuffer: true, premultipliedAlpha: true, antialias: false });
  if (!gl) throw new Error("WebGL unavailable");
  const R = cam.R, t = cam.t;  // world_from_camera, R row-major 3x3
  const n = splat.n, items = [];
  const Sc = new Float64Array(9);
  let culled = 0;
  for (let i = 0; i < n; i++) {
    const dx = splat.pos[3 * i] - t[0], dy = splat.pos[3 * i + 1] - t[1], dz = splat.pos[3 * i + 2] - t[2];
    // camera coords p = R^T (X - t)
    const x = R[0] * dx + R[3] * dy + R[6] * dz, y = R[1] * dx + R[4] * dy + R[7] * dz;
    const z = R[2] * dx + R[5] * dy + R[8] * dz;
    const c = splat.cov.subarray(6 * i, 6 * i + 6);
    const S = [c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5]];
    // Sc = R^T S R
    for (let a = 0; a < 3; a++) for (let b = 0; b < 3; b++) {
      let acc = 0;
      for (let k = 0; k < 3; k++) for (let l = 0; l < 3; l++) acc += R[3 * k + a] * S[3 * k + l] * R[3 * l + b];
      Sc[3 * a + b] = acc;
    }
    const sz = Math.sqrt(Math.max(Sc[8], 0));
    if (cull === "centre" ? z < near : z + 3 * sz < near) { culled++; continue; }
    const zp = Math.max(z, near);
    const u = cam.fx * x / zp + cam.cx, v = cam.fy * y / zp + cam.cy;
    const lx = 1.3 * 0.5 * W / cam.fx, ly = 1.3 * 0.5 * H / cam.fy;
    const tx = Math.min(Math.max(x / zp, -lx), lx) * zp, ty = Math.min(Math.max(y / zp, -ly), ly) * zp;
    const J = [cam.fx / zp, 0, -cam.fx * tx / (zp * zp), 0, cam.fy / zp, -cam.fy * ty / (zp * zp)];
    const T0 = [0, 0, 0], T1 = [0, 0, 0];
    for (let b = 0; b < 3; b++) for (let k = 0; k < 3; k++) { T0[b] += J[k] * Sc[3 * k + b]; T1[b] += J[3 + k] * Sc[3 * k + b]; }
    const A = T0[0] * J[0] + T0[1] * J[1] + T0[2] * J[2] + 0.3;
    const B = T0[0] * J[3] + T0[1] * J[4] + T0[2] * J[5];
    const C = T1[0] * J[3] + T1[1] * J[4] + T1[2] * J[5] + 0.3;
    const det = A * C - B * B;
    if (!(det > 0)) continue;
    const op = splat.rgba[4 * i + 3];
    if (op < 1 / 255) continue;
    const r = Math.sqrt(2 * Math.log(op * 255));
    const eu = r * Math.sqrt(A), ev = r * Math.sqrt(C);
    if (u + eu < -0.5 || u - eu > W - 0.5 || v + ev < -0.5 || v - ev > H - 0.5) continue;
    items.push({ z: z, u: u, v: v, eu: eu, ev: ev, conic: [C / det, -B / det, A / det], i: i });
  }
  items.sort((p, q) => q.z - p.z);  // back to front
  const m = items.length, stride = 11;
  const data = new Float32Array(m * 6 * stride);
  const corners = [[-1, -1], [1, -1], [1, 1], [-1, -1], [1, 1], [-1, 1]];
  let o = 0;
  for (const it of items) {
    const rgba = splat.rgba.subarray(4 * it.i, 4 * it.i + 4);
    for (const cc of corners) {
      data.set([it.u, it.v, cc[0] * it.eu, cc[1] * it.ev, it.conic[0], it.conic[1], it.conic[2],
                rgba[0], rgba[1], rgba[2], rgba[3]], o);
      o += stride;
    }
  }
  const sh = (type, src) => { const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s)); return s; };
  const prog = gl.createProgram();
  gl.attachShader(prog, sh(gl.VERTEX_SHADER, VS)); gl.attachShader(prog, sh(gl.FRAGMENT_SHADER, FS));
  gl.linkProgram(prog); gl.useProgram(prog);
  const buf = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, buf); gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
  let off = 0;
  for (const [name, size] of [["a_px", 2], ["a_off", 2], ["a_conic", 3], ["a_rgba", 4]]) {
    const loc = gl.getAttribLocation(prog, name); gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, size, gl.FLOAT, false, stride * 4, off * 4); off += size;
  }
  gl.uniform2f(gl.getUniformLocation(prog, "u_size"), W, H);
  gl.uniform1f(gl.getUniformLocation(prog, "u_alpha_mode"), alphaMode);
  gl.viewport(0, 0, W, H);
  gl.clearColor(0, 0, 0, 1); gl.clear(gl.COLOR_BUFFER_BIT);
  gl.enable(gl.BLEND); gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
  gl.drawArrays(gl.TRIANGLES, 0, m * 6);
  return { drawn: m, culled: culled };
}

function b64ToBuffer(b64) {
  const s = atob(b64), out = new Uint8Array(s.length);
  for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
  return out.buffer;
}

async function fsjaxViewerMain() {
  const params = new URLSearchParams(window.location.search);
  const opts = { cull: params.get("cull") || "extent", mode: params.get("mode") || "color" };
  const status = document.getElementById("status");
  try {
    let buf;
    if (window.FSJAX_SPLAT_B64) buf = b64ToBuffer(window.FSJAX_SPLAT_B64);
    else if (params.get("url")) buf = await (await fetch(params.get("url"))).arrayBuffer();
    else { status.textContent = "no .splat given (embed FSJAX_SPLAT_B64 or pass ?url=)"; return; }
    const cam = window.FSJAX_CAMERA;
    const res = renderSplats(document.getElementById("view"), decodeSplat(buf), cam, opts);
    document.title = "fsjax splat viewer: " + res.drawn + " drawn, " + res.culled + " culled";
  } catch (e) { status.textContent = "error: " + e.message; }
}
window.addEventListener("load", fsjaxViewerMain);
