// The relight page: the same scene as `gonio render` (src/view/render.rs), drawn by a
// WebGL2 fragment shader that decodes the BTF from its factors (PVMF, PCA, local PCA, DFMF,
// median cut, homomorphic; src/view/gpu.rs describes the last three) or from the
// raw images of a dataset, interpolating light and view exactly as `gonio reconstruct`
// does (src/compress/interp.rs: barycentric weights in the gnomonic projection of the 8
// nearest measured directions).
"use strict";

const VS = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

const FS = `#version 300 es
precision highp float; precision highp int;
precision highp sampler2D; precision highp sampler2DArray;
uniform vec2 uSize; uniform vec3 uLight; uniform vec3 uView; uniform int uShape;
uniform float uExposure; uniform ivec2 uTex; uniform int uKind; uniform int uC4;
uniform int uNL; uniform int uNV; uniform int uTilesX; uniform int uTilesY; uniform int uClusterCol;
uniform sampler2D uDirs; uniform sampler2DArray uBasis; uniform sampler2D uRows;
uniform sampler2D uAux; uniform ivec3 uC4s; uniform ivec3 uOff; uniform int uC4S; uniform int uColor;
uniform vec3 uWhite; uniform vec3 uX0; uniform vec3 uX1; uniform vec3 uX2; uniform int uNH;
out vec4 outColor;
const float COS_MAX_GAP = 0.8660254037844387; // cos 30°: MAX_GAP_DEG
const float SAME_CHORD = 1.7453292e-4;        // chord of 0.01°: SAME_DEG
const float TAU = 6.283185307179586;

int wi[3]; float ww[3]; int wn;

// interp.rs direction_weights, in f32.
bool dirWeights(int row, int n, vec3 q) {
  int ni[8]; float nd[8]; int cnt = 0;
  for (int i = 0; i < n; i++) {
    float c = dot(q, texelFetch(uDirs, ivec2(i, row), 0).xyz);
    if (cnt < 8 || c > nd[7]) {
      int p = cnt < 8 ? cnt : 7;
      while (p > 0 && nd[p - 1] < c) { nd[p] = nd[p - 1]; ni[p] = ni[p - 1]; p--; }
      nd[p] = c; ni[p] = i;
      if (cnt < 8) cnt++;
    }
  }
  wn = 0;
  if (cnt == 0) return false;
  if (distance(q, texelFetch(uDirs, ivec2(ni[0], row), 0).xyz) <= SAME_CHORD) {
    wi[0] = ni[0]; ww[0] = 1.0; wn = 1; return true;
  }
  int m = 0;
  for (int k = 0; k < 8; k++) { if (k < cnt && nd[k] >= COS_MAX_GAP) m = k + 1; }
  if (m == 0) return false;
  vec3 helper = abs(q.z) < 0.9 ? vec3(0, 0, 1) : vec3(1, 0, 0);
  vec3 e1 = normalize(cross(helper, q)); vec3 e2 = cross(q, e1);
  vec2 p[8];
  for (int k = 0; k < 8; k++) {
    if (k >= m) break;
    vec3 d = texelFetch(uDirs, ivec2(ni[k], row), 0).xyz;
    p[k] = vec2(dot(d, e1), dot(d, e2)) / nd[k];
  }
  float best = 1e30; ivec3 bi = ivec3(0); vec3 bw = vec3(0);
  for (int i = 0; i < m; i++) for (int j = i + 1; j < m; j++) for (int k = j + 1; k < m; k++) {
    vec2 a = p[i], b = p[j], c = p[k];
    float det = (b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y);
    float scale = max(dot(b - a, b - a), dot(c - a, c - a));
    if (abs(det) <= 1e-5 * scale) continue;
    float lb = ((-a.x) * (c.y - a.y) - (c.x - a.x) * (-a.y)) / det;
    float lc = ((b.x - a.x) * (-a.y) - (-a.x) * (b.y - a.y)) / det;
    float la = 1.0 - lb - lc;
    if (la < -1e-6 || lb < -1e-6 || lc < -1e-6) continue;
    float s = dot(a, a) + dot(b, b) + dot(c, c);
    if (s < best) { best = s; bi = ivec3(i, j, k); bw = vec3(la, lb, lc); }
  }
  if (best < 1e30) {
    for (int k = 0; k < 3; k++) {
      if (bw[k] > 0.0) { wi[wn] = ni[bi[k]]; ww[wn] = clamp(bw[k], 0.0, 1.0); wn++; }
    }
    return true;
  }
  float bd = dot(p[0], p[0]); int si = 0, sj = 0; float ss = 0.0;
  for (int i = 0; i < m; i++) for (int j = i + 1; j < m; j++) {
    vec2 a = p[i], ab = p[j] - p[i];
    float len2 = dot(ab, ab);
    if (len2 <= 0.0) continue;
    float s = clamp(dot(-a, ab) / len2, 0.0, 1.0);
    vec2 x = a + s * ab;
    if (dot(x, x) < bd) { bd = dot(x, x); si = i; sj = j; ss = s; }
  }
  if (si == sj || ss == 0.0) { wi[0] = ni[si]; ww[0] = 1.0; wn = 1; return true; }
  if (ss == 1.0) { wi[0] = ni[sj]; ww[0] = 1.0; wn = 1; return true; }
  wi[0] = ni[si]; ww[0] = 1.0 - ss; wi[1] = ni[sj]; ww[1] = ss; wn = 2;
  return true;
}

// dfmf.rs decode_color: the colour model's inverse with its clamping.
float labFinv(float t) { const float D = 6.0 / 29.0; return t > D ? t * t * t : 3.0 * D * D * (t - 4.0 / 29.0); }
vec3 decodeColor(vec3 c) {
  if (uColor == 1) { // log-YUV (UBO2014 colour model 11)
    float y = exp(c.x) - 1e-5;
    vec3 yuv = vec3(y, c.y * y + 1e-5, c.z * y + 1e-5);
    return clamp(vec3(yuv.x + 1.13983 * yuv.z, yuv.x - 0.39465 * yuv.y - 0.5806 * yuv.z, yuv.x + 2.03211 * yuv.y),
                 0.0, 1.0);
  }
  if (uColor == 2) { // CIELab
    float fy = (c.x + 16.0) / 116.0;
    vec3 xyz = uWhite * vec3(labFinv(fy + c.y / 500.0), labFinv(fy), labFinv(fy - c.z / 200.0));
    return max(vec3(dot(uX0, xyz), dot(uX1, xyz), dot(uX2, xyz)), 0.0);
  }
  return c;
}

// DFMF (dfmf.rs Dfmf::reconstruct of one grid pair): per channel Σ_k U[v·L + l, k] · SxV[t, k].
float dfmfChannel(int ch, int c4, int l, int v, ivec2 t) {
  float s = 0.0;
  for (int k = 0; k < c4; k++)
    s += dot(texelFetch(uBasis, ivec3(t.x * c4 + k, t.y, ch), 0), texelFetch(uRows, ivec2(v * uC4S + uOff[ch] + k, l), 0));
  return s;
}

vec3 texelValue(int l, int v, ivec2 t) {
  if (uKind == 4) { // median cut: the centroid of the texel's box
    int box = int(texelFetch(uAux, t, 0).r + 0.5);
    return texelFetch(uBasis, ivec3(l, box, v), 0).rgb;
  }
  if (uKind == 5) { // homomorphic: A · (exp(P + Q + R) − ε), 0 where A ≤ 0
    vec3 a = texelFetch(uBasis, ivec3(t, 0), 0).rgb;
    vec3 s = texelFetch(uBasis, ivec3(t, 1 + l), 0).rgb + texelFetch(uBasis, ivec3(t, 1 + uNL + v), 0).rgb;
    if (uNH > 0) s += texelFetch(uBasis, ivec3(t, 1 + uNL + uNV + int(texelFetch(uAux, ivec2(l, v), 0).r + 0.5)), 0).rgb;
    vec3 x = max(a * (exp(s) - 1e-5), 0.0);
    return mix(vec3(0), x, greaterThan(a, vec3(0)));
  }
  if (uKind == 6)
    return decodeColor(vec3(dfmfChannel(0, uC4s.x, l, v, t), dfmfChannel(1, uC4s.y, l, v, t), dfmfChannel(2, uC4s.z, l, v, t)));
  if (uKind == 2) { // raw: the pair's slot in the streamed pool (uTilesX × uTilesY tiles per layer)
    int s = int(texelFetch(uAux, ivec2(l, v), 0).r);
    int per = uTilesX * uTilesY, k = s % per;
    ivec2 tile = ivec2(k % uTilesX, k / uTilesX);
    return texelFetch(uBasis, ivec3(tile.x * uTex.x + t.x, tile.y * uTex.y + t.y, s / per), 0).rgb;
  }
  int layer = uKind == 0 ? v : 0;
  int y = l * 3;
  if (uKind == 3) { // local PCA: the texel's cluster selects its block of rows
    vec4 cb = texelFetch(uBasis, ivec3(t.x * uC4 + uClusterCol / 4, t.y, 0), 0);
    y += int(cb[uClusterCol % 4] + 0.5) * uNL * 3;
  }
  vec3 s = vec3(0);
  for (int k = 0; k < uC4; k++) {
    vec4 b = texelFetch(uBasis, ivec3(t.x * uC4 + k, t.y, layer), 0);
    int x = v * uC4 + k;
    s.r += dot(b, texelFetch(uRows, ivec2(x, y), 0));
    s.g += dot(b, texelFetch(uRows, ivec2(x, y + 1), 0));
    s.b += dot(b, texelFetch(uRows, ivec2(x, y + 2), 0));
  }
  return s;
}

float fract0(float x) { return x - floor(x); }

void main() {
  float m = min(uSize.x, uSize.y);
  float sx = (2.0 * gl_FragCoord.x - uSize.x) / m;
  float sy = (2.0 * gl_FragCoord.y - uSize.y) / m;
  vec3 w = uView;
  vec3 r = normalize(vec3(w.z, 0.0, -w.x));
  vec3 u = cross(w, r);
  vec3 o = sx * r + sy * u + 4.0 * w;
  vec3 d = -w;
  vec3 T, B, N; vec2 uv;
  outColor = vec4(0, 0, 0, 1);
  if (uShape == 0) {
    vec3 p = o + (o.z / w.z) * d;
    if (abs(p.x) > 1.0 || abs(p.y) > 1.0) return;
    uv = vec2((p.x + 1.0) / 2.0, (1.0 - p.y) / 2.0);
    T = vec3(1, 0, 0); B = vec3(0, 1, 0); N = vec3(0, 0, 1);
  } else if (uShape == 1) {
    float b = dot(o, d);
    float disc = b * b - (dot(o, o) - 1.0);
    if (disc < 0.0) return;
    vec3 p = o + (-b - sqrt(disc)) * d;
    N = normalize(p);
    vec3 e = vec3(-N.y, N.x, 0.0);
    T = dot(e, e) < 1e-18 ? vec3(1, 0, 0) : normalize(e);
    B = cross(N, T);
    float lon = fract0(atan(N.y, N.x) / TAU);
    uv = vec2(fract0(2.0 * lon), acos(clamp(N.z, -1.0, 1.0)) / 3.141592653589793);
  } else {
    float a = d.x * d.x + d.z * d.z;
    float b = o.x * d.x + o.z * d.z;
    float c = o.x * o.x + o.z * o.z - 1.0;
    float disc = b * b - a * c;
    if (disc < 0.0 || a < 1e-12) return;
    vec3 p = o + ((-b - sqrt(disc)) / a) * d;
    if (abs(p.y) > 1.0) return;
    N = normalize(vec3(p.x, 0.0, p.z));
    T = vec3(N.z, 0.0, -N.x); B = vec3(0, 1, 0);
    float ang = fract0(atan(N.x, N.z) / TAU + 0.5);
    uv = vec2(fract0(2.0 * ang), (1.0 - p.y) / 2.0);
  }
  vec3 ll = vec3(dot(uLight, T), dot(uLight, B), dot(uLight, N));
  vec3 vl = vec3(dot(w, T), dot(w, B), dot(w, N));
  if (ll.z <= 0.0 || vl.z <= 0.0) return;
  ivec2 t = min(ivec2(uv * vec2(uTex)), uTex - 1);
  if (!dirWeights(0, uNL, normalize(ll))) return;
  int li[3]; float lw[3]; int ln = wn;
  for (int k = 0; k < 3; k++) { li[k] = wi[k]; lw[k] = ww[k]; }
  if (!dirWeights(1, uNV, normalize(vl))) return;
  vec3 val = vec3(0);
  float have = 0.0; bool missing = false;
  for (int a = 0; a < wn; a++) for (int b = 0; b < ln; b++) {
    if (uKind == 2 && texelFetch(uAux, ivec2(li[b], wi[a]), 0).r < 0.0) { missing = true; continue; }
    val += (ww[a] * lw[b]) * texelValue(li[b], wi[a], t);
    have += ww[a] * lw[b];
  }
  if (missing) { if (have <= 0.0) return; val /= have; } // a raw pair still streaming
  vec3 x = clamp(uExposure * val, 0.0, 1.0);
  vec3 s = mix(12.92 * x, 1.055 * pow(x, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), x));
  outColor = vec4(s, 1.0);
}`;

const state = readState();
const canvas = document.getElementById("view");
let gl, prog, info, U = {};

function setStatus(s) { document.getElementById("status").textContent = s; }

function writeUrl() {
  const q = new URLSearchParams();
  q.set("light", fmt(state.light)); q.set("view", fmt(state.view));
  q.set("shape", state.shape); q.set("exposure", String(state.exposure));
  q.set("size", state.size[0] + "x" + state.size[1]);
  history.replaceState(null, "", location.pathname + "?" + q.toString());
}

function compile() {
  const sh = (type, src) => {
    const s = gl.createShader(type);
    gl.shaderSource(s, src); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error("shader: " + gl.getShaderInfoLog(s));
    return s;
  };
  prog = gl.createProgram();
  gl.attachShader(prog, sh(gl.VERTEX_SHADER, VS));
  gl.attachShader(prog, sh(gl.FRAGMENT_SHADER, FS));
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error("link: " + gl.getProgramInfoLog(prog));
  gl.useProgram(prog);
  for (const n of ["uSize", "uLight", "uView", "uShape", "uExposure", "uTex", "uKind", "uC4", "uNL", "uNV",
    "uTilesX", "uTilesY", "uClusterCol", "uDirs", "uBasis", "uRows",
    "uAux", "uC4s", "uOff", "uC4S", "uColor", "uWhite", "uX0", "uX1", "uX2", "uNH"]) U[n] = gl.getUniformLocation(prog, n);
}

function tex(unit, target) {
  const t = gl.createTexture();
  gl.activeTexture(gl.TEXTURE0 + unit);
  gl.bindTexture(target, t);
  gl.texParameteri(target, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
  gl.texParameteri(target, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  gl.texParameteri(target, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
  gl.texParameteri(target, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  return t;
}

// Directions as unit vectors in f32: row 0 lights, row 1 views.
function uploadDirs() {
  const n = Math.max(info.lights_deg.length, info.views_deg.length);
  const a = new Float32Array(n * 2 * 4);
  info.lights_deg.forEach((d, i) => a.set(unitDeg(d), i * 4));
  info.views_deg.forEach((d, i) => a.set(unitDeg(d), (n + i) * 4));
  tex(0, gl.TEXTURE_2D);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, n, 2, 0, gl.RGBA, gl.FLOAT, a);
}

async function pool(n, k, f) {
  let next = 0;
  const run = async () => { while (next < n) { const i = next++; await f(i); } };
  await Promise.all(Array.from({ length: Math.min(k, n) }, run));
}

async function loadFactors() {
  const W = info.width, H = info.height, nl = info.lights_deg.length, nv = info.views_deg.length;
  const c4 = Math.ceil(info.gpu_cols / 4), pvmf = info.gpu === "pvmf", K = info.clusters;
  const max = gl.getParameter(gl.MAX_TEXTURE_SIZE);
  if (W * c4 > max || c4 * nv > max || nl * 3 * K > max) throw new Error("factors too large for this GPU's textures");
  tex(1, gl.TEXTURE_2D_ARRAY);
  gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.RGBA16F, W * c4, H, pvmf ? nv : 1);
  tex(2, gl.TEXTURE_2D);
  gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, c4 * nv, nl * 3 * K);
  let done = 0;
  await pool(info.blocks, 4, async (i) => {
    const buf = await api("/api/factors?block=" + i);
    if (i % 2 === 0) {
      gl.activeTexture(gl.TEXTURE1);
      gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, i / 2, W * c4, H, 1, gl.RGBA, gl.HALF_FLOAT, new Uint16Array(buf));
    } else {
      gl.activeTexture(gl.TEXTURE2);
      const rows = new Float32Array(buf);
      if (pvmf) {
        gl.texSubImage2D(gl.TEXTURE_2D, 0, ((i - 1) / 2) * c4, 0, c4, nl * 3, gl.RGBA, gl.FLOAT, rows);
      } else { // PCA (K = 1) and local PCA: rows (cluster, view, light, channel)
        for (let j = 0; j < K; j++)
          for (let v = 0; v < nv; v++)
            gl.texSubImage2D(gl.TEXTURE_2D, 0, v * c4, j * nl * 3, c4, nl * 3, gl.RGBA, gl.FLOAT, rows,
              (j * nv + v) * nl * 3 * c4 * 4);
      }
    }
    setStatus("factors " + ++done + " / " + info.blocks);
  });
  return c4;
}

// Raw datasets are streamed: the images go into a fixed pool of GPU slots (tiles of
// RGB16F array layers, at most RAW_GPU_BYTES), a nl × nv table (texture unit 3) maps each
// grid pair to its slot or −1. For every state the server lists the pairs its picture uses
// (/api/needed, most used first); those are fetched first, then the rest of the dataset,
// nearest light and view first, while free slots remain. When the pool is full, slots of
// pairs the current picture does not use are reused (least recently needed first). A
// picture is complete when every pair it uses is loaded; until then missing pairs are left
// out and the weights of the others renormalized (the status line says so).
const RAW_GPU_BYTES = 512 * 1048576;
const RAW_BATCH = 8; // pairs per request (the server allows 16)
const raw = { slots: 0, table: null, slotOf: null, pairOf: [], stamp: null, clock: 0, needed: [], neededKey: "",
  inflight: new Set(), noSlot: new Set(), queued: false, free: [], loaded: 0, complete: false, asking: false, askedKey: "" };

function rawKey() { return [fmt(state.light), fmt(state.view), state.shape, state.size.join("x")].join("|"); }

async function loadRaw() {
  const W = info.width, H = info.height, nl = info.lights_deg.length, nv = info.views_deg.length;
  const max = gl.getParameter(gl.MAX_TEXTURE_SIZE), maxLayers = gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS);
  if (W > max || H > max) throw new Error("images larger than this GPU's textures; compress the dataset (gonio compress)");
  // `pool=N` in the URL caps the slots (tests use it to exercise reuse on a small dataset).
  const pool = Number(new URLSearchParams(location.search).get("pool")) || Infinity;
  const cap = Math.max(1, Math.min(nl * nv, pool, Math.floor(RAW_GPU_BYTES / (W * H * 6))));
  const mx = Math.floor(max / W), my = Math.floor(max / H);
  const layers = Math.min(maxLayers, Math.ceil(cap / (mx * my))), per = Math.ceil(cap / layers);
  const tx = Math.max(1, Math.min(mx, Math.ceil(Math.sqrt(per)))), ty = Math.max(1, Math.min(my, Math.ceil(per / tx)));
  raw.slots = Math.min(cap, layers * tx * ty);
  raw.tx = tx; raw.ty = ty;
  tex(1, gl.TEXTURE_2D_ARRAY);
  gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.RGB16F, tx * W, ty * H, layers);
  tex(2, gl.TEXTURE_2D);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, 1, 1, 0, gl.RGBA, gl.FLOAT, new Float32Array(4));
  raw.table = new Float32Array(nl * nv).fill(-1);
  raw.slotOf = new Int32Array(nl * nv).fill(-1);
  raw.stamp = new Float64Array(nl * nv);
  raw.pairOf = new Int32Array(raw.slots).fill(-1);
  for (let i = raw.slots - 1; i >= 0; i--) raw.free.push(i);
  tex(3, gl.TEXTURE_2D);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, nl, nv, 0, gl.RED, gl.FLOAT, raw.table);
  G.streaming = { slots: raw.slots, pairs: nl * nv, loaded: 0, neededLoaded: 0, needed: 0 };
  await askNeeded();
  return { tilesX: tx };
}

// The pairs the current state's picture uses, from the server (one question at a time).
async function askNeeded() {
  const key = rawKey();
  if (raw.asking || key === raw.neededKey) return;
  raw.asking = true;
  try {
    const q = new URLSearchParams({ light: fmt(state.light), view: fmt(state.view), shape: state.shape,
      size: state.size[0] + "x" + state.size[1] });
    const r = await api("/api/needed?" + q.toString(), "json");
    const nl = info.lights_deg.length;
    raw.needed = r.pairs.map((p) => p[1] * nl + p[0]);
    raw.neededKey = key;
    raw.noSlot = new Set();
    raw.clock++;
    for (const p of raw.needed) raw.stamp[p] = raw.clock;
  } finally { raw.asking = false; }
  if (rawKey() !== raw.neededKey) return askNeeded();
  pump();
}

// The next pairs to fetch: needed ones first, then the nearest of the rest while slots are free.
function nextBatch() {
  const out = [];
  let missing = false;
  for (const p of raw.needed) {
    if (raw.slotOf[p] >= 0 || raw.noSlot.has(p)) continue;
    missing = true;
    if (out.length < RAW_BATCH && !raw.inflight.has(p)) out.push(p);
  }
  // Nothing else while the current picture still misses images: they come first.
  if (out.length || missing || raw.free.length <= raw.inflight.size) return out;
  if (!raw.order || raw.orderKey !== raw.neededKey) {
    const nl = info.lights_deg.length, nv = info.views_deg.length;
    const L = unitDeg(state.light), V = unitDeg(state.view);
    const cl = info.lights_deg.map((d) => { const u = unitDeg(d); return u[0] * L[0] + u[1] * L[1] + u[2] * L[2]; });
    const cv = info.views_deg.map((d) => { const u = unitDeg(d); return u[0] * V[0] + u[1] * V[1] + u[2] * V[2]; });
    raw.order = Array.from({ length: nl * nv }, (_, i) => i)
      .sort((a, b) => (cl[b % nl] + cv[Math.floor(b / nl)]) - (cl[a % nl] + cv[Math.floor(a / nl)]) || a - b);
    raw.orderKey = raw.neededKey; raw.orderPos = 0;
  }
  while (raw.orderPos < raw.order.length && out.length < RAW_BATCH && out.length + raw.inflight.size < raw.free.length) {
    const p = raw.order[raw.orderPos++];
    if (raw.slotOf[p] < 0 && !raw.inflight.has(p)) out.push(p);
  }
  return out;
}

function takeSlot() {
  if (raw.free.length) return raw.free.pop();
  // Reuse the least recently needed slot whose pair the current picture does not use.
  let best = -1, bs = Infinity;
  for (let s = 0; s < raw.slots; s++) {
    const p = raw.pairOf[s];
    if (p >= 0 && raw.stamp[p] < raw.clock && raw.stamp[p] < bs) { bs = raw.stamp[p]; best = s; }
  }
  if (best < 0) return -1;
  const p = raw.pairOf[best];
  raw.slotOf[p] = -1; raw.table[p] = -1; raw.pairOf[best] = -1; raw.loaded--;
  return best;
}

let pumps = 0;
function pump() {
  while (pumps < 4) {
    const batch = nextBatch();
    if (!batch.length) break;
    pumps++;
    batch.forEach((p) => raw.inflight.add(p));
    fetchBatch(batch).catch((e) => showError(e.message || e)).finally(() => {
      pumps--; batch.forEach((p) => raw.inflight.delete(p)); pump(); draw();
    });
  }
  draw();
}

async function fetchBatch(batch) {
  const nl = info.lights_deg.length, W = info.width, H = info.height;
  const buf = await api("/api/raw_pairs?pairs=" + batch.map((p) => (p % nl) + "." + Math.floor(p / nl)).join(","));
  const a = new Uint16Array(buf);
  gl.activeTexture(gl.TEXTURE1);
  batch.forEach((p, k) => {
    if (raw.slotOf[p] >= 0) return;
    const s = takeSlot();
    if (s < 0) { raw.noSlot.add(p); return; } // every slot holds a pair the current picture uses
    const per = raw.tx * raw.ty, t = s % per;
    gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, (t % raw.tx) * W, Math.floor(t / raw.tx) * H, Math.floor(s / per), W, H, 1,
      gl.RGB, gl.HALF_FLOAT, a, k * W * H * 3);
    raw.slotOf[p] = s; raw.pairOf[s] = p; raw.table[p] = s; raw.loaded++;
  });
  gl.activeTexture(gl.TEXTURE3);
  gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, nl, info.views_deg.length, gl.RED, gl.FLOAT, raw.table);
}

// The decoders of src/view/gpu.rs (DFMF, median cut, homomorphic): blocks as the server
// describes them in /api/info.
async function loadGpuBlocks() {
  const W = info.width, H = info.height, nl = info.lights_deg.length, nv = info.views_deg.length;
  const max = gl.getParameter(gl.MAX_TEXTURE_SIZE), maxLayers = gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS);
  const half = info.texel_format === "f16";
  const ifmt = half ? gl.RGBA16F : gl.RGBA32F, type = half ? gl.HALF_FLOAT : gl.FLOAT;
  const texel = (buf) => (half ? new Uint16Array(buf) : new Float32Array(buf));
  const tooLarge = (what) => {
    const e = new Error(what + " too large for this GPU's textures: showing the server's picture");
    e.fallback = true;
    throw e;
  };
  let layerW, layerH, layers;
  if (info.gpu === "dfmf") {
    const c4 = info.channel_components.map((c) => Math.ceil(c / 4));
    const c4s = c4[0] + c4[1] + c4[2];
    if (W * Math.max(...c4) > max || nv * c4s > max || nl > max) tooLarge("DFMF factors");
    [layerW, layerH, layers] = [W * Math.max(...c4), H, 3];
    tex(2, gl.TEXTURE_2D);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, nv * c4s, nl);
    gl.uniform3i(U.uC4s, c4[0], c4[1], c4[2]);
    gl.uniform3i(U.uOff, 0, c4[0], c4[0] + c4[1]);
    gl.uniform1i(U.uC4S, c4s);
    gl.uniform1i(U.uColor, info.color_model);
    gl.uniform3fv(U.uWhite, info.lab_white);
    const m = info.lab_xyz_to_rgb;
    gl.uniform3fv(U.uX0, m[0]); gl.uniform3fv(U.uX1, m[1]); gl.uniform3fv(U.uX2, m[2]);
  } else if (info.gpu === "median-cut") {
    if (nl > max || info.boxes > max || nv > maxLayers || W > max || H > max) tooLarge("median-cut blocks");
    [layerW, layerH, layers] = [nl, info.boxes, nv];
  } else {
    layers = 1 + nl + nv + info.half_bins;
    if (W > max || H > max || layers > maxLayers) tooLarge("homomorphic tables");
    [layerW, layerH] = [W, H];
    gl.uniform1i(U.uNH, info.half_bins);
  }
  tex(1, gl.TEXTURE_2D_ARRAY);
  gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, ifmt, layerW, layerH, layers);
  if (info.gpu !== "dfmf") { tex(2, gl.TEXTURE_2D); gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, 1, 1, 0, gl.RGBA, gl.FLOAT, new Float32Array(4)); }
  tex(3, gl.TEXTURE_2D);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, 1, 1, 0, gl.RED, gl.FLOAT, new Float32Array(1));
  let done = 0;
  await pool(info.gpu_blocks, 4, async (i) => {
    const buf = await api("/api/factors?block=" + i);
    if (info.gpu === "dfmf") {
      if (i < 3) {
        const c4 = Math.ceil(info.channel_components[i] / 4);
        gl.activeTexture(gl.TEXTURE1);
        gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, i, W * c4, H, 1, gl.RGBA, type, texel(buf));
      } else {
        gl.activeTexture(gl.TEXTURE2);
        const c4s = info.channel_components.reduce((a, c) => a + Math.ceil(c / 4), 0);
        gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, nv * c4s, nl, gl.RGBA, gl.FLOAT, new Float32Array(buf));
      }
    } else if (i === 0) { // median cut: index image; homomorphic: bin of every pair
      gl.activeTexture(gl.TEXTURE3);
      const [w, h] = info.gpu === "median-cut" ? [W, H] : [nl, nv];
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, w, h, 0, gl.RED, gl.FLOAT, new Float32Array(buf));
    } else {
      gl.activeTexture(gl.TEXTURE1);
      gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, i - 1, layerW, layerH, 1, gl.RGBA, type, texel(buf));
    }
    setStatus("factors " + ++done + " / " + info.gpu_blocks);
  });
}

let pending = false;
function draw() {
  if (pending) return;
  pending = true;
  requestAnimationFrame(() => { pending = false; drawNow(); });
}

function drawNow() {
  writeUrl();
  document.getElementById("light-text").textContent = "θ,φ = " + fmt(state.light) + "°";
  document.getElementById("view-text").textContent = "θ,φ = " + fmt(state.view) + "°";
  document.getElementById("exposure-text").textContent = "× " + state.exposure.toPrecision(3);
  if (!info) return;
  if (!info.gpu) return drawServer();
  if (!G.setup) return;
  let complete = true;
  if (info.gpu === "raw") {
    if (rawKey() !== raw.neededKey) askNeeded().catch((e) => showError(e.message || e));
    const have = raw.needed.filter((p) => raw.slotOf[p] >= 0).length;
    complete = rawKey() === raw.neededKey && have === raw.needed.length;
    Object.assign(G.streaming, { loaded: raw.loaded, needed: raw.needed.length, neededLoaded: have });
    G.complete = complete;
    G.idle = complete && pumps === 0;
    setStatus("streaming: " + raw.loaded + " of " + info.lights_deg.length * info.views_deg.length + " images on the GPU (" +
      raw.slots + " slots); this picture " + (complete ? "complete" : "uses " + have + " of " + raw.needed.length + " images (missing ones left out)") +
      "; " + (G.bytes / 1048576).toFixed(1) + " MiB transferred");
    if (complete && !G.ready) { G.ready = true; G.firstCompleteBytes = G.bytes; }
  }
  const [W, H] = state.size;
  if (canvas.width !== W || canvas.height !== H) { canvas.width = W; canvas.height = H; }
  gl.viewport(0, 0, W, H);
  gl.uniform2f(U.uSize, W, H);
  gl.uniform3fv(U.uLight, unitDeg(state.light));
  gl.uniform3fv(U.uView, unitDeg(state.view));
  gl.uniform1i(U.uShape, ["plane", "sphere", "cylinder"].indexOf(state.shape));
  gl.uniform1f(U.uExposure, state.exposure);
  gl.drawArrays(gl.TRIANGLES, 0, 3);
  const px = new Uint8Array(4);
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px); // wait for the frame
  G.frames++;
  if (G.firstPictureMs === undefined && complete) G.firstPictureMs = performance.now();
  document.body.dataset.frame = String(G.frames);
}

// Methods without a GPU decoder: the server's CPU reference picture.
function drawServer() {
  const img = document.getElementById("fallback");
  canvas.hidden = true; img.hidden = false;
  const q = new URLSearchParams({ light: fmt(state.light), view: fmt(state.view), shape: state.shape,
    exposure: String(state.exposure), size: state.size[0] + "x" + state.size[1] });
  img.onload = () => { G.frames++; if (G.firstPictureMs === undefined) G.firstPictureMs = performance.now();
    document.body.dataset.frame = String(G.frames); };
  img.src = "/api/render?" + q.toString();
}

// For benchmarks: draw n frames with the light moving, return frames per second.
G.bench = (n) => {
  const t0 = performance.now();
  for (let i = 0; i < n; i++) { state.light = [30 + 20 * Math.sin(i), (i * 37) % 360]; drawNow(); }
  return (n * 1000) / (performance.now() - t0);
};
G.setState = (s) => { Object.assign(state, s); drawNow(); };
G.snapshot = () => canvas.toDataURL("image/png");

async function main() {
  const lh = new Hemi(document.getElementById("hemi-light"), [], (v) => { state.light = v; draw(); });
  const vh = new Hemi(document.getElementById("hemi-view"), [], (v) => { state.view = v; draw(); });
  const sh = document.getElementById("shape"), ex = document.getElementById("exposure");
  sh.value = state.shape;
  sh.onchange = () => { state.shape = sh.value; draw(); };
  ex.value = String(Math.log2(state.exposure));
  ex.oninput = () => { state.exposure = Math.pow(2, Number(ex.value)); draw(); };
  info = await api("/api/info", "json");
  G.gpu = info.gpu;
  lh.dirs = info.lights_deg; vh.dirs = info.views_deg;
  lh.set(state.light); vh.set(state.view);
  document.getElementById("what").textContent = info.kind + " · " + info.method + " · " + info.width + "×" +
    info.height + " · " + info.lights_deg.length + " lights × " + info.views_deg.length + " views" +
    (info.gpu ? " · decoded on the GPU" : " · rendered by the server (no GPU decoder for " + info.method + ")");
  if (info.gpu) {
    try { await setupGpu(); } catch (e) {
      if (!e.fallback) throw e;
      setStatus(e.message); // beyond this GPU's limits: the server's picture
      info.gpu = null; G.gpu = null;
    }
  }
  G.setup = true;
  if (info.gpu !== "raw") G.ready = true;
  drawNow();
}

async function setupGpu() {
  {
    gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true, premultipliedAlpha: false });
    if (!gl) throw new Error("this browser has no WebGL2");
    compile();
    uploadDirs();
    tex(3, gl.TEXTURE_2D); // unit 3 (uAux) holds a texture for every decoder
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.R32F, 1, 1, 0, gl.RED, gl.FLOAT, new Float32Array(1));
    let c4 = 0, tilesX = 1;
    if (info.gpu === "raw") tilesX = (await loadRaw()).tilesX, gl.uniform1i(U.uTilesY, raw.ty);
    else if (["dfmf", "median-cut", "homomorphic"].includes(info.gpu)) await loadGpuBlocks();
    else c4 = await loadFactors();
    gl.uniform1i(U.uDirs, 0); gl.uniform1i(U.uBasis, 1); gl.uniform1i(U.uRows, 2); gl.uniform1i(U.uAux, 3);
    gl.uniform2i(U.uTex, info.width, info.height);
    gl.uniform1i(U.uKind, { pvmf: 0, pca: 1, raw: 2, "local-pca": 3, "median-cut": 4, homomorphic: 5, dfmf: 6 }[info.gpu]);
    gl.uniform1i(U.uClusterCol, info.gpu_cols - 1);
    gl.uniform1i(U.uC4, c4); gl.uniform1i(U.uTilesX, tilesX);
    gl.uniform1i(U.uNL, info.lights_deg.length); gl.uniform1i(U.uNV, info.views_deg.length);
    const err = gl.getError();
    if (err) throw new Error("WebGL error " + err);
    if (info.gpu !== "raw") setStatus("ready: " + (G.bytes / 1048576).toFixed(2) + " MiB transferred");
  }
}
main().catch((e) => showError(e.message || e));
