//! `sylva bench tiles`: the time to build the 3D Tiles tileset of a twin (`splat::tiles`) and
//! its size on disk against the PLY, the glTF and SPZ of the same splats, for twins of the
//! given sizes. The twin is generated: Gaussians of the size and spread of a trained stand
//! (centres uniform over a 60 × 60 × 25 m plot, axis scales 1.5–20 cm, SH degree 3), seeded.

use std::time::Instant;

use sylva::rng::SplitMix64;
use sylva::splat::model::{Gaussians, SH_FLOATS};
use sylva::splat::tiles::{self, TileParams};

/// A generated twin of `n` Gaussians (see the module doc).
fn twin(n: usize, seed: u64) -> Gaussians {
    let mut rng = SplitMix64::new(seed);
    let mut range = |lo: f32, hi: f32| lo + (hi - lo) * rng.uniform() as f32;
    let mut g = Gaussians {
        sh_degree: 3,
        ..Default::default()
    };
    for _ in 0..n {
        g.means
            .push([range(-30.0, 30.0), range(-30.0, 30.0), range(0.0, 25.0)]);
        g.log_scales
            .push(std::array::from_fn(|_| range(0.015, 0.2).ln()));
        g.rotations.push(std::array::from_fn(|_| range(-1.0, 1.0)));
        g.opacity_logits.push(range(-2.0, 4.0));
        g.sh.push(std::array::from_fn::<f32, SH_FLOATS, _>(|k| {
            if k < 3 {
                range(-1.5, 1.5)
            } else {
                range(-0.2, 0.2)
            }
        }));
        g.trunk_prob.push(0.0);
    }
    g
}

/// Bytes `write` produces.
fn size(write: impl FnOnce(&mut Vec<u8>) -> std::io::Result<()>) -> anyhow::Result<usize> {
    let mut out = Vec::new();
    write(&mut out)?;
    Ok(out.len())
}

/// Prints the table for twins of `sizes` Gaussians.
pub fn run(sizes: &[usize]) -> anyhow::Result<()> {
    println!(
        "| Gaussians | build s | CPU s | tiles | levels | tileset MB | root Gaussians | root MB | PLY MB | glb MB | SPZ MB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for &n in sizes {
        let g = twin(n, 1);
        let (t, cpu) = (Instant::now(), super::geom::cpu_seconds());
        let set = tiles::build(&g, None, &[], &TileParams::default())?;
        let (wall, cpu) = (t.elapsed().as_secs_f64(), super::geom::cpu_seconds() - cpu);
        let bytes: usize = set.tiles.iter().map(|t| t.glb.len()).sum::<usize>()
            + serde_json::to_vec(&set.json)?.len();
        let root = set.tiles.first().map_or(0, |t| t.glb.len());
        let ply = size(|w| sylva::splat::export::write_ply(w, &g))?;
        let glb = size(|w| sylva::splat::export_gltf::write_glb(w, &g))?;
        let spz = size(|w| sylva::splat::export_spz::write_spz(w, &g))?;
        let mb = |b: usize| b as f64 / 1e6;
        println!(
            "| {n} | {wall:.1} | {cpu:.1} | {} | {} | {:.1} | {} | {:.2} | {:.1} | {:.1} | {:.1} |",
            set.tiles.len(),
            set.per_level.len(),
            mb(bytes),
            set.root_gaussians,
            mb(root),
            mb(ply),
            mb(glb),
            mb(spz)
        );
    }
    Ok(())
}
