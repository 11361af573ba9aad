// Sylva's Gaussian-splat viewer: WebGL2, splats depth-sorted back to front each time the view
// changes, orbit controls around a Z-up scene, and stems drawn as axes with their 1.3 m circle
// and an HTML label (tree id and DBH) that can be clicked.
//
// Inputs it understands:
// - the compact `.splat` format (antimatter15): 32 bytes per splat = position f32×3,
//   scale f32×3 (linear, metres), RGBA u8×4, rotation u8×4 = (w, x, y, z)·128 + 128;
// - binary little-endian PLY point clouds (the job's anchors), drawn as small round splats.
//
// Splat maths (Zwicker et al. 2001; Kerbl et al. 2023): the 3-D covariance Σ = R S Sᵀ Rᵀ is
// projected with the Jacobian of the pinhole projection, Σ' = J W Σ Wᵀ Jᵀ (+0.3 px² so a splat
// never gets thinner than a pixel), and each splat is a screen quad along Σ''s eigenvectors,
// shaded with exp(-½ dᵀΣ'⁻¹d) and blended with premultiplied alpha, farthest first.
'use strict';

const SylvaViewer = (() => {
  // ---------------------------------------------------------------- parsing

  /** Parses a `.splat` buffer into {count, positions, scales, colors, rotations}. */
  function parseSplat(buffer) {
    const ROW = 32;
    if (!(buffer instanceof ArrayBuffer) || buffer.byteLength % ROW !== 0) {
      throw new Error(`a .splat file has a multiple of 32 bytes; this one has ${buffer && buffer.byteLength}`);
    }
    const count = buffer.byteLength / ROW;
    const f = new Float32Array(buffer);
    const u = new Uint8Array(buffer);
    const positions = new Float32Array(3 * count);
    const scales = new Float32Array(3 * count);
    const colors = new Uint8Array(4 * count);
    const rotations = new Float32Array(4 * count);
    for (let i = 0; i < count; i++) {
      for (let k = 0; k < 3; k++) {
        positions[3 * i + k] = f[8 * i + k];
        scales[3 * i + k] = f[8 * i + 3 + k];
      }
      for (let k = 0; k < 4; k++) {
        colors[4 * i + k] = u[ROW * i + 24 + k];
        rotations[4 * i + k] = (u[ROW * i + 28 + k] - 128) / 128;
      }
    }
    return { count, positions, scales, colors, rotations };
  }

  const PLY_TYPES = {
    char: ['getInt8', 1], int8: ['getInt8', 1], uchar: ['getUint8', 1], uint8: ['getUint8', 1],
    short: ['getInt16', 2], int16: ['getInt16', 2], ushort: ['getUint16', 2], uint16: ['getUint16', 2],
    int: ['getInt32', 4], int32: ['getInt32', 4], uint: ['getUint32', 4], uint32: ['getUint32', 4],
    float: ['getFloat32', 4], float32: ['getFloat32', 4], double: ['getFloat64', 8], float64: ['getFloat64', 8],
  };

  /**
   * Parses the vertex element of a binary little-endian PLY: {count, props: {name: Float32Array},
   * offset: [x, y, z]} (the offset from a `comment sylva_offset X Y Z` line, else zeros).
   */
  function parsePly(buffer) {
    const head = new TextDecoder('latin1').decode(new Uint8Array(buffer, 0, Math.min(buffer.byteLength, 65536)));
    const end = head.indexOf('end_header');
    if (!head.startsWith('ply') || end < 0) throw new Error('not a PLY file');
    let bodyStart = end + 'end_header'.length;
    if (head[bodyStart] === '\r') bodyStart++;
    bodyStart++; // the newline
    const lines = head.slice(0, end).split(/\r?\n/);
    let format = '', offset = [0, 0, 0];
    const elements = [];
    for (const line of lines) {
      const w = line.trim().split(/\s+/);
      if (w[0] === 'format') format = w[1];
      else if (w[0] === 'comment' && w[1] === 'sylva_offset') offset = w.slice(2, 5).map(Number);
      else if (w[0] === 'element') elements.push({ name: w[1], count: Number(w[2]), props: [] });
      else if (w[0] === 'property' && elements.length) {
        const el = elements[elements.length - 1];
        if (w[1] === 'list') el.props.push({ list: true, countType: w[2], type: w[3], name: w[4] });
        else el.props.push({ type: w[1], name: w[2] });
      }
    }
    if (format !== 'binary_little_endian') throw new Error(`PLY format ${format} is not supported here (binary_little_endian only)`);
    const view = new DataView(buffer);
    let pos = bodyStart;
    for (const el of elements) {
      const fixed = el.props.every((p) => !p.list && PLY_TYPES[p.type]);
      if (el.name !== 'vertex') {
        if (!fixed) throw new Error('PLY elements before the vertices must have fixed-size rows');
        pos += el.count * el.props.reduce((s, p) => s + PLY_TYPES[p.type][1], 0);
        continue;
      }
      if (!fixed) throw new Error('PLY vertex lists are not supported');
      const stride = el.props.reduce((s, p) => s + PLY_TYPES[p.type][1], 0);
      if (pos + stride * el.count > buffer.byteLength) throw new Error('the PLY file is shorter than its header says');
      const props = {};
      let off = 0;
      for (const p of el.props) {
        const [getter, size] = PLY_TYPES[p.type];
        const out = new Float32Array(el.count);
        for (let i = 0, at = pos + off; i < el.count; i++, at += stride) out[i] = view[getter](at, true);
        props[p.name] = out;
        off += size;
      }
      return { count: el.count, props, offset };
    }
    throw new Error('the PLY file has no vertex element');
  }

  /**
   * Turns a PLY point cloud (anchors) into round splats of radius `size` metres (1 σ).
   * mode 'photo' keeps the points' colours; 'label' greys everything but the trunks (label 1),
   * which are drawn amber.
   */
  function pointsToSplats(ply, mode = 'photo', size = 0.015) {
    const n = ply.count, p = ply.props;
    if (!p.x || !p.y || !p.z) throw new Error('the point cloud has no x, y, z');
    const positions = new Float32Array(3 * n);
    const scales = new Float32Array(3 * n).fill(size);
    const colors = new Uint8Array(4 * n);
    const rotations = new Float32Array(4 * n);
    const hasRgb = p.red && p.green && p.blue;
    for (let i = 0; i < n; i++) {
      positions[3 * i] = p.x[i]; positions[3 * i + 1] = p.y[i]; positions[3 * i + 2] = p.z[i];
      let r = hasRgb ? p.red[i] : 150, g = hasRgb ? p.green[i] : 170, b = hasRgb ? p.blue[i] : 150;
      if (mode === 'label') {
        const trunk = p.label ? p.label[i] > 0.5 : (p.trunk_prob ? p.trunk_prob[i] > 0.5 : false);
        if (trunk) { r = 235; g = 160; b = 40; } else { const m = 0.25 * (r + g + b) / 3 + 60; r = m; g = m + 8; b = m; }
      }
      colors[4 * i] = r; colors[4 * i + 1] = g; colors[4 * i + 2] = b; colors[4 * i + 3] = 255;
      rotations[4 * i] = 1;
    }
    return { count: n, positions, scales, colors, rotations };
  }

  // ---------------------------------------------------------------- GPU data

  const halfBuf = new Float32Array(1);
  const halfInt = new Int32Array(halfBuf.buffer);
  /** IEEE half-float bits of `v` (round to nearest, flush tiny values to zero). */
  function toHalf(v) {
    halfBuf[0] = v;
    const x = halfInt[0];
    const sign = (x >> 16) & 0x8000;
    let exp = ((x >> 23) & 0xff) - 127 + 15;
    let mant = x & 0x7fffff;
    if (exp <= 0) {
      if (exp < -10) return sign;
      mant = (mant | 0x800000) >> (1 - exp);
      return sign | ((mant + 0x1000) >> 13);
    }
    if (exp >= 31) return sign | 0x7c00;
    const h = sign | (exp << 10) | ((mant + 0x1000) >> 13);
    return h;
  }

  /** Packs splats into the RGBA32UI texture layout the shader reads: 2 texels per splat. */
  function packTexture(s) {
    const width = 2048, height = Math.max(1, Math.ceil(s.count / 1024));
    const data = new Uint32Array(width * height * 4);
    const fbits = new Float32Array(data.buffer);
    for (let i = 0; i < s.count; i++) {
      const o = 8 * i;
      fbits[o] = s.positions[3 * i]; fbits[o + 1] = s.positions[3 * i + 1]; fbits[o + 2] = s.positions[3 * i + 2];
      data[o + 3] = (s.colors[4 * i] | (s.colors[4 * i + 1] << 8) | (s.colors[4 * i + 2] << 16) | (s.colors[4 * i + 3] << 24)) >>> 0;
      let w = s.rotations[4 * i], x = s.rotations[4 * i + 1], y = s.rotations[4 * i + 2], z = s.rotations[4 * i + 3];
      const qn = Math.hypot(w, x, y, z) || 1;
      w /= qn; x /= qn; y /= qn; z /= qn;
      const sx = s.scales[3 * i], sy = s.scales[3 * i + 1], sz = s.scales[3 * i + 2];
      // M = R·S (rows of R scaled by column), Σ = M Mᵀ.
      const m = [
        (1 - 2 * (y * y + z * z)) * sx, (2 * (x * y - w * z)) * sy, (2 * (x * z + w * y)) * sz,
        (2 * (x * y + w * z)) * sx, (1 - 2 * (x * x + z * z)) * sy, (2 * (y * z - w * x)) * sz,
        (2 * (x * z - w * y)) * sx, (2 * (y * z + w * x)) * sy, (1 - 2 * (x * x + y * y)) * sz,
      ];
      const dot = (a, b) => m[3 * a] * m[3 * b] + m[3 * a + 1] * m[3 * b + 1] + m[3 * a + 2] * m[3 * b + 2];
      const xx = dot(0, 0), xy = dot(0, 1), xz = dot(0, 2), yy = dot(1, 1), yz = dot(1, 2), zz = dot(2, 2);
      data[o + 4] = (toHalf(xx) | (toHalf(xy) << 16)) >>> 0;
      data[o + 5] = (toHalf(xz) | (toHalf(yy) << 16)) >>> 0;
      data[o + 6] = (toHalf(yz) | (toHalf(zz) << 16)) >>> 0;
    }
    return { width, height, data };
  }

  const SPLAT_VS = `#version 300 es
precision highp float; precision highp int;
uniform highp usampler2D u_data;
uniform mat4 u_view; uniform vec2 u_focal; uniform vec2 u_viewport; uniform float u_scale2;
in vec2 a_corner; in uint a_index;
out vec4 v_color; out vec2 v_pos;
void main() {
  ivec2 t = ivec2(int((a_index & 1023u) << 1u), int(a_index >> 10u));
  uvec4 c = texelFetch(u_data, t, 0);
  vec4 cam = u_view * vec4(uintBitsToFloat(c.xyz), 1.0);
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);
  if (cam.z < 0.05) return;
  vec2 pix = u_focal * cam.xy / cam.z;
  if (any(greaterThan(abs(pix), 0.75 * u_viewport))) return;
  uvec4 cv = texelFetch(u_data, t + ivec2(1, 0), 0);
  vec2 a = unpackHalf2x16(cv.x), b = unpackHalf2x16(cv.y), d = unpackHalf2x16(cv.z);
  mat3 S = u_scale2 * mat3(a.x, a.y, b.x, a.y, b.y, d.x, b.x, d.x, d.y);
  float iz = 1.0 / cam.z;
  mat3 J = mat3(u_focal.x * iz, 0.0, 0.0, 0.0, u_focal.y * iz, 0.0,
                -u_focal.x * cam.x * iz * iz, -u_focal.y * cam.y * iz * iz, 0.0);
  mat3 T = J * mat3(u_view);
  mat3 C = T * S * transpose(T);
  float xx = C[0][0] + 0.3, xy = C[0][1], yy = C[1][1] + 0.3;
  float mid = 0.5 * (xx + yy), rad = length(vec2(0.5 * (xx - yy), xy));
  float l1 = mid + rad, l2 = mid - rad;
  if (l2 <= 0.0) return;
  vec2 dir = abs(xy) > 1e-9 ? normalize(vec2(xy, l1 - xx)) : (xx >= yy ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
  vec2 major = min(sqrt(2.0 * l1), 1024.0) * dir;
  vec2 minor = min(sqrt(2.0 * l2), 1024.0) * vec2(dir.y, -dir.x);
  vec2 p = pix + a_corner.x * major + a_corner.y * minor;
  gl_Position = vec4(p.x / (0.5 * u_viewport.x), -p.y / (0.5 * u_viewport.y), 0.0, 1.0);
  v_color = vec4(float(c.w & 255u), float((c.w >> 8u) & 255u), float((c.w >> 16u) & 255u), float(c.w >> 24u)) / 255.0;
  v_pos = a_corner;
}`;
  const SPLAT_FS = `#version 300 es
precision highp float;
in vec4 v_color; in vec2 v_pos; out vec4 o;
void main() {
  float A = -dot(v_pos, v_pos);
  if (A < -4.0) discard;
  float B = exp(A) * v_color.a;
  o = vec4(v_color.rgb * B, B);
}`;
  const LINE_VS = `#version 300 es
precision highp float;
uniform mat4 u_view; uniform vec2 u_focal; uniform vec2 u_viewport;
in vec3 a_pos; in vec4 a_color; out vec4 v_color;
void main() {
  vec4 cam = u_view * vec4(a_pos, 1.0);
  float z = max(cam.z, 0.05);
  vec2 pix = u_focal * cam.xy / z;
  gl_Position = vec4(pix.x / (0.5 * u_viewport.x), -pix.y / (0.5 * u_viewport.y), 0.0, cam.z < 0.05 ? -1.0 : 1.0);
  v_color = a_color;
}`;
  const LINE_FS = `#version 300 es
precision highp float;
in vec4 v_color; out vec4 o;
void main() { o = vec4(v_color.rgb * v_color.a, v_color.a); }`;

  function compile(gl, vs, fs) {
    const prog = gl.createProgram();
    for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
      const sh = gl.createShader(type);
      gl.shaderSource(sh, src);
      gl.compileShader(sh);
      if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new Error(`shader: ${gl.getShaderInfoLog(sh)}`);
      gl.attachShader(prog, sh);
    }
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(`program: ${gl.getProgramInfoLog(prog)}`);
    return prog;
  }

  // ---------------------------------------------------------------- the viewer

  const BACKGROUND = [16 / 255, 24 / 255, 26 / 255];

  /**
   * A viewer on `canvas`, with stem labels placed in `labelLayer` (an element over it).
   * Options: onStemClick(stem).
   */
  function create(canvas, labelLayer, options = {}) {
    const gl = canvas.getContext('webgl2', { antialias: false, premultipliedAlpha: true, preserveDrawingBuffer: true });
    if (!gl) throw new Error('this browser has no WebGL2');
    const splatProg = compile(gl, SPLAT_VS, SPLAT_FS);
    const lineProg = compile(gl, LINE_VS, LINE_FS);
    const loc = (p, n) => gl.getUniformLocation(p, n);

    // One quad, instanced once per splat; a_index is the splat drawn, in sorted order.
    const splatVao = gl.createVertexArray();
    gl.bindVertexArray(splatVao);
    const cornerBuf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, cornerBuf);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-2, -2, 2, -2, 2, 2, -2, 2]), gl.STATIC_DRAW);
    const aCorner = gl.getAttribLocation(splatProg, 'a_corner');
    gl.enableVertexAttribArray(aCorner);
    gl.vertexAttribPointer(aCorner, 2, gl.FLOAT, false, 0, 0);
    const indexBuf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, indexBuf);
    const aIndex = gl.getAttribLocation(splatProg, 'a_index');
    gl.enableVertexAttribArray(aIndex);
    gl.vertexAttribIPointer(aIndex, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(aIndex, 1);
    const texture = gl.createTexture();

    const lineVao = gl.createVertexArray();
    gl.bindVertexArray(lineVao);
    const lineBuf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, lineBuf);
    const aPos = gl.getAttribLocation(lineProg, 'a_pos');
    const aColor = gl.getAttribLocation(lineProg, 'a_color');
    gl.enableVertexAttribArray(aPos);
    gl.vertexAttribPointer(aPos, 3, gl.FLOAT, false, 28, 0);
    gl.enableVertexAttribArray(aColor);
    gl.vertexAttribPointer(aColor, 4, gl.FLOAT, false, 28, 12);
    gl.bindVertexArray(null);

    const state = {
      splats: null, order: null, lineCount: 0, stems: [], stemsVisible: true, selected: null,
      scale: 1, target: [0, 0, 0], distance: 10, azimuth: -Math.PI / 3, elevation: 0.6, fovy: 50 * Math.PI / 180,
      home: null, dirty: true, lastSortView: null, lastSortTime: 0, frames: 0, destroyed: false, onView: null,
    };

    function camera() {
      const ce = Math.cos(state.elevation), se = Math.sin(state.elevation);
      const ca = Math.cos(state.azimuth), sa = Math.sin(state.azimuth);
      const t = state.target;
      const eye = [t[0] + state.distance * ce * ca, t[1] + state.distance * ce * sa, t[2] + state.distance * se];
      // OpenCV camera axes: x right, y down, z forward.
      const f = [-ce * ca, -ce * sa, -se];
      let r = [f[1], -f[0], 0]; // f × up(0,0,1)
      const rl = Math.hypot(r[0], r[1]) || 1;
      r = [r[0] / rl, r[1] / rl, 0];
      const d = [f[1] * r[2] - f[2] * r[1], f[2] * r[0] - f[0] * r[2], f[0] * r[1] - f[1] * r[0]];
      const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
      // Column-major 4×4: rows r, d, f; translation -R·eye.
      const view = new Float32Array([
        r[0], d[0], f[0], 0, r[1], d[1], f[1], 0, r[2], d[2], f[2], 0,
        -dot(r, eye), -dot(d, eye), -dot(f, eye), 1,
      ]);
      const w = canvas.width, h = canvas.height;
      const fy = 0.5 * h / Math.tan(0.5 * state.fovy);
      return { view, eye, f, focal: [fy, fy], viewport: [w, h] };
    }

    /** Pixel position (CSS pixels) of a world point, or null behind the camera. */
    function project(cam, p) {
      const v = cam.view;
      const x = v[0] * p[0] + v[4] * p[1] + v[8] * p[2] + v[12];
      const y = v[1] * p[0] + v[5] * p[1] + v[9] * p[2] + v[13];
      const z = v[2] * p[0] + v[6] * p[1] + v[10] * p[2] + v[14];
      if (z < 0.05) return null;
      const k = canvas.clientWidth / canvas.width || 1;
      return [(cam.focal[0] * x / z + 0.5 * cam.viewport[0]) * k, (cam.focal[1] * y / z + 0.5 * cam.viewport[1]) * k];
    }

    /** Sorts splats farthest first (16-bit counting sort on camera depth). */
    function sort(cam) {
      const s = state.splats;
      if (!s) return;
      const n = s.count, p = s.positions, f = cam.f, e = cam.eye;
      const depth = new Float32Array(n);
      let lo = Infinity, hi = -Infinity;
      for (let i = 0; i < n; i++) {
        const z = (p[3 * i] - e[0]) * f[0] + (p[3 * i + 1] - e[1]) * f[1] + (p[3 * i + 2] - e[2]) * f[2];
        depth[i] = z;
        if (z < lo) lo = z;
        if (z > hi) hi = z;
      }
      const B = 65536, k = (B - 1) / Math.max(hi - lo, 1e-6);
      const counts = new Uint32Array(B);
      const bucket = new Uint16Array(n);
      for (let i = 0; i < n; i++) {
        const q = B - 1 - Math.floor((depth[i] - lo) * k); // far first
        bucket[i] = q;
        counts[q]++;
      }
      for (let i = 1; i < B; i++) counts[i] += counts[i - 1];
      const order = state.order && state.order.length === n ? state.order : new Uint32Array(n);
      for (let i = n - 1; i >= 0; i--) order[--counts[bucket[i]]] = i;
      state.order = order;
      gl.bindBuffer(gl.ARRAY_BUFFER, indexBuf);
      gl.bufferData(gl.ARRAY_BUFFER, order, gl.DYNAMIC_DRAW);
      state.lastSortView = [...e, ...f];
      state.lastSortTime = performance.now();
    }

    function resize() {
      const dpr = Math.min(window.devicePixelRatio || 1, 2);
      const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
      if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; state.dirty = true; }
    }

    function draw() {
      resize();
      const cam = camera();
      gl.viewport(0, 0, canvas.width, canvas.height);
      gl.clearColor(BACKGROUND[0], BACKGROUND[1], BACKGROUND[2], 1);
      gl.clear(gl.COLOR_BUFFER_BIT);
      gl.disable(gl.DEPTH_TEST);
      gl.enable(gl.BLEND);
      gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
      if (state.splats) {
        const moved = !state.lastSortView || state.lastSortView.some((v, i) => Math.abs(v - [...cam.eye, ...cam.f][i]) > 1e-4);
        // Big scenes re-sort at most every 80 ms while moving; the last frame always sorts.
        if (moved && (state.splats.count < 300000 || performance.now() - state.lastSortTime > 80)) sort(cam);
        else if (moved) state.dirty = true;
        gl.useProgram(splatProg);
        gl.activeTexture(gl.TEXTURE0);
        gl.bindTexture(gl.TEXTURE_2D, texture);
        gl.uniform1i(loc(splatProg, 'u_data'), 0);
        gl.uniformMatrix4fv(loc(splatProg, 'u_view'), false, cam.view);
        gl.uniform2fv(loc(splatProg, 'u_focal'), cam.focal);
        gl.uniform2fv(loc(splatProg, 'u_viewport'), cam.viewport);
        gl.uniform1f(loc(splatProg, 'u_scale2'), state.scale * state.scale);
        gl.bindVertexArray(splatVao);
        gl.drawArraysInstanced(gl.TRIANGLE_FAN, 0, 4, state.splats.count);
      }
      if (state.stemsVisible && state.lineCount) {
        gl.useProgram(lineProg);
        gl.uniformMatrix4fv(loc(lineProg, 'u_view'), false, cam.view);
        gl.uniform2fv(loc(lineProg, 'u_focal'), cam.focal);
        gl.uniform2fv(loc(lineProg, 'u_viewport'), cam.viewport);
        gl.bindVertexArray(lineVao);
        gl.drawArrays(gl.LINES, 0, state.lineCount);
      }
      gl.bindVertexArray(null);
      placeLabels(cam);
      state.frames++;
      if (state.onView) state.onView(cam);
    }

    function loop() {
      if (state.destroyed) return;
      if (state.dirty) { state.dirty = false; draw(); }
      requestAnimationFrame(loop);
    }
    requestAnimationFrame(loop);

    // ------------------------------------------------------------ stems

    function stemTop(s) { return s.slice; }

    function rebuildLines() {
      const v = [];
      const push = (p, c) => v.push(p[0], p[1], p[2], c[0], c[1], c[2], c[3]);
      for (const s of state.stems) {
        const sel = state.selected === s.id;
        const axisColor = sel ? [1, 0.84, 0.3, 1] : [1, 0.85, 0.35, 0.75];
        const ringColor = sel ? [1, 0.3, 0.2, 1] : [0.95, 0.35, 0.25, 0.9];
        const top = [s.base[0] + s.axis[0] * s.height, s.base[1] + s.axis[1] * s.height, s.base[2] + s.axis[2] * s.height];
        push(s.base, axisColor); push(top, axisColor);
        const r = Math.max(s.radius, 0.02), c = s.slice, N = 48;
        for (let i = 0; i < N; i++) {
          const a0 = 2 * Math.PI * i / N, a1 = 2 * Math.PI * (i + 1) / N;
          push([c[0] + r * Math.cos(a0), c[1] + r * Math.sin(a0), c[2]], ringColor);
          push([c[0] + r * Math.cos(a1), c[1] + r * Math.sin(a1), c[2]], ringColor);
        }
      }
      gl.bindBuffer(gl.ARRAY_BUFFER, lineBuf);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(v), gl.STATIC_DRAW);
      state.lineCount = v.length / 7;
      state.dirty = true;
    }

    function placeLabels(cam) {
      for (const s of state.stems) {
        const el = s.label;
        if (!el) continue;
        const p = state.stemsVisible ? project(cam, stemTop(s)) : null;
        if (!p) { el.hidden = true; continue; }
        el.hidden = false;
        el.style.left = `${p[0]}px`;
        el.style.top = `${p[1]}px`;
        el.classList.toggle('selected', state.selected === s.id);
      }
    }

    /**
     * Stems in the scene's frame: [{id, base, axis, height, slice:[x,y,z], radius, text}].
     */
    function setStems(stems) {
      for (const s of state.stems) if (s.label) s.label.remove();
      state.stems = stems.map((s) => ({ ...s }));
      for (const s of state.stems) {
        const el = document.createElement('div');
        el.className = 'stem-label';
        el.textContent = s.text;
        el.dataset.stem = String(s.id);
        el.addEventListener('click', (ev) => { ev.stopPropagation(); select(s.id, true); });
        labelLayer.appendChild(el);
        s.label = el;
      }
      rebuildLines();
    }

    function select(id, fromUser) {
      state.selected = id;
      rebuildLines();
      const s = state.stems.find((x) => x.id === id);
      if (s && fromUser && options.onStemClick) options.onStemClick(s);
    }

    // ------------------------------------------------------------ content

    let texInfo = null;
    function setSplats(splats) {
      state.splats = splats;
      state.order = null;
      state.lastSortView = null;
      texInfo = packTexture(splats);
      gl.bindTexture(gl.TEXTURE_2D, texture);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32UI, texInfo.width, texInfo.height, 0, gl.RGBA_INTEGER, gl.UNSIGNED_INT, texInfo.data);
      state.dirty = true;
    }

    /** Frames the scene: robust bounds (2nd–98th percentile) so stray points do not matter. */
    function frame() {
      const s = state.splats;
      if (!s || !s.count) return;
      const step = Math.max(1, Math.floor(s.count / 50000));
      const axes = [[], [], []];
      for (let i = 0; i < s.count; i += step) for (let k = 0; k < 3; k++) axes[k].push(s.positions[3 * i + k]);
      const lo = [], hi = [];
      for (let k = 0; k < 3; k++) {
        const a = axes[k].sort((x, y) => x - y);
        lo.push(a[Math.floor(0.02 * (a.length - 1))]);
        hi.push(a[Math.ceil(0.98 * (a.length - 1))]);
      }
      const size = Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) || 1;
      state.target = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2] + 0.3 * (hi[2] - lo[2])];
      state.distance = 0.42 * size / Math.tan(0.5 * state.fovy);
      state.azimuth = -Math.PI / 3;
      state.elevation = 0.55;
      state.home = { target: [...state.target], distance: state.distance };
      state.dirty = true;
    }

    // ------------------------------------------------------------ controls

    let drag = null;
    const pointers = new Map();
    canvas.addEventListener('contextmenu', (e) => e.preventDefault());
    canvas.addEventListener('pointerdown', (e) => {
      canvas.setPointerCapture(e.pointerId);
      pointers.set(e.pointerId, [e.clientX, e.clientY]);
      drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey, moved: 0 };
    });
    canvas.addEventListener('pointermove', (e) => {
      if (!drag || !pointers.has(e.pointerId)) return;
      const prev = pointers.get(e.pointerId);
      pointers.set(e.pointerId, [e.clientX, e.clientY]);
      if (pointers.size === 2) {
        const [a, b] = [...pointers.values()];
        const other = [...pointers.entries()].find(([id]) => id !== e.pointerId)[1];
        const before = Math.hypot(prev[0] - other[0], prev[1] - other[1]);
        const after = Math.hypot(a[0] - b[0], a[1] - b[1]);
        if (before > 0 && after > 0) zoom(before / after);
        return;
      }
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY;
      drag.moved += Math.abs(dx) + Math.abs(dy);
      if (drag.pan) pan(dx, dy);
      else {
        state.azimuth -= dx * 0.008;
        state.elevation = Math.min(1.5, Math.max(-0.2, state.elevation + dy * 0.008));
      }
      state.dirty = true;
    });
    const up = (e) => {
      pointers.delete(e.pointerId);
      if (drag && drag.moved < 4 && e.type === 'pointerup') clickAt(e);
      if (!pointers.size) drag = null;
      state.lastSortTime = 0;
      state.dirty = true;
    };
    canvas.addEventListener('pointerup', up);
    canvas.addEventListener('pointercancel', up);
    canvas.addEventListener('wheel', (e) => { e.preventDefault(); zoom(Math.exp(e.deltaY * 0.0015)); }, { passive: false });

    function zoom(k) {
      state.distance = Math.min(5000, Math.max(0.2, state.distance * k));
      state.dirty = true;
    }
    function pan(dx, dy) {
      const cam = camera();
      const k = state.distance / cam.focal[1] * (canvas.width / (canvas.clientWidth || canvas.width));
      const v = cam.view; // rows: r = (v0, v4, v8), d = (v1, v5, v9)
      for (let i = 0; i < 3; i++) state.target[i] -= k * (dx * v[4 * i] + dy * v[4 * i + 1]);
    }
    /** A click near a stem's 1.3 m point selects it. */
    function clickAt(e) {
      const rect = canvas.getBoundingClientRect();
      const x = e.clientX - rect.left, y = e.clientY - rect.top;
      const cam = camera();
      let best = null, bestD = 24;
      for (const s of state.stems) {
        const p = project(cam, s.slice);
        if (!p) continue;
        const d = Math.hypot(p[0] - x, p[1] - y);
        if (d < bestD) { bestD = d; best = s; }
      }
      if (best) select(best.id, true);
    }

    const resizeObserver = new ResizeObserver(() => { state.dirty = true; });
    resizeObserver.observe(canvas);

    return {
      setSplats, setStems, frame, select: (id) => select(id, false),
      setScale(k) { state.scale = k; state.dirty = true; },
      /** Calls `fn(camera)` after each drawn frame (a tile streamer picks its tiles from it). */
      onView(fn) { state.onView = fn; state.dirty = true; },
      /** The camera as the next frame draws it: {view, eye, f, focal, viewport}. */
      camera,
      /** Sets the orbit camera: any of {target: [x, y, z], distance (m), azimuth, elevation (rad)}. */
      setCamera(c) {
        if (c.target) state.target = [...c.target];
        if (c.distance > 0) state.distance = c.distance;
        if (Number.isFinite(c.azimuth)) state.azimuth = c.azimuth;
        if (Number.isFinite(c.elevation)) state.elevation = c.elevation;
        state.dirty = true;
      },
      setStemsVisible(v) { state.stemsVisible = v; state.dirty = true; },
      reset() { if (state.home) { state.target = [...state.home.target]; state.distance = state.home.distance; state.azimuth = -Math.PI / 3; state.elevation = 0.55; state.dirty = true; } },
      /** Looks at a stem from close by. */
      focus(id) {
        const s = state.stems.find((x) => x.id === id);
        if (!s) return;
        state.target = [...s.slice];
        state.distance = Math.max(3, 12 * s.radius + 4);
        state.dirty = true;
      },
      get splats() { return state.splats; },
      get frames() { return state.frames; },
      /** Draws now and counts pixels that differ from the background (for tests and checks). */
      drawnPixels() {
        draw();
        const w = canvas.width, h = canvas.height, px = new Uint8Array(4 * w * h);
        gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
        const bg = BACKGROUND.map((c) => Math.round(c * 255));
        let n = 0;
        for (let i = 0; i < w * h; i++) {
          if (Math.abs(px[4 * i] - bg[0]) + Math.abs(px[4 * i + 1] - bg[1]) + Math.abs(px[4 * i + 2] - bg[2]) > 12) n++;
        }
        return { drawn: n, total: w * h };
      },
      destroy() {
        state.destroyed = true;
        resizeObserver.disconnect();
        for (const s of state.stems) if (s.label) s.label.remove();
        const lose = gl.getExtension('WEBGL_lose_context');
        if (lose) lose.loseContext();
      },
    };
  }

  return { parseSplat, parsePly, pointsToSplats, packTexture, toHalf, create };
})();
window.SylvaViewer = SylvaViewer;
