//! The splats as an OGC 3D Tiles 1.1 tileset of glTF tiles (`KHR_gaussian_splatting` with SPZ
//! compression, [`crate::splat::export_gltf`]), with levels of detail, georeferenced from the
//! job's CRS.
//!
//! **Tree.** An octree over the Gaussians' centres: a node holding more than
//! [`TileParams::max_per_tile`] Gaussians splits into its 8 octants (empty ones dropped), down
//! to [`MAX_DEPTH`]. A leaf's content is its Gaussians as trained. An inner node's content is
//! its Gaussians merged on a grid of cubic cells, the finest grid (cells 1/64 of the node's
//! longest side, then each 2^(1/3) times larger) whose occupied cells number at most `max_per_tile`; children
//! replace it (`refine: REPLACE`). A node's geometric error is the diagonal of its merge cell,
//! the size of the detail merged away (0 for leaves), and a parent's is never below its
//! children's.
//!
//! **Merge.** The Gaussians of a cell become one by matching moments, each weighted by its
//! coverage w = α · A, its opacity α times its mean projected area A = π (s₁s₂ + s₂s₃ + s₁s₃)
//! / 3 (s the axis scales): mean μ = Σ w μᵢ / Σ w, covariance Σ w (Σᵢ + (μᵢ − μ)(μᵢ − μ)ᵀ) / Σ w
//! (whose eigenvectors give the rotation and the square roots of its eigenvalues the scales),
//! SH coefficients and trunk probability the weighted means, and opacity min(0.99, Σ w / A)
//! with A the merged Gaussian's own mean projected area, so that a cell covers about what its
//! Gaussians covered. The idea is that of the hierarchical 3DGS of Kerbl et al. 2024 (merged
//! interior nodes for distant views), with Sylva's own weights.
//!
//! **Coordinates.** Each tile's content is relative to its box centre (its glTF node carries
//! the translation, then the turn from z up to glTF's y up), so float32 holds 0.24 mm steps
//! (SPZ's 12 fraction bits) in tiles of any size. With a CRS the root's `transform` takes the
//! local frame (file coordinates minus the job's offset, metres) to Earth-centred Earth-fixed
//! coordinates (WGS84): the affine map fitted by least squares to 27 points spread over the
//! plot's box, each taken through the CRS to longitude and latitude and then to ECEF with its
//! height as ellipsoidal height (the CRS's vertical datum is not applied); the fit's largest
//! residual is reported (under a millimetre for a plot of a few hundred metres). Without a
//! CRS there is no transform: the tileset stays in the local frame and says so in its
//! `asset.extras`.

use std::collections::HashMap;

use glam::{DMat3, DVec3};
use serde_json::{Value, json};

use crate::splat::export_gltf::{self, EXTENSION, SPZ_EXTENSION, Z_UP_TO_Y_UP};
use crate::splat::model::{Gaussians, SH_FLOATS, sigmoid};

/// Deepest octree level (the root is 0): 2¹² cells of a 100 m plot are 2.4 cm.
pub const MAX_DEPTH: u32 = 12;
/// Highest merged opacity: a merged Gaussian never hides all that is behind it.
const MAX_MERGED_OPACITY: f32 = 0.99;

/// How the tileset is cut.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileParams {
    /// Most Gaussians in one tile: 50 000 (Sylva's choice: 3.2 MB of SPZ at SH degree 3, under
    /// the 5 MB a client should fetch first; CesiumJS ran out of memory at 5 M splats in one
    /// file).
    pub max_per_tile: usize,
}

impl Default for TileParams {
    fn default() -> Self {
        TileParams {
            max_per_tile: 50_000,
        }
    }
}

/// One tree for the tileset's metadata: id, base position in the local frame (metres), DBH (m)
/// and height (m).
#[derive(Debug, Clone, PartialEq)]
pub struct TreeMeta {
    pub id: String,
    pub position: [f64; 3],
    pub dbh_m: f64,
    pub height_m: f64,
}

/// One tile: its path under the tileset's folder and its `.glb` bytes.
pub struct TileFile {
    pub path: String,
    pub glb: Vec<u8>,
}

/// What [`build`] made.
pub struct Tileset {
    /// `tileset.json`.
    pub json: Value,
    pub tiles: Vec<TileFile>,
    /// Tiles per level, root first.
    pub per_level: Vec<usize>,
    /// Gaussians of the root tile (the coarsest level).
    pub root_gaussians: usize,
}

/// An octree node while it is built.
struct Node {
    lo: [f64; 3],
    hi: [f64; 3],
    content: Gaussians,
    geometric_error: f64,
    children: Vec<Node>,
}

fn subset(g: &Gaussians, idx: &[usize]) -> Gaussians {
    Gaussians {
        means: idx.iter().map(|&i| g.means[i]).collect(),
        log_scales: idx.iter().map(|&i| g.log_scales[i]).collect(),
        rotations: idx.iter().map(|&i| g.rotations[i]).collect(),
        opacity_logits: idx.iter().map(|&i| g.opacity_logits[i]).collect(),
        sh: idx.iter().map(|&i| g.sh[i]).collect(),
        trunk_prob: idx.iter().map(|&i| g.trunk_prob[i]).collect(),
        sh_degree: g.sh_degree,
    }
}

/// Mean projected area of an ellipsoid with axis scales `s` (m²), over view directions: π
/// times the mean of the pairwise products (exact for spheres, within 15 % otherwise).
fn mean_area(s: [f64; 3]) -> f64 {
    std::f64::consts::PI * (s[0] * s[1] + s[1] * s[2] + s[0] * s[2]) / 3.0
}

/// The Gaussians `idx` of `g` merged into one (see the module doc).
fn merge_one(
    g: &Gaussians,
    idx: &[usize],
) -> ([f32; 3], [f32; 3], [f32; 4], f32, [f32; SH_FLOATS], f32) {
    let mut total = 0.0;
    let mut mean = DVec3::ZERO;
    let weights: Vec<f64> = idx
        .iter()
        .map(|&i| {
            let s = g.log_scales[i].map(|v| f64::from(v).exp());
            f64::from(sigmoid(g.opacity_logits[i])) * mean_area(s) + 1e-30
        })
        .collect();
    for (&i, &w) in idx.iter().zip(&weights) {
        mean += w * DVec3::from_array(g.means[i].map(f64::from));
        total += w;
    }
    mean /= total;
    let mut cov = DMat3::ZERO;
    let mut sh = [0.0f64; SH_FLOATS];
    let mut trunk = 0.0;
    for (&i, &w) in idx.iter().zip(&weights) {
        let q = g.rotations[i].map(f64::from);
        let r = DMat3::from_quat(glam::DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize());
        let s = DVec3::from_array(g.log_scales[i].map(|v| (2.0 * f64::from(v)).exp()));
        let d = DVec3::from_array(g.means[i].map(f64::from)) - mean;
        let own = r * DMat3::from_diagonal(s) * r.transpose();
        cov += (own + DMat3::from_cols(d * d.x, d * d.y, d * d.z)) * w;
        for (k, v) in sh.iter_mut().enumerate() {
            *v += w * f64::from(g.sh[i][k]);
        }
        trunk += w * f64::from(g.trunk_prob[i]);
    }
    cov *= 1.0 / total;
    let eig = crate::geom::symmetric_eigen3(cov);
    let mut axes = eig.vectors;
    if axes[0].cross(axes[1]).dot(axes[2]) < 0.0 {
        axes[2] = -axes[2];
    }
    let rot = glam::DQuat::from_mat3(&DMat3::from_cols(axes[0], axes[1], axes[2])).normalize();
    let scales = eig.values.map(|v| v.max(1e-12).sqrt());
    let opacity = (total / mean_area(scales)).min(f64::from(MAX_MERGED_OPACITY)) as f32;
    let logit = (opacity / (1.0 - opacity)).ln();
    (
        mean.as_vec3().to_array(),
        scales.map(|s| s.ln() as f32),
        [rot.w as f32, rot.x as f32, rot.y as f32, rot.z as f32],
        logit,
        sh.map(|v| (v / total) as f32),
        (trunk / total) as f32,
    )
}

/// `g`'s Gaussians merged on a grid of cubic cells of side `cell` (m) from `lo`.
fn merge_cells(g: &Gaussians, idx: &[usize], lo: [f64; 3], cell: f64) -> Gaussians {
    let mut cells: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
    for &i in idx {
        let key =
            std::array::from_fn(|k| ((f64::from(g.means[i][k]) - lo[k]) / cell).floor() as i64);
        cells.entry(key).or_default().push(i);
    }
    let mut keys: Vec<[i64; 3]> = cells.keys().copied().collect();
    keys.sort_unstable();
    let mut out = Gaussians {
        sh_degree: g.sh_degree,
        ..Default::default()
    };
    for key in keys {
        let members = &cells[&key];
        // A cell of one keeps its Gaussian as trained.
        let (m, s, r, o, sh, t) = match members.as_slice() {
            &[i] => (
                g.means[i],
                g.log_scales[i],
                g.rotations[i],
                g.opacity_logits[i],
                g.sh[i],
                g.trunk_prob[i],
            ),
            _ => merge_one(g, members),
        };
        out.means.push(m);
        out.log_scales.push(s);
        out.rotations.push(r);
        out.opacity_logits.push(o);
        out.sh.push(sh);
        out.trunk_prob.push(t);
    }
    out
}

/// Occupied cells of side `cell` from `lo`.
fn occupied(g: &Gaussians, idx: &[usize], lo: [f64; 3], cell: f64) -> usize {
    let mut keys: Vec<[i64; 3]> = idx
        .iter()
        .map(|&i| {
            std::array::from_fn(|k| ((f64::from(g.means[i][k]) - lo[k]) / cell).floor() as i64)
        })
        .collect();
    keys.sort_unstable();
    keys.dedup();
    keys.len()
}

fn build_node(
    g: &Gaussians,
    idx: Vec<usize>,
    lo: [f64; 3],
    hi: [f64; 3],
    depth: u32,
    p: &TileParams,
) -> Node {
    let max = p.max_per_tile.max(1);
    if idx.len() <= max || depth >= MAX_DEPTH {
        return Node {
            lo,
            hi,
            content: subset(g, &idx),
            geometric_error: 0.0,
            children: Vec::new(),
        };
    }
    let mid: [f64; 3] = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
    let mut octants: [Vec<usize>; 8] = Default::default();
    for &i in &idx {
        let o = (0..3).fold(0, |o, k| {
            o | (usize::from(f64::from(g.means[i][k]) >= mid[k]) << k)
        });
        octants[o].push(i);
    }
    let children: Vec<Node> = octants
        .into_iter()
        .enumerate()
        .filter(|(_, v)| !v.is_empty())
        .map(|(o, v)| {
            let clo = std::array::from_fn(|k| if o >> k & 1 == 1 { mid[k] } else { lo[k] });
            let chi = std::array::from_fn(|k| if o >> k & 1 == 1 { hi[k] } else { mid[k] });
            build_node(g, v, clo, chi, depth + 1, p)
        })
        .collect();
    let side = (0..3)
        .map(|k| hi[k] - lo[k])
        .fold(0.0f64, f64::max)
        .max(1e-6);
    // Cells from 1/64 of the side, each step 2^(1/3) larger (about half the cells).
    let mut cell = side / 64.0;
    while occupied(g, &idx, lo, cell) > max {
        cell *= 2f64.cbrt();
    }
    let child_error = children
        .iter()
        .map(|c| c.geometric_error)
        .fold(0.0, f64::max);
    Node {
        lo,
        hi,
        content: merge_cells(g, &idx, lo, cell),
        geometric_error: (cell * 3f64.sqrt()).max(child_error * 1.0001),
        children,
    }
}

/// The tile JSON of `node` at `path` (e.g. "0", "0_3"), its files pushed on `files`.
fn emit(
    node: &Node,
    path: &str,
    depth: usize,
    files: &mut Vec<TileFile>,
    per_level: &mut Vec<usize>,
) -> std::io::Result<Value> {
    let centre: [f64; 3] = std::array::from_fn(|k| 0.5 * (node.lo[k] + node.hi[k]));
    let half: [f64; 3] = std::array::from_fn(|k| (0.5 * (node.hi[k] - node.lo[k])).max(1e-3));
    let mut local = node.content.clone();
    for m in &mut local.means {
        for k in 0..3 {
            m[k] = (f64::from(m[k]) - centre[k]) as f32;
        }
    }
    // The node: translate to the box centre in the z-up frame, then turn into glTF's y up.
    let to_y = glam::DMat4::from_cols_array(&Z_UP_TO_Y_UP);
    let matrix = (to_y * glam::DMat4::from_translation(DVec3::from_array(centre))).to_cols_array();
    let (doc, bin) = export_gltf::gltf_parts_spz(&local, &matrix, json!({ "tile": path }))?;
    let mut glb = Vec::new();
    export_gltf::write_glb_parts(&mut glb, &doc, &bin)?;
    let uri = format!("tiles/{path}.glb");
    files.push(TileFile {
        path: uri.clone(),
        glb,
    });
    if per_level.len() <= depth {
        per_level.push(0);
    }
    per_level[depth] += 1;
    let children = node
        .children
        .iter()
        .enumerate()
        .map(|(i, c)| emit(c, &format!("{path}_{i}"), depth + 1, files, per_level))
        .collect::<std::io::Result<Vec<Value>>>()?;
    let mut tile = json!({
        "boundingVolume": { "box": [
            centre[0], centre[1], centre[2],
            half[0], 0.0, 0.0,
            0.0, half[1], 0.0,
            0.0, 0.0, half[2],
        ]},
        "geometricError": node.geometric_error,
        "refine": "REPLACE",
        "content": { "uri": uri },
    });
    if !children.is_empty() {
        tile["children"] = json!(children);
    }
    Ok(tile)
}

/// The tileset of `g` (local frame), with `to_ecef` (column-major 4×4, local metres to ECEF) as
/// the root's transform when the CRS is known, and `trees` as tileset metadata.
pub fn build(
    g: &Gaussians,
    to_ecef: Option<&[f64; 16]>,
    trees: &[TreeMeta],
    params: &TileParams,
) -> std::io::Result<Tileset> {
    let Some((lo, hi)) = g.bounds() else {
        return Err(std::io::Error::other("no Gaussians to tile"));
    };
    let (lo, hi) = (lo.map(f64::from), hi.map(f64::from));
    // A cube about the centres, so that octants are cubes too.
    let side = (0..3)
        .map(|k| hi[k] - lo[k])
        .fold(0.0f64, f64::max)
        .max(1e-3)
        * 1.0001;
    let centre: [f64; 3] = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
    let lo = centre.map(|c| c - 0.5 * side);
    let hi = centre.map(|c| c + 0.5 * side);
    let root = build_node(g, (0..g.len()).collect(), lo, hi, 0, params);
    let mut tiles = Vec::new();
    let mut per_level = Vec::new();
    let mut root_json = emit(&root, "0", 0, &mut tiles, &mut per_level)?;
    if let Some(m) = to_ecef {
        root_json["transform"] = json!(m);
    }
    let frame = match to_ecef {
        Some(_) => "local metres; the root transform takes them to ECEF (WGS84)",
        None => {
            "local metres (file coordinates minus the job's offset); no CRS, so not placed on the Earth"
        }
    };
    let json = json!({
        "asset": {
            "version": "1.1",
            "generator": concat!("Sylva ", env!("CARGO_PKG_VERSION")),
            "extras": { "frame": frame },
        },
        // Below this much error on screen the whole tileset is left out: the root box's
        // diagonal, the size of the scene.
        "geometricError": (2.0 * 3f64.sqrt() * 0.5 * side).max(root.geometric_error * 2.0),
        "extensionsUsed": ["3DTILES_content_gltf"],
        "extensions": {
            "3DTILES_content_gltf": {
                "extensionsUsed": [EXTENSION, SPZ_EXTENSION],
                "extensionsRequired": [EXTENSION, SPZ_EXTENSION],
            }
        },
        "schema": {
            "id": "sylva",
            "classes": {
                "plot": {
                    "description": "The plot's trees (stage dbh): base positions in the tileset's local frame, metres",
                    "properties": {
                        "treeId": { "type": "STRING", "array": true },
                        "position": { "type": "VEC3", "componentType": "FLOAT64", "array": true },
                        "dbh": { "type": "SCALAR", "componentType": "FLOAT64", "array": true, "description": "diameter at breast height, m" },
                        "height": { "type": "SCALAR", "componentType": "FLOAT64", "array": true, "description": "tree height, m" },
                    }
                }
            }
        },
        "metadata": {
            "class": "plot",
            "properties": {
                "treeId": trees.iter().map(|t| t.id.clone()).collect::<Vec<_>>(),
                "position": trees.iter().map(|t| t.position).collect::<Vec<_>>(),
                "dbh": trees.iter().map(|t| t.dbh_m).collect::<Vec<_>>(),
                "height": trees.iter().map(|t| t.height_m).collect::<Vec<_>>(),
            }
        },
        "root": root_json,
    });
    Ok(Tileset {
        json,
        root_gaussians: root.content.len(),
        tiles,
        per_level,
    })
}

/// WGS84 longitude, latitude (degrees) and ellipsoidal height (m) to ECEF (m).
pub fn wgs84_to_ecef(lon_deg: f64, lat_deg: f64, h: f64) -> [f64; 3] {
    const A: f64 = 6_378_137.0;
    const F: f64 = 1.0 / 298.257_223_563;
    let e2 = F * (2.0 - F);
    let (lon, lat) = (lon_deg.to_radians(), lat_deg.to_radians());
    let n = A / (1.0 - e2 * lat.sin().powi(2)).sqrt();
    [
        (n + h) * lat.cos() * lon.cos(),
        (n + h) * lat.cos() * lon.sin(),
        (n * (1.0 - e2) + h) * lat.sin(),
    ]
}

/// The affine map (column-major 4×4) from the local frame to ECEF for a plot whose file
/// coordinates are local + `offset` in `crs`, fitted over the box `lo`…`hi` (local metres), and
/// the fit's largest residual (m). See the module doc.
pub fn local_to_ecef(
    crs: &crate::io::crs::Crs,
    offset: [f64; 3],
    lo: [f64; 3],
    hi: [f64; 3],
) -> Result<([f64; 16], f64), crate::io::crs::CrsError> {
    let mut local = Vec::new();
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..3 {
                let t = |a: usize, d: usize| lo[d] + (hi[d] - lo[d]).max(1.0) * a as f64 / 2.0;
                local.push([t(i, 0), t(j, 1), t(k, 2)]);
            }
        }
    }
    let mut xy: Vec<(f64, f64)> = local
        .iter()
        .map(|p| (p[0] + offset[0], p[1] + offset[1]))
        .collect();
    crs.to_wgs84(&mut xy)?;
    let ecef: Vec<[f64; 3]> = local
        .iter()
        .zip(&xy)
        .map(|(p, &(lon, lat))| wgs84_to_ecef(lon, lat, p[2] + offset[2]))
        .collect();
    // Least squares for each ECEF axis: e = A p + t, in coordinates relative to the centroids.
    let n = local.len() as f64;
    let pc: [f64; 3] = std::array::from_fn(|k| local.iter().map(|p| p[k]).sum::<f64>() / n);
    let ec: [f64; 3] = std::array::from_fn(|k| ecef.iter().map(|e| e[k]).sum::<f64>() / n);
    let mut ptp = DMat3::ZERO;
    let mut rows = [DVec3::ZERO; 3];
    for (p, e) in local.iter().zip(&ecef) {
        let d = DVec3::new(p[0] - pc[0], p[1] - pc[1], p[2] - pc[2]);
        ptp += DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        for r in 0..3 {
            rows[r] += d * (e[r] - ec[r]);
        }
    }
    let inv = ptp.inverse();
    let a = DMat3::from_cols(inv * rows[0], inv * rows[1], inv * rows[2]).transpose();
    let t = DVec3::from_array(ec) - a * DVec3::from_array(pc);
    let residual = local
        .iter()
        .zip(&ecef)
        .map(|(p, e)| (a * DVec3::from_array(*p) + t - DVec3::from_array(*e)).length())
        .fold(0.0, f64::max);
    let m = glam::DMat4::from_cols(
        a.x_axis.extend(0.0),
        a.y_axis.extend(0.0),
        a.z_axis.extend(0.0),
        t.extend(1.0),
    );
    Ok((m.to_cols_array(), residual))
}

#[cfg(test)]
#[path = "tiles_tests.rs"]
mod tests;
