// nehad web player (docs/web.md): the exported deformation field evaluated by onnxruntime-web
// (wasm), the Gaussians drawn by a WebGL2 splat shader that follows the rasterizer semantics of
// the project's CPU renderer (docs/design.md section 6): EWA projection with the 0.3 pixel
// dilation, alpha = min(0.99, opacity exp(-d^T conic d / 2)) at pixel centres, nothing under
// 1/255, Gaussians composited in depth order over the background. Everything it loads is in
// its own folder.
import * as ort from './ort/ort.wasm.min.mjs';

const $ = (id) => document.getElementById(id);
const api = (window.nehad = { ready: false, error: null, frames: 0 });

function fail(message) {
  api.error = message instanceof Error ? message.message : String(message);
  const box = $('error');
  box.textContent = 'Error: ' + api.error;
  box.hidden = false;
  $('readout').textContent = 'failed';
}

async function fetchBytes(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status} ${r.statusText}`);
  return new Uint8Array(await r.arrayBuffer());
}

async function fetchGunzipped(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status} ${r.statusText}`);
  return new Response(r.body.pipeThrough(new DecompressionStream('gzip'))).arrayBuffer();
}

// ---------------------------------------------------------------------------------------------
// the scene: deformation (onnxruntime-web) and its layers

function parseChunk(buffer, source) {
  // a `nehad-layer/1` chunk (runtime/layers.py): magic, uint32 header length, JSON, arrays
  const bytes = new Uint8Array(buffer);
  const magic = String.fromCharCode(...bytes.subarray(0, 8));
  if (magic !== 'NEHADLYR') throw new Error(`${source}: not a nehad layer chunk`);
  const h = new DataView(buffer).getUint32(8, true);
  const header = JSON.parse(new TextDecoder().decode(bytes.subarray(12, 12 + h)));
  const arrays = {};
  for (const e of header.arrays) {
    const start = 12 + h + e.offset;
    arrays[e.name] = new Float32Array(buffer.slice(start, start + e.nbytes));
  }
  return { count: header.count, arrays };
}

class Deformer {
  constructor(session, scene) {
    this.session = session;
    this.scene = scene;
    this.chunks = []; // enhancement layers 1.. (split-layer models)
    this.detail = 0;
    this.busy = Promise.resolve();
  }

  async loadLayers() {
    for (const layer of this.scene.layers || []) {
      const buf = await (await fetch(layer.file)).arrayBuffer();
      this.chunks.push(parseChunk(buf, layer.file));
    }
    this.detail = this.chunks.length;
  }

  feeds(t) {
    const feeds = { time: new ort.Tensor('float32', new Float32Array([t]), [1]) };
    if (!this.scene.layers) return feeds;
    const used = this.chunks.slice(0, this.detail);
    const rows = used.reduce((n, c) => n + c.count, 0);
    const k = (this.scene.sh_degree + 1) ** 2;
    const shapes = { means: [3], log_scales: [3], quats: [4], opacity_logits: [], sh: [k, 3],
                     mu_eq: [3], t_eq: [1] };
    for (const [name, tail] of Object.entries(shapes)) {
      const per = tail.reduce((a, b) => a * b, 1);
      const data = new Float32Array(rows * per);
      let at = 0;
      for (const c of used) { data.set(c.arrays[name], at); at += c.arrays[name].length; }
      feeds['extra_' + name] = new ort.Tensor('float32', data, [rows, ...tail]);
    }
    const layer = new Int32Array(rows);
    let at = 0;
    used.forEach((c, j) => { layer.fill(j + 1, at, at + c.count); at += c.count; });
    feeds.extra_layer = new ort.Tensor('int32', layer, [rows]);
    return feeds;
  }

  // the activated Gaussians at time t: {means, scales, quats, opacities, sh, n}
  run(t) {
    const job = this.busy.then(async () => {
      const start = performance.now();
      // the outputs a file in parts also has per part (NAME.partP) are not needed here
      const names = this.session.outputNames.filter((n) => !n.includes('.part'));
      const out = await this.session.run(this.feeds(t), names);
      const g = { means: out.means.data, scales: out.scales.data, quats: out.quats.data,
                  opacities: out.opacities.data, sh: out.sh.data, n: out.opacities.dims[0],
                  k: out.sh.dims[1], ms: performance.now() - start, t };
      return g;
    });
    this.busy = job.catch(() => {});
    return job;
  }
}

// ---------------------------------------------------------------------------------------------
// cameras: OpenCV axes, world_to_camera = [R | t]; the view keeps a camera's intrinsics

const SH_C0 = 0.28209479177387814, SH_C1 = 0.4886025119029199;
const SH_C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
  -1.0925484305920792, 0.5462742152960396];
const SH_C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
  -0.4570457994644658, 1.445305721320277, -0.5900435899266435];

function cameraFrom(c) {
  const m = c.world_to_camera; // 4x4 row-major
  const R = [m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2]];
  const t = [m[0][3], m[1][3], m[2][3]];
  return { width: c.width, height: c.height, fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy, R, t };
}

function centre(cam) { // -R^T t
  const { R, t } = cam;
  return [-(R[0] * t[0] + R[3] * t[1] + R[6] * t[2]), -(R[1] * t[0] + R[4] * t[1] + R[7] * t[2]),
    -(R[2] * t[0] + R[5] * t[1] + R[8] * t[2])];
}

function withPose(cam, R, c) {
  const t = [-(R[0] * c[0] + R[1] * c[1] + R[2] * c[2]), -(R[3] * c[0] + R[4] * c[1] + R[5] * c[2]),
    -(R[6] * c[0] + R[7] * c[1] + R[8] * c[2])];
  return { ...cam, R, t };
}

function axisRotation(a, angle) { // Rodrigues, a unit
  const [x, y, z] = a, c = Math.cos(angle), s = Math.sin(angle), C = 1 - c;
  return [c + x * x * C, x * y * C - z * s, x * z * C + y * s,
    y * x * C + z * s, c + y * y * C, y * z * C - x * s,
    z * x * C - y * s, z * y * C + x * s, c + z * z * C];
}

const mul = (A, B) => [0, 1, 2].flatMap((i) => [0, 1, 2].map((j) =>
  A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j]));
const apply = (M, v) => [M[0] * v[0] + M[1] * v[1] + M[2] * v[2],
  M[3] * v[0] + M[4] * v[1] + M[5] * v[2], M[6] * v[0] + M[7] * v[1] + M[8] * v[2]];
const transpose = (M) => [M[0], M[3], M[6], M[1], M[4], M[7], M[2], M[5], M[8]];

// ---------------------------------------------------------------------------------------------
// per-frame Gaussian attributes: colour from SH at the view direction, 3D covariance, depth order

function shColour(g, i, dir, degree, out, o) {
  const k = g.k, base = i * k * 3, sh = g.sh;
  const [x, y, z] = dir;
  const b = [SH_C0];
  if (degree >= 1) b.push(-SH_C1 * y, SH_C1 * z, -SH_C1 * x);
  if (degree >= 2) {
    const xx = x * x, yy = y * y, zz = z * z;
    b.push(SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
      SH_C2[4] * (xx - yy));
    if (degree >= 3) {
      b.push(SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, SH_C3[2] * y * (4 * zz - xx - yy),
        SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
        SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy));
    }
  }
  for (let ch = 0; ch < 3; ch++) {
    let v = 0.5;
    for (let j = 0; j < b.length; j++) v += b[j] * sh[base + 3 * j + ch];
    out[o + ch] = Math.max(v, 0);
  }
}

function covariances(g) { // Sigma = (R S)(R S)^T: s00 s01 s02 s11 s12 s22 per Gaussian
  const cov = new Float32Array(g.n * 6);
  for (let i = 0; i < g.n; i++) {
    let w = g.quats[4 * i], x = g.quats[4 * i + 1], y = g.quats[4 * i + 2], z = g.quats[4 * i + 3];
    const qn = Math.hypot(w, x, y, z) || 1;
    w /= qn; x /= qn; y /= qn; z /= qn;
    const r = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
      2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
      2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)];
    const s = [g.scales[3 * i], g.scales[3 * i + 1], g.scales[3 * i + 2]];
    const a = [r[0] * s[0], r[1] * s[1], r[2] * s[2], r[3] * s[0], r[4] * s[1], r[5] * s[2],
      r[6] * s[0], r[7] * s[1], r[8] * s[2]];
    const row = (p, q) => a[3 * p] * a[3 * q] + a[3 * p + 1] * a[3 * q + 1] + a[3 * p + 2] * a[3 * q + 2];
    cov.set([row(0, 0), row(0, 1), row(0, 2), row(1, 1), row(1, 2), row(2, 2)], 6 * i);
  }
  return cov;
}

const FLOATS = 13; // centre 3, colour 3 + opacity, covariance 6

function sortedInstances(g, cov, cam, degree) {
  const n = g.n, depth = new Float32Array(n), order = new Uint32Array(n);
  const { R, t } = cam, c = centre(cam);
  for (let i = 0; i < n; i++) {
    order[i] = i;
    depth[i] = R[6] * g.means[3 * i] + R[7] * g.means[3 * i + 1] + R[8] * g.means[3 * i + 2] + t[2];
  }
  order.sort((a, b) => depth[b] - depth[a] || b - a); // back to front
  const data = new Float32Array(n * FLOATS), rgb = new Float32Array(3);
  for (let j = 0; j < n; j++) {
    const i = order[j], o = j * FLOATS;
    const mx = g.means[3 * i], my = g.means[3 * i + 1], mz = g.means[3 * i + 2];
    let dx = mx - c[0], dy = my - c[1], dz = mz - c[2];
    const dn = Math.hypot(dx, dy, dz) || 1;
    shColour(g, i, [dx / dn, dy / dn, dz / dn], degree, rgb, 0);
    data[o] = mx; data[o + 1] = my; data[o + 2] = mz;
    data[o + 3] = rgb[0]; data[o + 4] = rgb[1]; data[o + 5] = rgb[2];
    data[o + 6] = g.opacities[i];
    data.set(cov.subarray(6 * i, 6 * i + 6), o + 7);
  }
  return data;
}

// ---------------------------------------------------------------------------------------------
// WebGL2 splatting

const SPLAT_VS = `#version 300 es
precision highp float;
layout(location = 0) in vec2 corner;
layout(location = 1) in vec3 centre;
layout(location = 2) in vec4 colour;
layout(location = 3) in vec3 covA;
layout(location = 4) in vec3 covB;
uniform mat3 R;
uniform vec3 T;
uniform vec4 intr;
uniform vec2 size;
uniform vec2 lim;
flat out vec4 vColour;
flat out vec3 vConic;
flat out vec2 vMean;
void main() {
  vec3 p = R * centre + T;
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);
  if (!(p.z > 0.2) || colour.a < 1.0 / 255.0) return;
  float tx = clamp(p.x / p.z, -lim.x, lim.x) * p.z;
  float ty = clamp(p.y / p.z, -lim.y, lim.y) * p.z;
  vec3 u = vec3(intr.x / p.z, 0.0, -intr.x * tx / (p.z * p.z)) * R;
  vec3 v = vec3(0.0, intr.y / p.z, -intr.y * ty / (p.z * p.z)) * R;
  mat3 S = mat3(covA.x, covA.y, covA.z, covA.y, covB.x, covB.y, covA.z, covB.y, covB.z);
  float ca = dot(u, S * u) + 0.3;
  float cb = dot(u, S * v);
  float cc = dot(v, S * v) + 0.3;
  float det = ca * cc - cb * cb;
  if (!(det > 0.0)) return;
  vec2 mean = vec2(intr.x * p.x / p.z + intr.z, intr.y * p.y / p.z + intr.w);
  // the box where opacity exp(-d^T conic d / 2) >= 1/255, one pixel wider
  float k = sqrt(2.0 * log(255.0 * colour.a));
  vec2 half_size = k * sqrt(vec2(ca, cc)) + 1.0;
  vec2 pixel = mean + corner * half_size;
  gl_Position = vec4(2.0 * pixel.x / size.x - 1.0, 1.0 - 2.0 * pixel.y / size.y, 0.0, 1.0);
  vColour = colour;
  vConic = vec3(cc, -cb, ca) / det;
  vMean = mean;
}`;

const SPLAT_FS = `#version 300 es
precision highp float;
flat in vec4 vColour;
flat in vec3 vConic;
flat in vec2 vMean;
uniform vec2 size;
out vec4 fragColour;
void main() {
  vec2 d = vec2(gl_FragCoord.x, size.y - gl_FragCoord.y) - vMean;
  float power = -0.5 * (vConic.x * d.x * d.x + vConic.z * d.y * d.y) - vConic.y * d.x * d.y;
  if (power > 0.0) discard;
  float alpha = min(0.99, vColour.a * exp(power));
  if (alpha < 1.0 / 255.0) discard;
  fragColour = vec4(vColour.rgb * alpha, alpha);
}`;

const BLIT_VS = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}`;

const BLIT_FS = `#version 300 es
precision highp float;
uniform highp sampler2D image;
out vec4 fragColour;
void main() {
  fragColour = vec4(clamp(texelFetch(image, ivec2(gl_FragCoord.xy), 0).rgb, 0.0, 1.0), 1.0);
}`;

function program(gl, vs, fs) {
  const p = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    gl.attachShader(p, s);
  }
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
  return p;
}

class SplatRenderer {
  constructor(canvas) {
    const gl = canvas.getContext('webgl2', { antialias: false, alpha: false, depth: false,
                                              preserveDrawingBuffer: true });
    if (!gl) throw new Error('this browser has no WebGL2 (the player needs it)');
    this.gl = gl;
    this.canvas = canvas;
    const float32 = gl.getExtension('EXT_color_buffer_float') && gl.getExtension('EXT_float_blend');
    const float16 = float32 || gl.getExtension('EXT_color_buffer_half_float') ||
      gl.getExtension('EXT_color_buffer_float');
    this.format = float32 ? [gl.RGBA32F, gl.FLOAT] : float16 ? [gl.RGBA16F, gl.HALF_FLOAT] : null;
    this.formatName = float32 ? 'float32' : float16 ? 'float16' : '8-bit';
    this.splat = program(gl, SPLAT_VS, SPLAT_FS);
    this.blit = program(gl, BLIT_VS, BLIT_FS);
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const quad = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, quad);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    this.instances = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.instances);
    const layout = [[1, 3, 0], [2, 4, 3], [3, 3, 7], [4, 3, 10]];
    for (const [loc, n, off] of layout) {
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, n, gl.FLOAT, false, FLOATS * 4, off * 4);
      gl.vertexAttribDivisor(loc, 1);
    }
    gl.bindVertexArray(null);
  }

  target(w, h) {
    const gl = this.gl;
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
    }
    if (!this.format || (this.fbo && this.fboSize === `${w}x${h}`)) return;
    if (this.fbo) { gl.deleteFramebuffer(this.fbo); gl.deleteTexture(this.texture); }
    this.texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.texStorage2D(gl.TEXTURE_2D, 1, this.format[0], w, h);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST); // complete without mips
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    this.fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.texture, 0);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.fboSize = `${w}x${h}`;
  }

  draw(data, n, cam, background) {
    const gl = this.gl, w = cam.width, h = cam.height;
    this.target(w, h);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo || null);
    gl.viewport(0, 0, w, h);
    gl.clearColor(background[0], background[1], background[2], 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.useProgram(this.splat);
    const loc = (name) => gl.getUniformLocation(this.splat, name);
    gl.uniformMatrix3fv(loc('R'), true, cam.R);
    gl.uniform3fv(loc('T'), cam.t);
    gl.uniform4f(loc('intr'), cam.fx, cam.fy, cam.cx, cam.cy);
    gl.uniform2f(loc('size'), w, h);
    gl.uniform2f(loc('lim'), 1.3 * w / (2 * cam.fx), 1.3 * h / (2 * cam.fy));
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA); // back to front: C = c a + (1 - a) C
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.instances);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.DYNAMIC_DRAW);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, n);
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);
    if (this.fbo) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.useProgram(this.blit);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.texture);
      gl.uniform1i(gl.getUniformLocation(this.blit, 'image'), 0);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    }
    gl.finish();
  }
}

// ---------------------------------------------------------------------------------------------
// the player

class Player {
  constructor(scene, deformer, renderer, mode) {
    this.scene = scene;
    this.deformer = deformer;
    this.renderer = renderer;
    this.mode = mode;
    this.cameras = scene.cameras.map(cameraFrom);
    this.camera = this.cameras[scene.default_camera || 0];
    this.target = scene.target;
    [this.t0, this.t1] = scene.time_range;
    this.t = this.t0;
    this.playing = false;
    this.speed = 1;
    this.gaussians = null;
    this.cov = null;
    this.deformMs = [];
    this.drawMs = [];
    this.frameTimes = [];
  }

  async setTime(t) {
    this.t = Math.min(Math.max(t, this.t0), this.t1);
    const g = await this.deformer.run(this.t);
    if (g.t !== this.t && this.playing) return; // a newer time is on its way
    this.gaussians = g;
    this.cov = covariances(g);
    this.deformMs.push(g.ms);
    this.draw();
  }

  draw() {
    const g = this.gaussians;
    if (!g) return;
    const start = performance.now();
    const data = sortedInstances(g, this.cov, this.camera, this.scene.sh_degree);
    this.renderer.draw(data, g.n, this.camera, this.scene.background);
    this.drawMs.push(performance.now() - start);
    this.frameTimes.push(performance.now());
    api.frames += 1;
    this.updateReadout();
  }

  updateReadout() {
    const med = (a) => a.length ? [...a].sort((x, y) => x - y)[a.length >> 1] : NaN;
    const recent = (a) => a.slice(-30);
    const ft = recent(this.frameTimes);
    const fps = ft.length > 1 ? (ft.length - 1) * 1000 / (ft[ft.length - 1] - ft[0]) : NaN;
    const g = this.gaussians;
    api.stats = { deform_ms: med(recent(this.deformMs)), draw_ms: med(recent(this.drawMs)),
                  fps, gaussians: g ? g.n : 0, mode: this.mode };
    $('readout').textContent =
      `deform ${api.stats.deform_ms.toFixed(1)} ms (wasm, ${this.mode}) · ` +
      `draw ${api.stats.draw_ms.toFixed(1)} ms (${this.renderer.formatName} blending) · ` +
      `${this.playing && isFinite(fps) ? fps.toFixed(1) + ' frames/s · ' : ''}` +
      `${g ? g.n : 0} Gaussians (${this.scene.static_gaussians || 0} still, not deformed)`;
    $('tval').textContent = this.t.toFixed(3);
    $('time').value = String(Math.round(1000 * (this.t - this.t0) / (this.t1 - this.t0 || 1)));
  }

  async loop(now) {
    if (this.playing) {
      const dt = this.last === undefined ? 0 : (now - this.last) / 1000;
      // 1x plays the whole time range in 4 seconds
      let t = this.t + dt * this.speed * (this.t1 - this.t0) / 4;
      if (t > this.t1) t = this.t0 + (t - this.t1);
      this.last = now;
      if (!this.inFlight) {
        this.inFlight = true;
        await this.setTime(t).catch(fail);
        this.inFlight = false;
      } else {
        this.t = t;
      }
    } else {
      this.last = undefined;
    }
    requestAnimationFrame((n) => this.loop(n));
  }

  orbit(dx, dy) {
    const cam = this.camera, c = centre(cam), Rt = transpose(cam.R);
    const right = [Rt[0], Rt[3], Rt[6]], up = [-Rt[1], -Rt[4], -Rt[7]];
    const M = mul(axisRotation(up, -dx * 0.005), axisRotation(right, dy * 0.005));
    const rel = apply(M, [c[0] - this.target[0], c[1] - this.target[1], c[2] - this.target[2]]);
    this.camera = withPose(cam, mul(cam.R, transpose(M)),
      [this.target[0] + rel[0], this.target[1] + rel[1], this.target[2] + rel[2]]);
    this.draw();
  }

  move(right, down, forward) { // in camera axes, world units
    const cam = this.camera, c = centre(cam), R = cam.R;
    const d = [R[0] * right + R[3] * down + R[6] * forward, R[1] * right + R[4] * down + R[7] * forward,
      R[2] * right + R[5] * down + R[8] * forward];
    this.camera = withPose(cam, cam.R, [c[0] + d[0], c[1] + d[1], c[2] + d[2]]);
    this.target = [this.target[0] + d[0], this.target[1] + d[1], this.target[2] + d[2]];
    this.draw();
  }

  distance() {
    const c = centre(this.camera);
    return Math.hypot(c[0] - this.target[0], c[1] - this.target[1], c[2] - this.target[2]);
  }

  zoom(factor) {
    const cam = this.camera, c = centre(cam), d = this.distance();
    const f = [cam.R[6], cam.R[7], cam.R[8]];
    const step = d * (1 - factor);
    this.camera = withPose(cam, cam.R, [c[0] + f[0] * step, c[1] + f[1] * step, c[2] + f[2] * step]);
    this.draw();
  }
}

function bindControls(player) {
  const canvas = $('canvas');
  let drag = null;
  canvas.addEventListener('contextmenu', (e) => e.preventDefault());
  canvas.addEventListener('pointerdown', (e) => {
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener('pointerup', () => { drag = null; });
  canvas.addEventListener('pointermove', (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) {
      const s = player.distance() / player.camera.fx;
      player.move(-dx * s, -dy * s, 0);
    } else {
      player.orbit(dx, dy);
    }
  });
  canvas.addEventListener('wheel', (e) => {
    e.preventDefault();
    player.zoom(Math.exp(-e.deltaY * 0.001));
  }, { passive: false });
  window.addEventListener('keydown', (e) => {
    const s = player.distance() * 0.05;
    const keys = { w: [0, 0, s], s: [0, 0, -s], a: [-s, 0, 0], d: [s, 0, 0], q: [0, s, 0], e: [0, -s, 0] };
    const m = keys[e.key.toLowerCase()];
    if (m && e.target.tagName !== 'SELECT' && e.target.tagName !== 'INPUT') player.move(...m);
    if (e.key === ' ') { e.preventDefault(); $('play').click(); }
  });
  $('play').addEventListener('click', () => {
    player.playing = !player.playing;
    $('play').textContent = player.playing ? 'Pause' : 'Play';
  });
  $('speed').addEventListener('change', (e) => { player.speed = Number(e.target.value); });
  $('time').addEventListener('input', (e) => {
    const t = player.t0 + (player.t1 - player.t0) * Number(e.target.value) / 1000;
    player.setTime(t).catch(fail);
  });
  const select = $('camera');
  player.scene.cameras.forEach((c, i) => select.add(
    new Option((c.name || `camera ${i}`).replace(/^\.\//, ''), String(i))));
  select.value = String(Math.max(player.cameras.indexOf(player.camera), 0));
  select.addEventListener('change', (e) => {
    player.camera = player.cameras[Number(e.target.value)];
    player.draw();
  });
  if (player.scene.layers) {
    $('lodlabel').hidden = false;
    const lod = $('lod');
    for (let k = 0; k <= player.scene.layers.length; k++) {
      lod.add(new Option(`layers 0-${k}`, String(k)));
    }
    lod.value = String(player.deformer.detail);
    lod.addEventListener('change', (e) => {
      player.deformer.detail = Number(e.target.value);
      player.setTime(player.t).catch(fail);
    });
  }
}

async function main() {
  const started = performance.now();
  const scene = await (await fetch('scene.json')).json().catch((e) => {
    throw new Error(`scene.json: ${e.message}`);
  });
  if (scene.format !== 'nehad-web/1') throw new Error('scene.json is not a nehad player scene');
  const isolated = self.crossOriginIsolated === true;
  const threads = isolated ? Math.min(navigator.hardwareConcurrency || 1, 4) : 1;
  ort.env.wasm.numThreads = threads;
  ort.env.wasm.wasmPaths = new URL('./ort/', location.href).href;
  ort.env.wasm.wasmBinary = await fetchGunzipped('ort/ort-wasm-simd-threaded.wasm.gz');
  const mode = isolated ? `${threads} threads, cross-origin isolated`
    : '1 thread: the page is not cross-origin isolated';
  let session;
  try {
    session = await ort.InferenceSession.create(await fetchBytes(scene.model),
      { executionProviders: ['wasm'], graphOptimizationLevel: 'all' });
  } catch (e) {
    throw new Error(`${scene.model}: onnxruntime-web cannot load it (${e.message || e})`);
  }
  const deformer = new Deformer(session, scene);
  await deformer.loadLayers();
  const renderer = new SplatRenderer($('canvas'));
  const player = new Player(scene, deformer, renderer, mode);
  api.player = player;
  api.load_ms = performance.now() - started;
  const params = new URLSearchParams(location.search);
  if (params.has('camera')) player.camera = player.cameras[Number(params.get('camera'))];
  bindControls(player);
  await player.setTime(params.has('t') ? Number(params.get('t')) : player.t0);
  // for tests and scripts: draw camera `camera` at time t, then return the frame's figures
  api.show = async (t, camera) => {
    if (camera !== undefined && camera !== null) player.camera = player.cameras[camera];
    await player.setTime(t);
    return api.stats;
  };
  api.png = () => $('canvas').toDataURL('image/png');
  api.play = (on) => { if (player.playing !== on) $('play').click(); };
  api.ready = true;
  requestAnimationFrame((n) => player.loop(n));
}

main().catch(fail);
