// egobench view: the run's Gaussians rendered by egobench's rules (egobench/export/viewer.py says which), in
// WebGL2, with the method's image formation as a post pass, beside the captured frame and their difference.
"use strict";
(function () {
  const D = JSON.parse(document.getElementById("egobench-data").textContent);
  const W = D.width, H = D.height, TEXW = 1024;
  const $ = (id) => document.getElementById(id);

  function floats(b64) {
    const bin = atob(b64), bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    return new Float32Array(bytes.buffer);
  }

  // ---- poses: row-major 4 x 4 arrays; the camera is T_world_camera (OpenCV axes: x right, y down, z ahead)
  function rotation(axis, angle) { // Rodrigues, row-major 3 x 3
    const n = Math.hypot(axis[0], axis[1], axis[2]) || 1, x = axis[0] / n, y = axis[1] / n, z = axis[2] / n;
    const c = Math.cos(angle), s = Math.sin(angle), t = 1 - c;
    return [t * x * x + c, t * x * y - s * z, t * x * z + s * y,
            t * x * y + s * z, t * y * y + c, t * y * z - s * x,
            t * x * z - s * y, t * y * z + s * x, t * z * z + c];
  }
  const mul3 = (A, B) => [0, 1, 2].flatMap((i) => [0, 1, 2].map((j) => A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j]));
  const apply3 = (A, v) => [0, 1, 2].map((i) => A[3 * i] * v[0] + A[3 * i + 1] * v[1] + A[3 * i + 2] * v[2]);
  const column = (R, j) => [R[j], R[3 + j], R[6 + j]];

  const camera = { R: null, c: null, dist: 1.0, frame: null, moved: false }; // R_world_camera, centre
  function setPose(T) {
    camera.R = [T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]];
    camera.c = [T[3], T[7], T[11]];
  }
  function worldToCamera() { // (R_cw row-major, t_cw)
    const R = camera.R, Rt = [R[0], R[3], R[6], R[1], R[4], R[7], R[2], R[5], R[8]];
    const t = apply3(Rt, camera.c).map((v) => -v);
    return { R: Rt, t };
  }

  // ---- WebGL2: Gaussians into a floating-point target, then the formation into the canvas
  const canvas = $("render");
  canvas.width = W; canvas.height = H;
  const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, preserveDrawingBuffer: true,
                                           premultipliedAlpha: false });
  if (!gl) { $("status").textContent = "This page needs WebGL2."; throw new Error("no WebGL2"); }
  const floatTarget = gl.getExtension("EXT_color_buffer_float");
  const floatBlend = gl.getExtension("EXT_float_blend");

  const SPLAT_VS = `#version 300 es
  precision highp float; precision highp int; precision highp sampler2D;
  layout(location = 0) in vec2 a_corner;
  layout(location = 1) in uint a_index;
  uniform sampler2D u_t0, u_t1, u_t2, u_t3;
  uniform mat3 u_R; uniform vec3 u_t; uniform vec4 u_intr; uniform vec2 u_size; uniform float u_near;
  flat out vec2 v_mean; flat out vec3 v_conic; flat out float v_op; flat out vec3 v_color;
  void main() {
    ivec2 ij = ivec2(int(a_index % ${TEXW}u), int(a_index / ${TEXW}u));
    vec4 t0 = texelFetch(u_t0, ij, 0), t1 = texelFetch(u_t1, ij, 0), t2 = texelFetch(u_t2, ij, 0), t3 = texelFetch(u_t3, ij, 0);
    gl_Position = vec4(0.0, 0.0, 2.0, 1.0);  // culled: outside the clip volume
    vec3 p = u_R * t0.xyz + u_t;
    float op = t0.w;
    if (p.z < u_near || p.z > 1e10 || op < 1.0 / 255.0) return;
    mat3 S = mat3(t1.x, t1.y, t1.z, t1.y, t1.w, t2.x, t1.z, t2.x, t2.y);
    mat3 C = u_R * S * transpose(u_R);
    float fx = u_intr.x, fy = u_intr.y, cx = u_intr.z, cy = u_intr.w;
    float tanx = 0.5 * u_size.x / fx, tany = 0.5 * u_size.y / fy;
    float iz = 1.0 / p.z;
    float tx = clamp(p.x * iz, -(cx / fx + 0.3 * tanx), (u_size.x - cx) / fx + 0.3 * tanx);
    float ty = clamp(p.y * iz, -(cy / fy + 0.3 * tany), (u_size.y - cy) / fy + 0.3 * tany);
    vec3 J0 = vec3(fx * iz, 0.0, -fx * iz * tx), J1 = vec3(0.0, fy * iz, -fy * iz * ty);
    vec3 CJ0 = C * J0, CJ1 = C * J1;
    float c00 = dot(J0, CJ0) + 0.3, c11 = dot(J1, CJ1) + 0.3, c01 = dot(J0, CJ1);
    float det = c00 * c11 - c01 * c01;
    if (!(det > 0.0)) return;
    vec2 mean = vec2(fx * p.x * iz + cx, fy * p.y * iz + cy);
    float extend = min(3.33, sqrt(2.0 * log(op * 255.0)));
    vec2 radius = ceil(extend * sqrt(vec2(c00, c11)));
    vec2 px = mean + a_corner * radius;
    gl_Position = vec4(2.0 * px.x / u_size.x - 1.0, 1.0 - 2.0 * px.y / u_size.y, 0.0, 1.0);
    v_mean = mean; v_conic = vec3(c11 / det, -c01 / det, c00 / det); v_op = op; v_color = vec3(t2.z, t2.w, t3.x);
  }`;
  const SPLAT_FS = `#version 300 es
  precision highp float;
  flat in vec2 v_mean; flat in vec3 v_conic; flat in float v_op; flat in vec3 v_color;
  uniform vec2 u_size;
  out vec4 o;
  void main() {
    vec2 d = v_mean - vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);  // pixel centres at +0.5 (gsplat's pixels)
    float s = 0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) + v_conic.y * d.x * d.y;
    if (s < 0.0) discard;
    float a = min(0.999, v_op * exp(-s));
    if (a < 1.0 / 255.0) discard;
    o = vec4(v_color * a, a);  // premultiplied: composited back to front
  }`;
  const QUAD_VS = `#version 300 es
  layout(location = 0) in vec2 a_corner;
  void main() { gl_Position = vec4(a_corner, 0.0, 1.0); }`;
  const FORM_FS = `#version 300 es
  precision highp float; precision highp sampler2D;
  uniform sampler2D u_acc, u_vig;
  uniform vec3 u_bg; uniform float u_scale, u_gamma, u_toe; uniform int u_formation, u_scene_gamma, u_vig_on, u_clamp;
  out vec4 o;
  vec3 decode(vec3 y) {
    float y0 = pow(u_toe, 1.0 / u_gamma), slope = y0 / u_toe;
    return mix(y / slope, pow(max(y, vec3(y0)), vec3(u_gamma)), step(vec3(y0), y));
  }
  vec3 encode(vec3 x) {
    float slope = pow(u_toe, 1.0 / u_gamma) / u_toe;
    return mix(x * slope, pow(max(x, vec3(u_toe)), vec3(1.0 / u_gamma)), step(vec3(u_toe), x));
  }
  void main() {
    ivec2 ij = ivec2(gl_FragCoord.xy);
    vec4 acc = texelFetch(u_acc, ij, 0);
    vec3 rgb = acc.rgb + u_bg * (1.0 - acc.a);
    vec3 img = clamp(rgb, 0.0, 1.0);
    if (u_formation == 1) {
      float v = u_vig_on == 1 ? texelFetch(u_vig, ivec2(ij.x, ${H - 1} - ij.y), 0).r : 1.0;
      vec3 lin = u_scene_gamma == 1 ? decode(rgb) : rgb;
      img = encode(lin * (u_scale * v));
      if (u_clamp == 1) img = clamp(img, 0.0, 1.0);
    }
    o = vec4(img, 1.0);
  }`;

  function program(vs, fs) {
    const p = gl.createProgram();
    for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
      const s = gl.createShader(type);
      gl.shaderSource(s, src); gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
      gl.attachShader(p, s);
    }
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
    const u = {};
    for (let i = 0; i < gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS); i++) {
      const name = gl.getActiveUniform(p, i).name;
      u[name] = gl.getUniformLocation(p, name);
    }
    return { p, u };
  }
  const splat = program(SPLAT_VS, SPLAT_FS), form = program(QUAD_VS, FORM_FS);

  function floatTexture(data, width, height, format) {
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, t);
    for (const k of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, k, gl.NEAREST);
    const internal = format === gl.RED ? gl.R32F : gl.RGBA32F;
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, width, height, 0, format, gl.FLOAT, data);
    return t;
  }

  // the accumulation target: RGBA32F where float blending is available, else RGBA16F, else 8 bits
  const accFormat = floatTarget && floatBlend ? ["RGBA32F", gl.RGBA32F, gl.FLOAT]
    : floatTarget ? ["RGBA16F", gl.RGBA16F, gl.HALF_FLOAT] : ["RGBA8", gl.RGBA8, gl.UNSIGNED_BYTE];
  const acc = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, acc);
  for (const k of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, k, gl.NEAREST);
  gl.texImage2D(gl.TEXTURE_2D, 0, accFormat[1], W, H, 0, gl.RGBA, accFormat[2], null);
  const fbo = gl.createFramebuffer();
  gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
  gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, acc, 0);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);

  const corners = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, corners);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);

  // ---- the runs: Gaussians in four float textures, a sorted index per draw
  const runs = D.runs.map((r) => {
    const n = r.n, rows = Math.max(1, Math.ceil(n / TEXW)), size = TEXW * rows * 4;
    const means = floats(r.means), cov = floats(r.cov), op = floats(r.opacity), col = floats(r.colors);
    const t = [new Float32Array(size), new Float32Array(size), new Float32Array(size), new Float32Array(size)];
    for (let i = 0; i < n; i++) {
      t[0].set([means[3 * i], means[3 * i + 1], means[3 * i + 2], op[i]], 4 * i);
      t[1].set([cov[6 * i], cov[6 * i + 1], cov[6 * i + 2], cov[6 * i + 3]], 4 * i);
      t[2].set([cov[6 * i + 4], cov[6 * i + 5], col[3 * i], col[3 * i + 1]], 4 * i);
      t[3][4 * i] = col[3 * i + 2];
    }
    const vao = gl.createVertexArray(), index = gl.createBuffer();
    gl.bindVertexArray(vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, corners);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, index);
    gl.enableVertexAttribArray(1);
    gl.vertexAttribIPointer(1, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(1, 1);
    gl.bindVertexArray(null);
    return { label: r.label, n, means, vao, index, order: new Uint32Array(n), depth: new Float32Array(n),
             tex: t.map((a) => floatTexture(a, TEXW, rows, gl.RGBA)), bg: r.background, formation: r.formation,
             vig: floatTexture(floats(r.vignette), W, H, gl.RED), k: r.k };
  });
  const quadVao = gl.createVertexArray();
  gl.bindVertexArray(quadVao);
  gl.bindBuffer(gl.ARRAY_BUFFER, corners);
  gl.enableVertexAttribArray(0);
  gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
  gl.bindVertexArray(null);

  const state = { run: 0, stops: 0.0, gamma: null, diffGain: 4 };

  function sortBackToFront(run, view) {
    const r2 = [view.R[6], view.R[7], view.R[8]], tz = view.t[2], m = run.means;
    for (let i = 0; i < run.n; i++) {
      run.depth[i] = r2[0] * m[3 * i] + r2[1] * m[3 * i + 1] + r2[2] * m[3 * i + 2] + tz;
      run.order[i] = i;
    }
    const depth = run.depth;
    run.order.sort((a, b) => depth[b] - depth[a]);  // farthest first: "over" in reverse is front-to-back
    gl.bindBuffer(gl.ARRAY_BUFFER, run.index);
    gl.bufferData(gl.ARRAY_BUFFER, run.order, gl.DYNAMIC_DRAW);
  }

  function draw() {
    const run = runs[state.run], view = worldToCamera(), R = view.R;
    sortBackToFront(run, view);
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.viewport(0, 0, W, H);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.useProgram(splat.p);
    run.tex.forEach((t, i) => {
      gl.activeTexture(gl.TEXTURE0 + i); gl.bindTexture(gl.TEXTURE_2D, t); gl.uniform1i(splat.u[`u_t${i}`], i);
    });
    gl.uniformMatrix3fv(splat.u.u_R, false, [R[0], R[3], R[6], R[1], R[4], R[7], R[2], R[5], R[8]]);  // column-major
    gl.uniform3fv(splat.u.u_t, view.t);
    gl.uniform4f(splat.u.u_intr, D.fx, D.fy, D.cx + 0.5, D.cy + 0.5);  // gsplat's pixels: centres at +0.5
    gl.uniform2f(splat.u.u_size, W, H);
    gl.uniform1f(splat.u.u_near, D.near);
    gl.bindVertexArray(run.vao);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, run.n);
    gl.disable(gl.BLEND);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.useProgram(form.p);
    gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, acc); gl.uniform1i(form.u.u_acc, 0);
    gl.activeTexture(gl.TEXTURE1); gl.bindTexture(gl.TEXTURE_2D, run.vig); gl.uniform1i(form.u.u_vig, 1);
    const f = run.formation, k = camera.frame === null ? 1.0 : run.k[String(camera.frame)];
    gl.uniform3fv(form.u.u_bg, run.bg);
    gl.uniform1f(form.u.u_scale, (f.exposure_gain ? k : 1.0) * Math.pow(2.0, state.stops));
    gl.uniform1f(form.u.u_gamma, state.gamma === null ? f.gamma : state.gamma);
    gl.uniform1f(form.u.u_toe, f.toe_linear);
    gl.uniform1i(form.u.u_formation, f.enabled ? 1 : 0);
    gl.uniform1i(form.u.u_scene_gamma, f.scene_gamma ? 1 : 0);
    gl.uniform1i(form.u.u_vig_on, f.vignette ? 1 : 0);
    gl.uniform1i(form.u.u_clamp, f.clamp ? 1 : 0);
    gl.bindVertexArray(quadVao);
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
    gl.bindVertexArray(null);
    drawDifference();
    status();
  }

  // ---- the captured frame and the difference
  const capCtx = Object.assign($("captured"), { width: W, height: H }).getContext("2d", { willReadFrequently: true });
  const diffCanvas = Object.assign($("diff"), { width: W, height: H }), diffCtx = diffCanvas.getContext("2d");
  let captured = null;  // ImageData of the snapped frame

  function loadCaptured(frame) {
    return new Promise((resolve, reject) => {
      const img = new Image();
      img.onload = () => { capCtx.drawImage(img, 0, 0, W, H); captured = capCtx.getImageData(0, 0, W, H); resolve(); };
      img.onerror = () => reject(new Error(`frame ${frame.index}: its image does not decode`));
      img.src = frame.image;
    });
  }

  function renderPixels() {  // the canvas's RGBA, top row first
    const px = new Uint8Array(W * H * 4), out = new Uint8ClampedArray(W * H * 4);
    gl.readPixels(0, 0, W, H, gl.RGBA, gl.UNSIGNED_BYTE, px);
    for (let y = 0; y < H; y++) out.set(px.subarray((H - 1 - y) * W * 4, (H - y) * W * 4), y * W * 4);
    return out;
  }

  function drawDifference() {
    if (captured === null) return;
    const r = renderPixels(), c = captured.data, d = diffCtx.createImageData(W, H);
    for (let i = 0; i < r.length; i += 4) {
      for (let ch = 0; ch < 3; ch++) d.data[i + ch] = Math.min(255, Math.abs(r[i + ch] - c[i + ch]) * state.diffGain);
      d.data[i + 3] = 255;
    }
    diffCtx.putImageData(d, 0, 0);
  }

  function status() {
    const run = runs[state.run], f = D.frames.find((x) => x.index === camera.frame);
    const where = f ? `frame ${f.index} (${f.held_out ? "held out" : "training"})${camera.moved ? ", moved" : ""}` : "free";
    $("render-cap").textContent = `render: ${run.label}`;
    $("captured-cap").textContent = f ? `captured: frame ${f.index}` + (camera.moved ? " (the camera has moved)" : "") : "captured";
    $("status").textContent = `${run.n} Gaussians · camera: ${where} · near plane ${D.near} m · ` +
      `composited in ${accFormat[0]} · ${W} x ${H} px`;
  }

  // ---- controls
  function snap(index) {
    const f = D.frames.find((x) => x.index === index);
    if (!f) throw new Error(`no frame ${index}`);
    setPose(f.pose);
    camera.frame = index; camera.moved = false;
    $("frame").value = String(index);
    const run = runs[state.run], view = worldToCamera();
    sortBackToFront(run, view);  // the orbit distance: the median depth in front
    const ahead = Array.from(run.depth).filter((z) => z > D.near).sort((a, b) => a - b);
    camera.dist = ahead.length ? ahead[ahead.length >> 1] : 1.0;
    return loadCaptured(f).then(draw);
  }

  function turn(Q, about) {
    camera.R = mul3(Q, camera.R);
    const rel = camera.c.map((v, i) => v - about[i]);
    camera.c = apply3(Q, rel).map((v, i) => v + about[i]);
    camera.moved = true;
    draw();
  }

  let drag = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, look: e.shiftKey || e.button === 2 };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const k = 0.005, dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    const up = column(camera.R, 1), right = column(camera.R, 0);
    const Q = mul3(rotation(up, -dx * k * (drag.look ? -1 : 1)), rotation(right, dy * k * (drag.look ? -1 : 1)));
    const target = drag.look ? camera.c : camera.c.map((v, i) => v + camera.dist * camera.R[3 * i + 2]);
    turn(Q, target);
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const step = Math.sign(e.deltaY) * -0.1 * camera.dist;
    camera.c = camera.c.map((v, i) => v + step * camera.R[3 * i + 2]);
    camera.dist = Math.max(1e-3, camera.dist - step);
    camera.moved = true;
    draw();
  }, { passive: false });
  window.addEventListener("keydown", (e) => {
    if (e.target.tagName === "SELECT" || e.target.tagName === "INPUT") return;
    const move = { w: [0, 0, 1], s: [0, 0, -1], a: [-1, 0, 0], d: [1, 0, 0], q: [0, -1, 0], e: [0, 1, 0] }[e.key.toLowerCase()];
    const i = D.frames.findIndex((x) => x.index === camera.frame);
    if (move) {
      const v = apply3(camera.R, move).map((x) => x * 0.05 * camera.dist);
      camera.c = camera.c.map((c, j) => c + v[j]);
      camera.moved = true;
      draw();
    } else if (e.key === "]" || e.key === "[") {
      snap(D.frames[(i + (e.key === "]" ? 1 : D.frames.length - 1)) % D.frames.length].index);
    } else if (e.key.toLowerCase() === "r" && camera.frame !== null) {
      snap(camera.frame);
    }
  });

  const frameSelect = $("frame");
  for (const f of D.frames) {
    const o = document.createElement("option");
    o.value = String(f.index);
    o.textContent = `frame ${f.index}${f.held_out ? " (held out)" : ""}`;
    frameSelect.appendChild(o);
  }
  frameSelect.addEventListener("change", () => snap(Number(frameSelect.value)));
  const exposure = $("exposure"), gamma = $("gamma");
  gamma.value = String(runs[0].formation.gamma);
  function showSliders() {
    $("exposure-out").textContent = `${state.stops >= 0 ? "+" : ""}${state.stops.toFixed(2)} stops`;
    $("gamma-out").textContent = (state.gamma === null ? runs[state.run].formation.gamma : state.gamma).toFixed(2);
  }
  exposure.addEventListener("input", () => { state.stops = Number(exposure.value); showSliders(); draw(); });
  gamma.addEventListener("input", () => { state.gamma = Number(gamma.value); showSliders(); draw(); });
  $("diffgain").addEventListener("change", (e) => { state.diffGain = Number(e.target.value); draw(); });
  function zoom(z) {
    for (const c of [canvas, $("captured"), diffCanvas]) { c.style.width = `${W * z}px`; c.style.height = `${H * z}px`; }
  }
  $("zoom").addEventListener("change", (e) => zoom(Number(e.target.value)));
  if (runs.length > 1) {
    runs.forEach((r, j) => {
      const label = document.createElement("label"), input = document.createElement("input");
      Object.assign(input, { type: "radio", name: "run", checked: j === 0 });
      input.addEventListener("change", () => { state.run = j; showSliders(); draw(); });
      label.append(input, ` ${r.label} `);
      $("runs").appendChild(label);
    });
  }
  $("title").textContent = `egobench view: ${runs.map((r) => r.label).join(" | ")} on ${D.recording}`;

  // the page's interface (the browser test drives it)
  window.egobench = {
    ready: false, target: accFormat[0], frames: D.frames.map((f) => ({ index: f.index, held_out: f.held_out })),
    snap, draw,
    setExposure(stops) { state.stops = stops; exposure.value = String(stops); showSliders(); draw(); },
    setGamma(g) { state.gamma = g; gamma.value = String(g); showSliders(); draw(); },
    setRun(j) { state.run = j; showSliders(); draw(); },
    zoom,
    renderPNG() { return canvas.toDataURL("image/png"); },
  };
  zoom(Number($("zoom").value));
  showSliders();
  const first = D.frames.find((f) => f.held_out) || D.frames[0];
  snap(first.index).then(() => { window.egobench.ready = true; });
})();
