// Sylva's 3D Tiles streamer for the splat viewer: reads a 3D Tiles 1.1 tileset whose tiles are
// glTF Gaussian splats (`KHR_gaussian_splatting`, plain or SPZ-compressed with
// `KHR_gaussian_splatting_compression_spz_2`, as stage export writes them) and keeps in the
// viewer the tiles the current view needs, fetching them as the view changes.
//
// Level of detail (3D Tiles 1.1 §"Geometric error"): a tile's screen-space error is its
// geometric error (metres) times the focal length (pixels) over its distance from the eye; a
// tile whose error exceeds `maxError` pixels (16 by default, CesiumJS's default) and has
// children is replaced by them (`refine: REPLACE`) once they have all arrived, and drawn
// itself until then. Tiles wholly behind the eye or outside the field of view are skipped.
// Fetched tiles stay cached up to `cacheSplats` Gaussians; past that the least recently drawn
// are dropped and fetched again when needed.
//
// Frame: the tileset's local frame (z up, metres). The root's transform, which places that
// frame on the Earth (ECEF), is not applied: the page shows the plot in its own metres, as
// it shows the splat file.
//
// Decoding: the GLB container (glTF 2.0 §4.4), the node hierarchy's matrices (or TRS), then the
// 3D Tiles turn from glTF's y up to z up. SPZ (version 2): a gzip stream (unpacked with the
// browser's DecompressionStream) of a 16-byte header and per-attribute arrays: positions as
// 24-bit fixed point, alphas, colours (DC term × 0.15 + 0.5), log-scales ((v + 10) × 16),
// rotations (x, y, z as v × 127.5 + 127.5, w ≥ 0 derived) — the layout Sylva's writer and
// Niantic's format description give; the extension stores SPZ in SPZ's own axes, a half turn
// about y from glTF's.
'use strict';

const SylvaTiles = (() => {
  const GLB_MAGIC = 0x46546c67, CHUNK_JSON = 0x4e4f534a, CHUNK_BIN = 0x004e4942;
  const EXT = 'KHR_gaussian_splatting', SPZ_EXT = 'KHR_gaussian_splatting_compression_spz_2';
  const SPZ_MAGIC = 0x5053474e;
  const SH_C0 = 0.28209479177387814;
  /** 3D Tiles' turn of glTF content from y up to z up (column-major). */
  const Y_UP_TO_Z_UP = [1, 0, 0, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 0, 0, 1];
  /** SPZ's axes against glTF's: a half turn about y (column-major). */
  const HALF_TURN_Y = [-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1];
  const IDENTITY = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];

  // ------------------------------------------------------------ small maths

  function mul(a, b) {
    const o = new Array(16).fill(0);
    for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[4 * k + r] * b[4 * c + k];
      o[4 * c + r] = s;
    }
    return o;
  }

  /** A glTF node's local matrix: `matrix`, else translation · rotation · scale. */
  function nodeMatrix(n) {
    if (Array.isArray(n.matrix) && n.matrix.length === 16) return n.matrix.map(Number);
    const [tx, ty, tz] = n.translation || [0, 0, 0];
    const [x, y, z, w] = n.rotation || [0, 0, 0, 1];
    const [sx, sy, sz] = n.scale || [1, 1, 1];
    return [
      (1 - 2 * (y * y + z * z)) * sx, 2 * (x * y + z * w) * sx, 2 * (x * z - y * w) * sx, 0,
      2 * (x * y - z * w) * sy, (1 - 2 * (x * x + z * z)) * sy, 2 * (y * z + x * w) * sy, 0,
      2 * (x * z + y * w) * sz, 2 * (y * z - x * w) * sz, (1 - 2 * (x * x + y * y)) * sz, 0,
      tx, ty, tz, 1,
    ];
  }

  /** The rotation (w, x, y, z) and uniform scale of a similarity's 3×3 part (column-major 4×4). */
  function similarity(m) {
    const col = (c) => [m[4 * c], m[4 * c + 1], m[4 * c + 2]];
    const s = Math.cbrt(Math.abs(
      m[0] * (m[5] * m[10] - m[9] * m[6]) - m[4] * (m[1] * m[10] - m[9] * m[2]) + m[8] * (m[1] * m[6] - m[5] * m[2]))) || 1;
    const [c0, c1, c2] = [col(0), col(1), col(2)].map((v) => v.map((x) => x / s));
    // R[r][c] = c_c[r]; Shepperd's method.
    const r00 = c0[0], r11 = c1[1], r22 = c2[2], tr = r00 + r11 + r22;
    let w, x, y, z;
    if (tr > 0) {
      const k = 2 * Math.sqrt(tr + 1);
      w = k / 4; x = (c1[2] - c2[1]) / k; y = (c2[0] - c0[2]) / k; z = (c0[1] - c1[0]) / k;
    } else if (r00 > r11 && r00 > r22) {
      const k = 2 * Math.sqrt(1 + r00 - r11 - r22);
      w = (c1[2] - c2[1]) / k; x = k / 4; y = (c1[0] + c0[1]) / k; z = (c2[0] + c0[2]) / k;
    } else if (r11 > r22) {
      const k = 2 * Math.sqrt(1 + r11 - r00 - r22);
      w = (c2[0] - c0[2]) / k; x = (c1[0] + c0[1]) / k; y = k / 4; z = (c2[1] + c1[2]) / k;
    } else {
      const k = 2 * Math.sqrt(1 + r22 - r00 - r11);
      w = (c0[1] - c1[0]) / k; x = (c2[0] + c0[2]) / k; y = (c2[1] + c1[2]) / k; z = k / 4;
    }
    return { q: [w, x, y, z], s };
  }

  /** Applies the similarity `m` to splats in place (positions, rotations, scales). */
  function transform(sp, m) {
    const { q, s } = similarity(m);
    const [aw, ax, ay, az] = q;
    const p = sp.positions, r = sp.rotations;
    for (let i = 0; i < sp.count; i++) {
      const x = p[3 * i], y = p[3 * i + 1], z = p[3 * i + 2];
      p[3 * i] = m[0] * x + m[4] * y + m[8] * z + m[12];
      p[3 * i + 1] = m[1] * x + m[5] * y + m[9] * z + m[13];
      p[3 * i + 2] = m[2] * x + m[6] * y + m[10] * z + m[14];
      const bw = r[4 * i], bx = r[4 * i + 1], by = r[4 * i + 2], bz = r[4 * i + 3];
      r[4 * i] = aw * bw - ax * bx - ay * by - az * bz;
      r[4 * i + 1] = aw * bx + ax * bw + ay * bz - az * by;
      r[4 * i + 2] = aw * by - ax * bz + ay * bw + az * bx;
      r[4 * i + 3] = aw * bz + ax * by - ay * bx + az * bw;
    }
    if (s !== 1) for (let i = 0; i < sp.scales.length; i++) sp.scales[i] *= s;
    return sp;
  }

  // ------------------------------------------------------------ decoding

  /** Splits a GLB into its JSON document and binary chunk. */
  function splitGlb(buffer) {
    if (!(buffer instanceof ArrayBuffer) || buffer.byteLength < 20) throw new Error('not a GLB file (too short)');
    const v = new DataView(buffer);
    if (v.getUint32(0, true) !== GLB_MAGIC) throw new Error('not a GLB file (no glTF magic)');
    if (v.getUint32(4, true) !== 2) throw new Error(`GLB version ${v.getUint32(4, true)} is not read here (2 only)`);
    let at = 12, doc = null, bin = new Uint8Array(0);
    const end = Math.min(v.getUint32(8, true), buffer.byteLength);
    while (at + 8 <= end) {
      const len = v.getUint32(at, true), type = v.getUint32(at + 4, true);
      if (at + 8 + len > end) throw new Error(`GLB chunk at byte ${at} runs past the file's end`);
      const body = new Uint8Array(buffer, at + 8, len);
      if (type === CHUNK_JSON && !doc) doc = JSON.parse(new TextDecoder().decode(body));
      else if (type === CHUNK_BIN && !bin.byteLength) bin = body;
      at += 8 + len;
    }
    if (!doc) throw new Error('the GLB has no JSON chunk');
    return { doc, bin };
  }

  function viewBytes(doc, bin, index) {
    const bv = (doc.bufferViews || [])[index];
    if (!bv || (bv.buffer || 0) !== 0) throw new Error(`bufferView ${index} is missing or not in the GLB's buffer`);
    const off = bv.byteOffset || 0;
    if (off + bv.byteLength > bin.byteLength) throw new Error(`bufferView ${index} runs past the binary chunk`);
    return { bytes: bin.subarray(off, off + bv.byteLength), stride: bv.byteStride || 0 };
  }

  const COMPONENTS = { SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4 };
  const TYPES = { 5120: [1, 'getInt8', 127], 5121: [1, 'getUint8', 255], 5122: [2, 'getInt16', 32767], 5123: [2, 'getUint16', 65535], 5126: [4, 'getFloat32', 0] };

  /** An accessor's values as floats (normalised integers scaled to 0…1 or −1…1). */
  function accessor(doc, bin, index) {
    const a = (doc.accessors || [])[index];
    if (!a) throw new Error(`accessor ${index} is missing`);
    const n = COMPONENTS[a.type], t = TYPES[a.componentType];
    if (!n || !t) throw new Error(`accessor ${index}: type ${a.type}/${a.componentType} is not read here`);
    if (a.bufferView === undefined) throw new Error(`accessor ${index} has no data`);
    const { bytes, stride } = viewBytes(doc, bin, a.bufferView);
    const [size, get, norm] = t;
    const step = stride || size * n, base = a.byteOffset || 0;
    if (a.count > 0 && base + (a.count - 1) * step + size * n > bytes.byteLength) throw new Error(`accessor ${index} runs past its bufferView`);
    const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    const out = new Float32Array(a.count * n);
    for (let i = 0; i < a.count; i++) for (let k = 0; k < n; k++) {
      let x = dv[get](base + i * step + k * size, true);
      if (norm && a.normalized) x = Math.max(x / norm, -1);
      out[n * i + k] = x;
    }
    return out;
  }

  async function gunzip(bytes) {
    if (typeof DecompressionStream === 'undefined') throw new Error('this browser cannot unpack gzip (no DecompressionStream)');
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('gzip'));
    return new Response(stream).arrayBuffer();
  }

  /** Parses an unpacked SPZ (version 2) into splats in SPZ's own axes. */
  function parseSpz(buffer) {
    const v = new DataView(buffer);
    if (buffer.byteLength < 16 || v.getUint32(0, true) !== SPZ_MAGIC) throw new Error('not an SPZ stream');
    const version = v.getUint32(4, true), count = v.getUint32(8, true);
    const shDegree = v.getUint8(12), frac = v.getUint8(13);
    if (version !== 2) throw new Error(`SPZ version ${version} is not read here (2 only)`);
    if (shDegree > 3) throw new Error(`SPZ SH degree ${shDegree} is over 3`);
    const shBytes = 3 * ((shDegree + 1) ** 2 - 1);
    const need = 16 + count * (9 + 1 + 3 + 3 + 3 + shBytes);
    if (buffer.byteLength < need) throw new Error(`SPZ declares ${count} Gaussians but holds ${buffer.byteLength} of their ${need} bytes`);
    const u = new Uint8Array(buffer);
    const positions = new Float32Array(3 * count), scales = new Float32Array(3 * count);
    const colors = new Uint8Array(4 * count), rotations = new Float32Array(4 * count);
    const unit = 1 / (1 << frac);
    let at = 16;
    for (let i = 0; i < 3 * count; i++, at += 3) {
      let x = u[at] | (u[at + 1] << 8) | (u[at + 2] << 16);
      if (x & 0x800000) x -= 0x1000000;
      positions[i] = x * unit;
    }
    for (let i = 0; i < count; i++) colors[4 * i + 3] = u[at++];
    for (let i = 0; i < count; i++) for (let k = 0; k < 3; k++) {
      const dc = (u[at++] / 255 - 0.5) / 0.15;
      colors[4 * i + k] = Math.max(0, Math.min(255, Math.round((0.5 + SH_C0 * dc) * 255)));
    }
    for (let i = 0; i < 3 * count; i++) scales[i] = Math.exp(u[at++] / 16 - 10);
    for (let i = 0; i < count; i++) {
      const x = u[at] / 127.5 - 1, y = u[at + 1] / 127.5 - 1, z = u[at + 2] / 127.5 - 1;
      at += 3;
      rotations[4 * i] = Math.sqrt(Math.max(0, 1 - x * x - y * y - z * z));
      rotations[4 * i + 1] = x; rotations[4 * i + 2] = y; rotations[4 * i + 3] = z;
    }
    return { count, positions, scales, colors, rotations };
  }

  /** The world matrix of the first node that holds a mesh, walking the default scene. */
  function meshNode(doc) {
    const nodes = doc.nodes || [];
    const scene = (doc.scenes || [])[doc.scene || 0];
    const roots = scene ? scene.nodes || [] : nodes.map((_, i) => i);
    const stack = roots.map((i) => [i, IDENTITY, 0]);
    while (stack.length) {
      const [i, parent, depth] = stack.pop();
      const n = nodes[i];
      if (!n || depth > 64) continue;
      const m = mul(parent, nodeMatrix(n));
      if (n.mesh !== undefined) return { mesh: n.mesh, matrix: m };
      for (const c of n.children || []) stack.push([c, m, depth + 1]);
    }
    throw new Error('the glTF has no node with a mesh');
  }

  /**
   * Parses a glTF splat tile (GLB) into {count, positions, scales, colors, rotations} in the
   * tileset's z-up frame (node matrices and 3D Tiles' y-up turn applied).
   */
  async function parseGlbSplats(buffer) {
    const { doc, bin } = splitGlb(buffer);
    const { mesh, matrix } = meshNode(doc);
    const prim = (((doc.meshes || [])[mesh] || {}).primitives || [])[0];
    const ext = prim && prim.extensions && prim.extensions[EXT];
    if (!ext) throw new Error(`the glTF's mesh has no ${EXT} primitive`);
    const spz = ext.extensions && ext.extensions[SPZ_EXT];
    let sp, m = mul(Y_UP_TO_Z_UP, matrix);
    if (spz) {
      sp = parseSpz(await gunzip(viewBytes(doc, bin, spz.bufferView).bytes));
      m = mul(m, HALF_TURN_Y);
    } else {
      const at = prim.attributes || {};
      const need = (name) => {
        if (at[name] === undefined) throw new Error(`the splat primitive has no ${name}`);
        return accessor(doc, bin, at[name]);
      };
      const positions = need('POSITION');
      const count = positions.length / 3;
      const scales = need(`${EXT}:SCALE`);
      const rot = need(`${EXT}:ROTATION`);
      const opacity = need(`${EXT}:OPACITY`);
      // The view-independent colour: the SH DC term where present (0.5 + C0 · dc, display
      // sRGB as the splats were trained), else COLOR_0, which glTF defines as linear.
      const dcName = `${EXT}:SH_DEGREE_0_COEF_0`;
      const dc = at[dcName] !== undefined ? accessor(doc, bin, at[dcName]) : null;
      const linear = !dc && at.COLOR_0 !== undefined ? accessor(doc, bin, at.COLOR_0) : null;
      const cw = linear ? linear.length / count : 0;
      const toSrgb = (c) => (c <= 0.0031308 ? 12.92 * c : 1.055 * c ** (1 / 2.4) - 0.055);
      const colors = new Uint8Array(4 * count), rotations = new Float32Array(4 * count);
      for (let i = 0; i < count; i++) {
        for (let k = 0; k < 3; k++) {
          const c = dc ? 0.5 + SH_C0 * dc[3 * i + k] : linear ? toSrgb(Math.min(1, Math.max(0, linear[cw * i + k]))) : 0.8;
          colors[4 * i + k] = Math.round(255 * Math.min(1, Math.max(0, c)));
        }
        colors[4 * i + 3] = Math.round(255 * Math.min(1, Math.max(0, opacity[i])));
        // glTF quaternions are (x, y, z, w); the viewer's are (w, x, y, z).
        rotations[4 * i] = rot[4 * i + 3];
        for (let k = 0; k < 3; k++) rotations[4 * i + 1 + k] = rot[4 * i + k];
      }
      sp = { count, positions, scales, colors, rotations };
    }
    return transform(sp, m);
  }

  /** One splat set of several (positions, scales, colours and rotations laid end to end). */
  function concat(parts) {
    const count = parts.reduce((n, p) => n + p.count, 0);
    const out = {
      count, positions: new Float32Array(3 * count), scales: new Float32Array(3 * count),
      colors: new Uint8Array(4 * count), rotations: new Float32Array(4 * count),
    };
    let at = 0;
    for (const p of parts) {
      out.positions.set(p.positions, 3 * at);
      out.scales.set(p.scales, 3 * at);
      out.colors.set(p.colors, 4 * at);
      out.rotations.set(p.rotations, 4 * at);
      at += p.count;
    }
    return out;
  }

  // ------------------------------------------------------------ streaming

  /**
   * Streams the tileset at `url` into `viewer` (a SylvaViewer). `fetchBuffer(href)` fetches
   * with the caller's credentials. Options: `maxError` (pixels, default 16), `cacheSplats`
   * (default 4 000 000), `parallel` (fetches at once, default 4), `onChange(stats)` after each
   * new selection. Resolves once the tileset's JSON is read; tiles follow.
   */
  async function stream(viewer, url, fetchBuffer, options = {}) {
    let maxError = options.maxError ?? 16;
    const cacheSplats = options.cacheSplats ?? 4000000;
    const parallel = options.parallel ?? 4;
    const json = JSON.parse(new TextDecoder().decode(await fetchBuffer(url)));
    if (!json.root) throw new Error('the tileset has no root tile');
    const base = new URL(url, window.location.href);
    const tiles = [];
    function make(t, depth) {
      const b = t.boundingVolume && t.boundingVolume.box;
      if (!Array.isArray(b) || b.length !== 12) throw new Error('a tile without a bounding box (only boxes are read here)');
      const half = [[b[3], b[4], b[5]], [b[6], b[7], b[8]], [b[9], b[10], b[11]]];
      const tile = {
        depth, centre: [b[0], b[1], b[2]], radius: Math.hypot(...half.flat()),
        error: Number(t.geometricError) || 0,
        href: t.content && t.content.uri ? new URL(t.content.uri, base).href : null,
        state: 'none', splats: null, used: 0, children: [],
      };
      tiles.push(tile);
      tile.children = (t.children || []).map((c) => make(c, depth + 1));
      return tile;
    }
    const root = make(json.root, 0);
    const queue = [];
    let active = 0, clock = 0, selected = [], selectedKey = '', destroyed = false, failed = 0, fetched = 0;
    let lastCam = null, pending = false, selectedEye = null;

    const usable = (t) => !t.href || t.state === 'ready' || t.state === 'failed';
    function request(t) {
      if (!t.href || t.state !== 'none') return;
      t.state = 'queued';
      queue.push(t);
      pump();
    }
    function pump() {
      while (active < parallel && queue.length) {
        const t = queue.shift();
        active++;
        t.state = 'loading';
        fetchBuffer(t.href)
          .then(parseGlbSplats)
          .then((sp) => { t.splats = sp; t.state = 'ready'; fetched++; evict(); })
          .catch((e) => { t.state = 'failed'; failed++; console.warn(`tile ${t.href}: ${e.message}`); })
          .finally(() => { active--; pump(); schedule(); });
      }
    }
    function evict() {
      let held = tiles.reduce((n, t) => n + (t.splats ? t.splats.count : 0), 0);
      if (held <= cacheSplats) return;
      const keep = new Set(selected);
      const old = tiles.filter((t) => t.splats && !keep.has(t)).sort((a, b) => a.used - b.used);
      for (const t of old) {
        if (held <= cacheSplats) break;
        held -= t.splats.count;
        t.splats = null;
        t.state = 'none';
      }
    }
    function visible(cam, t) {
      const v = cam.view, c = t.centre;
      const x = v[0] * c[0] + v[4] * c[1] + v[8] * c[2] + v[12];
      const y = v[1] * c[0] + v[5] * c[1] + v[9] * c[2] + v[13];
      const z = v[2] * c[0] + v[6] * c[1] + v[10] * c[2] + v[14];
      if (z < -t.radius) return false;
      const tx = 0.5 * cam.viewport[0] / cam.focal[0], ty = 0.5 * cam.viewport[1] / cam.focal[1];
      // Outside a side plane by more than the radius (the plane's normal has length √(1+t²)).
      return Math.abs(x) - tx * z <= t.radius * Math.hypot(1, tx) && Math.abs(y) - ty * z <= t.radius * Math.hypot(1, ty);
    }
    function screenError(cam, t) {
      const d = Math.hypot(cam.eye[0] - t.centre[0], cam.eye[1] - t.centre[1], cam.eye[2] - t.centre[2]) - t.radius;
      return d <= 0 ? Infinity : t.error * cam.focal[1] / d;
    }
    function select(cam) {
      const out = [];
      const visit = (t) => {
        if (!visible(cam, t)) return;
        if (t.children.length && screenError(cam, t) > maxError) {
          t.children.forEach(request);
          if (t.children.every(usable)) { t.children.forEach(visit); return; }
        }
        if (t.state === 'ready') out.push(t);
        else request(t);
      };
      visit(root);
      return out;
    }
    function update() {
      pending = false;
      if (destroyed || !lastCam) return;
      const now = select(lastCam);
      selectedEye = [...lastCam.eye];
      clock++;
      for (const t of now) t.used = clock;
      const key = now.map((t) => t.href).join('|');
      if (key === selectedKey) return;
      selected = now;
      selectedKey = key;
      const merged = concat(now.map((t) => t.splats));
      viewer.setSplats(merged);
      if (options.onChange) options.onChange(stats(), merged);
    }
    function schedule() {
      if (pending || destroyed) return;
      pending = true;
      setTimeout(update, 60);
    }
    function stats() {
      const depths = selected.map((t) => t.depth);
      return {
        tiles: tiles.length, selected: selected.length, fetched, failed,
        drawn: selected.reduce((n, t) => n + t.splats.count, 0),
        minDepth: depths.length ? Math.min(...depths) : null, maxDepth: depths.length ? Math.max(...depths) : null,
        loading: active + queue.length, maxError, pending,
        // The eye the selection was made for (m, the tileset's frame).
        eye: selectedEye,
      };
    }
    viewer.onView((cam) => { lastCam = cam; schedule(); });
    request(root);
    return {
      stats, root: json,
      /** Sets the screen-space error bound (pixels) and selects again. */
      setMaxError(px) { maxError = px; selectedKey = null; schedule(); },
      destroy() { destroyed = true; viewer.onView(null); },
    };
  }

  return { parseGlbSplats, parseSpz, splitGlb, concat, stream };
})();
window.SylvaTiles = SylvaTiles;
