//! What the registration examples share: the generator's truth of a `sylva synth` plot, the
//! errors of an estimate against it, and the seeds argument.

use glam::{DQuat, DVec3};
use sylva::geom::Similarity;
use sylva::pipeline::register::similarity_from_json;

pub type Error = Box<dyn std::error::Error>;

/// Rotation (degrees), scale (relative) and translation at the plot centre (metres) errors.
pub fn errors(est: &Similarity, truth: &Similarity, centre: DVec3) -> (f64, f64, f64) {
    let rot = DQuat::from_mat3(&(est.rotation.transpose() * truth.rotation))
        .angle_between(DQuat::IDENTITY)
        .to_degrees();
    let scale = est.scale / truth.scale - 1.0;
    let p = truth.inverse().apply(centre);
    (rot, scale, (est.apply(p) - centre).length())
}

/// The plot's true SfM → LiDAR file similarity and its centre (file coordinates), from
/// `out/truth.json`.
pub fn truth_of(out: &std::path::Path) -> Result<(Similarity, DVec3), Error> {
    let truth: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("truth.json"))?)?;
    let sim = similarity_from_json(&truth["sfm_to_world"]).ok_or("truth: sfm_to_world")?;
    let centre = DVec3::from_array(serde_json::from_value(truth["plot_center"].clone())?);
    Ok((sim, centre))
}

/// Seeds from `A-B` or `N` (default 1-5).
pub fn seeds(arg: Option<&str>) -> Result<Vec<u64>, Error> {
    let arg = arg.unwrap_or("1-5");
    Ok(match arg.split_once('-') {
        Some((a, b)) => (a.parse()?..=b.parse()?).collect(),
        None => vec![arg.parse()?],
    })
}

/// The registration stage's log lines on stderr when the environment variable `var` is set,
/// else nothing.
pub fn stage_log(var: &str) -> &'static dyn sylva::progress::Progress {
    if std::env::var_os(var).is_some() {
        &sylva::progress::LogLines("")
    } else {
        &sylva::progress::NoProgress
    }
}
