//! The splats as glTF 2.0 binary (`.glb`) with Khronos's `KHR_gaussian_splatting` extension
//! (release candidate, KhronosGroup/glTF `extensions/2.0/Khronos/KHR_gaussian_splatting`,
//! read 2026-11-28): one mesh with one `POINTS` primitive whose attributes are
//!
//! | attribute | accessor | from our model |
//! |---|---|---|
//! | `POSITION` | VEC3 float, with min and max | the mean, metres |
//! | `KHR_gaussian_splatting:ROTATION` | VEC4 float, unit quaternion (x, y, z, w) | `rotations` (w, x, y, z), normalised |
//! | `KHR_gaussian_splatting:SCALE` | VEC3 float, linear | exp(`log_scales`) |
//! | `KHR_gaussian_splatting:OPACITY` | SCALAR float in [0, 1] | sigmoid(`opacity_logits`) |
//! | `KHR_gaussian_splatting:SH_DEGREE_0_COEF_0` | VEC3 float | the DC coefficients |
//! | `KHR_gaussian_splatting:SH_DEGREE_l_COEF_n` | VEC3 float, l = 1 … the model's degree, n = 0 … 2l | coefficient l² + n |
//! | `COLOR_0` | VEC4 unsigned byte, normalised | the fallback colour: SH_C0 · DC + 0.5 clamped, sRGB decoded to linear, and the opacity |
//! | `_TRUNK_PROB` | SCALAR float | `trunk_prob` (an application attribute: glTF's leading underscore) |
//!
//! Our SH basis is the reference trainer's, which is the extension's: real harmonics with the
//! Condon–Shortley phase, coefficients of each degree from m = −l to m = l, the colour
//! `SH · Y + 0.5`. The colours are the photos' own values, so the colour space is
//! `srgb_rec709_display`. The kernel is `ellipse` (the 3σ Gaussian of the reference), the
//! projection `perspective`, the sorting `cameraDistance` (the extension's defaults, written
//! out).
//!
//! Axes: the model's frame is metric with z up; glTF's is y up. The mesh keeps the model's
//! coordinates and its node carries the rotation from z up to y up (x stays, y → −z, z → y),
//! which a client composes with the splats' covariance as the extension's "Splat
//! Reconstruction" says. A 3D Tiles client turns glTF content from y up back to z up, so the
//! same file stands upright in both.
//!
//! With SPZ compression ([`write_glb_spz`]), the draft `KHR_gaussian_splatting_compression_spz_2`
//! (KhronosGroup/glTF commit 90db9264, read 2026-11-28): the primitive's accessors keep their
//! types and counts but no buffer view, and the extension's `bufferView` holds one SPZ v2
//! stream ([`crate::splat::export_spz`]) of the mesh's coordinates, packed for glTF's
//! left-up-front axes: SPZ stores right-up-back, so x and z change sign (a half turn about y:
//! quaternion (w, −x, y, −z), and each SH coefficient the sign its basis function takes under
//! the turn). As the draft's example, the opacity rides in `COLOR_0`'s alpha and the DC term
//! in its colour, so there is no `OPACITY` or degree-0 attribute. CesiumJS (1.140) renders
//! splats in 3D Tiles only in this form.
//!
//! Written by hand with `serde_json`: the `gltf` crate's `Semantic` (gltf-json 1.4) has no
//! variant for extension-prefixed semantics such as `KHR_gaussian_splatting:SCALE`, so it can
//! neither write nor read these primitives. The reader here reads what the writer writes
//! (float accessors, tightly packed), for round trips and tests; it refuses what it does not
//! read with the reason.

use std::io::{self, Read, Write};

use serde_json::{Value, json};

use crate::splat::model::{Gaussians, MAX_SH_DEGREE, SH_C0, SH_FLOATS, sigmoid};

/// The extension's name, as `extensionsUsed` and the attribute prefixes spell it.
pub const EXTENSION: &str = "KHR_gaussian_splatting";
/// "glTF", little-endian (GLB header magic).
const GLB_MAGIC: u32 = 0x4654_6C67;
/// Chunk types: "JSON" and "BIN\0", little-endian.
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;
/// Accessor component types (glTF 2.0 §3.6.2.2).
const FLOAT: u32 = 5126;
const UNSIGNED_BYTE: u32 = 5121;
/// `bufferView.target` of vertex attributes.
const ARRAY_BUFFER: u32 = 34962;
/// The node's matrix, column-major: the model's z-up frame into glTF's y-up one.
pub const Z_UP_TO_Y_UP: [f64; 16] = [
    1.0, 0.0, 0.0, 0.0, //
    0.0, 0.0, -1.0, 0.0, //
    0.0, 1.0, 0.0, 0.0, //
    0.0, 0.0, 0.0, 1.0,
];

/// What [`read_glb`] refuses.
#[derive(Debug, thiserror::Error)]
pub enum GlbError {
    #[error(transparent)]
    Io(#[from] io::Error),
    #[error("not a glTF binary (bad magic or version)")]
    NotGlb,
    #[error("malformed glTF binary: {0}")]
    Malformed(String),
    #[error("unsupported glTF content: {0}")]
    Unsupported(String),
}

/// The attribute semantic of SH degree `l`, coefficient `n` (n = 0 … 2l).
pub fn sh_semantic(l: u32, n: u32) -> String {
    format!("{EXTENSION}:SH_DEGREE_{l}_COEF_{n}")
}

/// sRGB-encoded value in [0, 1] to linear (IEC 61966-2-1), for `COLOR_0`, which glTF defines
/// as linear.
fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// One attribute's accessor before it is laid out: semantic, accessor type, component type,
/// normalised, its bytes, and min/max for `POSITION`.
struct Attribute {
    semantic: String,
    kind: &'static str,
    component: u32,
    normalized: bool,
    bytes: Vec<u8>,
    bounds: Option<([f32; 3], [f32; 3])>,
}

fn floats(semantic: String, kind: &'static str, values: impl Iterator<Item = f32>) -> Attribute {
    Attribute {
        semantic,
        kind,
        component: FLOAT,
        normalized: false,
        bytes: values.flat_map(f32::to_le_bytes).collect(),
        bounds: None,
    }
}

/// The primitive's attributes for `g` (see the module doc).
fn attributes(g: &Gaussians) -> Vec<Attribute> {
    let mut position = floats("POSITION".into(), "VEC3", g.means.iter().flatten().copied());
    position.bounds = g.bounds();
    let rotation = floats(
        format!("{EXTENSION}:ROTATION"),
        "VEC4",
        g.rotations.iter().flat_map(|q| {
            let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
            let [w, x, y, z] = if n > 0.0 && n.is_finite() {
                q.map(|v| v / n)
            } else {
                [1.0, 0.0, 0.0, 0.0]
            };
            [x, y, z, w]
        }),
    );
    let scale = floats(
        format!("{EXTENSION}:SCALE"),
        "VEC3",
        g.log_scales.iter().flatten().map(|s| s.exp()),
    );
    let opacity = floats(
        format!("{EXTENSION}:OPACITY"),
        "SCALAR",
        g.opacity_logits.iter().map(|&o| sigmoid(o)),
    );
    let mut out = vec![position, rotation, scale, opacity];
    let degree = g.sh_degree.min(MAX_SH_DEGREE);
    for l in 0..=degree {
        for n in 0..=2 * l {
            let k = (l * l + n) as usize;
            out.push(floats(
                sh_semantic(l, n),
                "VEC3",
                g.sh.iter()
                    .flat_map(move |sh| [sh[3 * k], sh[3 * k + 1], sh[3 * k + 2]]),
            ));
        }
    }
    let colour: Vec<u8> =
        g.sh.iter()
            .zip(&g.opacity_logits)
            .flat_map(|(sh, &o)| {
                let c = |k: usize| srgb_to_linear((SH_C0 * sh[k] + 0.5).clamp(0.0, 1.0));
                [c(0), c(1), c(2), sigmoid(o)].map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            })
            .collect();
    out.push(Attribute {
        semantic: "COLOR_0".into(),
        kind: "VEC4",
        component: UNSIGNED_BYTE,
        normalized: true,
        bytes: colour,
        bounds: None,
    });
    out.push(floats(
        "_TRUNK_PROB".into(),
        "SCALAR",
        g.trunk_prob.iter().copied(),
    ));
    out
}

/// What a splat document holds beside its node: the primitive's attributes (semantic →
/// accessor), the accessors and buffer views, the buffer's length (bytes), and whether the
/// data is one SPZ stream (the extension's `bufferView` 0).
struct SplatParts {
    attributes: serde_json::Map<String, Value>,
    accessors: Vec<Value>,
    views: Vec<Value>,
    bin_len: usize,
    spz: bool,
}

/// The glTF JSON of one splat primitive in one node carrying `matrix`, the asset `extras`.
fn splat_document(parts: &SplatParts, matrix: &[f64; 16], extras: Value) -> Value {
    let mut ext = json!({
        "kernel": "ellipse",
        "colorSpace": "srgb_rec709_display",
        "projection": "perspective",
        "sortingMethod": "cameraDistance",
    });
    let mut doc = json!({
        "asset": {
            "version": "2.0",
            "generator": concat!("Sylva ", env!("CARGO_PKG_VERSION")),
            "extras": extras,
        },
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": [{ "mesh": 0, "matrix": matrix }],
        "buffers": [{ "byteLength": parts.bin_len }],
        "bufferViews": parts.views,
        "accessors": parts.accessors,
    });
    if parts.spz {
        ext["extensions"] = json!({ SPZ_EXTENSION: { "bufferView": 0 } });
        doc["extensionsUsed"] = json!([EXTENSION, SPZ_EXTENSION]);
        doc["extensionsRequired"] = json!([EXTENSION, SPZ_EXTENSION]);
    }
    doc["meshes"] = json!([{
        "primitives": [{ "mode": 0, "attributes": parts.attributes, "extensions": { EXTENSION: ext } }]
    }]);
    doc
}

/// The glTF JSON and binary buffer of `g`, its node carrying `matrix` (column-major; e.g.
/// [`Z_UP_TO_Y_UP`]) and `extras` on the asset (free-form: Sylva puts the frame there).
pub fn gltf_parts(g: &Gaussians, matrix: &[f64; 16], extras: Value) -> (Value, Vec<u8>) {
    let mut bin = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut attrs = serde_json::Map::new();
    for (i, a) in attributes(g).into_iter().enumerate() {
        // Every view starts on a 4-byte boundary, as vertex attributes must.
        while bin.len() % 4 != 0 {
            bin.push(0);
        }
        views.push(json!({
            "buffer": 0,
            "byteOffset": bin.len(),
            "byteLength": a.bytes.len(),
            "target": ARRAY_BUFFER,
        }));
        bin.extend_from_slice(&a.bytes);
        let mut acc = json!({
            "bufferView": i,
            "componentType": a.component,
            "count": g.len(),
            "type": a.kind,
        });
        if a.normalized {
            acc["normalized"] = json!(true);
        }
        if let Some((lo, hi)) = a.bounds {
            acc["min"] = json!(lo);
            acc["max"] = json!(hi);
        }
        accessors.push(acc);
        attrs.insert(a.semantic, json!(i));
    }
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let doc = splat_document(
        &SplatParts {
            attributes: attrs,
            accessors,
            views,
            bin_len: bin.len(),
            spz: false,
        },
        matrix,
        extras,
    );
    (doc, bin)
}

/// Writes `doc` and `bin` as a GLB: the 12-byte header, the JSON chunk padded with spaces and
/// the binary chunk padded with zeros, each to 4 bytes (glTF 2.0 §4.4).
pub fn write_glb_parts<W: Write>(mut out: W, doc: &Value, bin: &[u8]) -> io::Result<()> {
    let mut json = serde_json::to_vec(doc).map_err(io::Error::other)?;
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let pad = (4 - bin.len() % 4) % 4;
    let bin_len = bin.len() + pad;
    let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin_len };
    let total =
        u32::try_from(total).map_err(|_| io::Error::other("a glTF binary holds at most 4 GiB"))?;
    out.write_all(&GLB_MAGIC.to_le_bytes())?;
    out.write_all(&2u32.to_le_bytes())?;
    out.write_all(&total.to_le_bytes())?;
    out.write_all(&(json.len() as u32).to_le_bytes())?;
    out.write_all(&CHUNK_JSON.to_le_bytes())?;
    out.write_all(&json)?;
    if !bin.is_empty() {
        out.write_all(&(bin_len as u32).to_le_bytes())?;
        out.write_all(&CHUNK_BIN.to_le_bytes())?;
        out.write_all(bin)?;
        out.write_all(&[0; 3][..pad])?;
    }
    Ok(())
}

/// Writes `g` as a `.glb` in the model's frame, its node turning z up into glTF's y up.
pub fn write_glb<W: Write>(out: W, g: &Gaussians) -> io::Result<()> {
    let (doc, bin) = gltf_parts(g, &Z_UP_TO_Y_UP, json!({ "frame": "local, z up" }));
    write_glb_parts(out, &doc, &bin)
}

/// The draft SPZ compression extension nested in `KHR_gaussian_splatting`.
pub const SPZ_EXTENSION: &str = "KHR_gaussian_splatting_compression_spz_2";

/// Sign each SH coefficient (index k = 0 … 15, l² + l + m) takes under the half turn about y
/// that swaps glTF's left-up-front and SPZ's right-up-back axes: (x, y, z) → (−x, y, −z).
const HALF_TURN_Y_SH: [f32; 16] = [
    1.0, // 1
    1.0, -1.0, -1.0, // y, z, x
    -1.0, -1.0, 1.0, 1.0, 1.0, // xy, yz, 3z²−1, xz, x²−y²
    1.0, 1.0, 1.0, -1.0, -1.0, -1.0,
    -1.0, // y(3x²−y²), xyz, y(5z²−1), z(5z²−3), x(5z²−1), z(x²−y²), x(x²−3y²)
];

/// `g` turned half a turn about y (its own inverse): the mesh's coordinates as SPZ stores them
/// for glTF, and back.
pub fn half_turn_y(g: &Gaussians) -> Gaussians {
    let mut out = g.clone();
    for m in &mut out.means {
        *m = [-m[0], m[1], -m[2]];
    }
    for q in &mut out.rotations {
        *q = [q[0], -q[1], q[2], -q[3]];
    }
    for sh in &mut out.sh {
        for (k, sign) in HALF_TURN_Y_SH.iter().enumerate() {
            for c in 0..3 {
                sh[3 * k + c] *= sign;
            }
        }
    }
    out
}

/// The glTF JSON and binary buffer of `g` with SPZ compression (see the module doc), its
/// node carrying `matrix` and the asset `extras`.
pub fn gltf_parts_spz(
    g: &Gaussians,
    matrix: &[f64; 16],
    extras: Value,
) -> io::Result<(Value, Vec<u8>)> {
    let mut bin = Vec::new();
    crate::splat::export_spz::write_spz(&mut bin, &half_turn_y(g))?;
    let spz_len = bin.len();
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let bounds = g.bounds();
    let mut accessors = Vec::new();
    let mut attrs = serde_json::Map::new();
    let mut add = |semantic: String, kind: &str, component: u32| {
        let mut acc = json!({ "componentType": component, "count": g.len(), "type": kind });
        if component == UNSIGNED_BYTE {
            acc["normalized"] = json!(true);
        }
        if let Some((lo, hi)) = bounds.filter(|_| semantic == "POSITION") {
            acc["min"] = json!(lo);
            acc["max"] = json!(hi);
        }
        attrs.insert(semantic, json!(accessors.len()));
        accessors.push(acc);
    };
    add("POSITION".into(), "VEC3", FLOAT);
    add("COLOR_0".into(), "VEC4", UNSIGNED_BYTE);
    add(format!("{EXTENSION}:SCALE"), "VEC3", FLOAT);
    add(format!("{EXTENSION}:ROTATION"), "VEC4", FLOAT);
    for l in 1..=g.sh_degree.min(MAX_SH_DEGREE) {
        for n in 0..=2 * l {
            add(sh_semantic(l, n), "VEC3", FLOAT);
        }
    }
    let doc = splat_document(
        &SplatParts {
            attributes: attrs,
            accessors,
            views: vec![json!({ "buffer": 0, "byteOffset": 0, "byteLength": spz_len })],
            bin_len: bin.len(),
            spz: true,
        },
        matrix,
        extras,
    );
    Ok((doc, bin))
}

/// Writes `g` as an SPZ-compressed `.glb` in the model's frame, its node turning z up into
/// glTF's y up.
pub fn write_glb_spz<W: Write>(out: W, g: &Gaussians) -> io::Result<()> {
    let (doc, bin) = gltf_parts_spz(g, &Z_UP_TO_Y_UP, json!({ "frame": "local, z up" }))?;
    write_glb_parts(out, &doc, &bin)
}

/// Splits a GLB into its JSON and binary chunk.
pub fn read_glb_parts<R: Read>(mut input: R) -> Result<(Value, Vec<u8>), GlbError> {
    let mut bytes = Vec::new();
    input.read_to_end(&mut bytes)?;
    let word = |at: usize| -> Result<u32, GlbError> {
        bytes
            .get(at..at + 4)
            .and_then(|b| b.try_into().ok())
            .map(u32::from_le_bytes)
            .ok_or_else(|| GlbError::Malformed(format!("truncated at byte {at}")))
    };
    if word(0)? != GLB_MAGIC || word(4)? != 2 {
        return Err(GlbError::NotGlb);
    }
    let (mut at, mut doc, mut bin) = (12usize, None, Vec::new());
    while at + 8 <= bytes.len() {
        let len = word(at)? as usize;
        let kind = word(at + 4)?;
        let body = bytes
            .get(at + 8..at + 8 + len)
            .ok_or_else(|| GlbError::Malformed(format!("chunk at byte {at} runs past the end")))?;
        match kind {
            CHUNK_JSON => {
                doc = Some(
                    serde_json::from_slice(body)
                        .map_err(|e| GlbError::Malformed(format!("JSON chunk: {e}")))?,
                )
            }
            CHUNK_BIN => bin = body.to_vec(),
            _ => {}
        }
        at += 8 + len;
    }
    let doc = doc.ok_or_else(|| GlbError::Malformed("no JSON chunk".into()))?;
    Ok((doc, bin))
}

/// Reads the splats of the first primitive with `KHR_gaussian_splatting` in a GLB that
/// [`write_glb`] (or a writer with the same float accessors) made, in the mesh's own frame.
pub fn read_glb<R: Read>(input: R) -> Result<Gaussians, GlbError> {
    let (doc, bin) = read_glb_parts(input)?;
    let prim = doc["meshes"]
        .as_array()
        .into_iter()
        .flatten()
        .flat_map(|m| m["primitives"].as_array().into_iter().flatten())
        .find(|p| p["extensions"].get(EXTENSION).is_some())
        .ok_or_else(|| GlbError::Unsupported(format!("no primitive with {EXTENSION}")))?;
    if let Some(view) = prim["extensions"][EXTENSION]["extensions"][SPZ_EXTENSION]
        .get("bufferView")
        .and_then(Value::as_u64)
    {
        let view = &doc["bufferViews"][view as usize];
        let start = view["byteOffset"].as_u64().unwrap_or(0) as usize;
        let len = view["byteLength"].as_u64().unwrap_or(0) as usize;
        let body = bin
            .get(start..start + len)
            .ok_or_else(|| GlbError::Malformed("the SPZ stream runs past the buffer".into()))?;
        let g = crate::splat::export_spz::read_spz(body)
            .map_err(|e| GlbError::Malformed(format!("SPZ stream: {e}")))?;
        return Ok(half_turn_y(&g));
    }
    let attrs = &prim["attributes"];
    let read = |semantic: &str, width: usize| -> Result<Option<Vec<f32>>, GlbError> {
        let Some(index) = attrs.get(semantic).and_then(Value::as_u64) else {
            return Ok(None);
        };
        let acc = &doc["accessors"][index as usize];
        if acc["componentType"].as_u64() != Some(u64::from(FLOAT)) {
            return Err(GlbError::Unsupported(format!(
                "{semantic}: only float accessors are read"
            )));
        }
        let view = &doc["bufferViews"][acc["bufferView"].as_u64().unwrap_or(u64::MAX) as usize];
        if view
            .get("byteStride")
            .is_some_and(|s| s.as_u64() != Some(4 * width as u64))
        {
            return Err(GlbError::Unsupported(format!(
                "{semantic}: interleaved views are not read"
            )));
        }
        let count = acc["count"].as_u64().unwrap_or(0) as usize;
        let start = view["byteOffset"].as_u64().unwrap_or(0) as usize
            + acc["byteOffset"].as_u64().unwrap_or(0) as usize;
        let len = count * width * 4;
        let body = bin
            .get(start..start + len)
            .ok_or_else(|| GlbError::Malformed(format!("{semantic}: data past the buffer")))?;
        Ok(Some(
            body.chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
        ))
    };
    let need = |semantic: &str, width: usize| {
        read(semantic, width)?
            .ok_or_else(|| GlbError::Malformed(format!("the primitive has no {semantic}")))
    };
    let pos = need("POSITION", 3)?;
    let n = pos.len() / 3;
    let rot = need(&format!("{EXTENSION}:ROTATION"), 4)?;
    let scale = need(&format!("{EXTENSION}:SCALE"), 3)?;
    let opacity = need(&format!("{EXTENSION}:OPACITY"), 1)?;
    let mut sh = vec![[0.0f32; SH_FLOATS]; n];
    let mut degree = 0;
    for l in 0..=MAX_SH_DEGREE {
        let mut coefs = Vec::new();
        for k in 0..=2 * l {
            match read(&sh_semantic(l, k), 3)? {
                Some(c) => coefs.push(c),
                None => break,
            }
        }
        if coefs.is_empty() && l > 0 {
            break;
        }
        if coefs.len() != (2 * l + 1) as usize {
            return Err(GlbError::Malformed(format!(
                "SH degree {l} is partly defined ({} of {} coefficients)",
                coefs.len(),
                2 * l + 1
            )));
        }
        for (k, c) in coefs.iter().enumerate() {
            let slot = (l * l) as usize + k;
            for (i, row) in sh.iter_mut().enumerate() {
                row[3 * slot..3 * slot + 3].copy_from_slice(&c[3 * i..3 * i + 3]);
            }
        }
        degree = l;
    }
    let trunk = read("_TRUNK_PROB", 1)?.unwrap_or_else(|| vec![0.0; n]);
    let lengths = [rot.len() / 4, scale.len() / 3, opacity.len(), trunk.len()];
    if lengths.iter().any(|&l| l != n) {
        return Err(GlbError::Malformed(format!(
            "attribute counts differ: {n} positions, {lengths:?}"
        )));
    }
    Ok(Gaussians {
        means: pos.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        log_scales: scale
            .chunks_exact(3)
            .map(|c| [c[0].ln(), c[1].ln(), c[2].ln()])
            .collect(),
        rotations: rot
            .chunks_exact(4)
            .map(|c| [c[3], c[0], c[1], c[2]])
            .collect(),
        opacity_logits: opacity
            .iter()
            .map(|&a| {
                let a = a.clamp(1e-7, 1.0 - 1e-7);
                (a / (1.0 - a)).ln()
            })
            .collect(),
        sh,
        trunk_prob: trunk,
        sh_degree: degree,
    })
}

#[cfg(test)]
#[path = "export_gltf_tests.rs"]
mod tests;
