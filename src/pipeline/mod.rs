//! The pipeline: eight stages, each a function of files in and files out.
//!
//! A stage reads its inputs and the outputs of earlier stages from the job's work directory,
//! writes its own outputs into a fresh `<stage>.partial/` folder, and [`execute_stage`] renames
//! that folder to `<stage>/` only when the stage succeeded. A crash therefore never leaves a
//! half-written stage that looks finished, and a resumed job simply starts again at the first
//! stage without a folder. The same code serves the HTTP worker and `sylva run`; nothing here
//! knows about HTTP or SQL.

pub mod anchors;
pub mod dbh;
pub mod export;
pub mod fuzz;
pub mod ingest;
pub mod inspect;
pub mod params;
pub mod register;
pub mod segment;
pub mod sfm;
pub mod train;

use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::io::{IoError, colmap};
use crate::progress::Progress;
pub use crate::stage::{OutputFile, Stage};
pub use params::PipelineParams;

/// The files a job starts from, already on local disk. `colmap` is a folder holding the
/// COLMAP project, `photos` a folder of photos for stage `sfm` to reconstruct (an uploaded
/// archive is unpacked before the pipeline sees it); a job gives one of the two.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StageInputs {
    pub lidar: PathBuf,
    #[serde(default)]
    pub colmap: Option<PathBuf>,
    #[serde(default)]
    pub photos: Option<PathBuf>,
    pub control_points: Option<PathBuf>,
    pub field_dbh: Option<PathBuf>,
}

impl StageInputs {
    /// The inputs of a plot `sylva synth` wrote to `plot`: its LiDAR, COLMAP project,
    /// control points and field DBH.
    pub fn of_synth_plot(plot: &std::path::Path) -> Self {
        Self {
            lidar: plot.join("lidar.laz"),
            colmap: Some(plot.join("colmap")),
            photos: None,
            control_points: Some(plot.join("control_points.csv")),
            field_dbh: Some(plot.join("field_dbh.csv")),
        }
    }

    /// Inputs from a COLMAP project (the form every job had before stage `sfm`).
    pub fn with_colmap(lidar: PathBuf, colmap: PathBuf) -> Self {
        Self {
            lidar,
            colmap: Some(colmap),
            photos: None,
            control_points: None,
            field_dbh: None,
        }
    }
}

/// Why a stage did not finish.
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    /// An input file is unusable: the message names the file and the fault.
    #[error("{0}")]
    Input(String),
    /// Reading or writing files failed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The GPU is missing or failed (the service's fault, not the input's).
    #[error("{0}")]
    Device(String),
    /// A program the stage runs is missing on this worker (the service's fault): the message
    /// names it and how to install it.
    #[error("{0}")]
    Unavailable(String),
    /// The data were usable but a gate refused the result (the automatic registration was
    /// not sure): `detail` says why and what to supply, `candidates` what was weighed (the
    /// job's problem carries them, the web page lists them).
    #[error("{detail}")]
    Refused {
        detail: String,
        candidates: Vec<serde_json::Value>,
    },
    /// The job was cancelled while the stage ran.
    #[error("cancelled")]
    Cancelled,
    /// A stage needs the output of an earlier stage that is missing.
    #[error("stage {stage} needs the output of stage {needs}, which has not finished")]
    MissingPredecessor { stage: Stage, needs: Stage },
}

impl From<crate::geom::GeomError> for StageError {
    /// Geometry fails on the data it was given (too few points, degenerate shapes): an input
    /// fault, except cancellation.
    fn from(e: crate::geom::GeomError) -> Self {
        match e {
            crate::geom::GeomError::Cancelled => StageError::Cancelled,
            other => StageError::Input(other.to_string()),
        }
    }
}

impl StageError {
    /// True when the failure is the user's input (a 422-like fault), not the service's.
    pub fn is_input_fault(&self) -> bool {
        matches!(self, StageError::Input(_) | StageError::Refused { .. })
            || matches!(self, StageError::Io(IoError::Format { .. }))
    }

    /// True when the disk is full (mapped to HTTP 507 by the API).
    pub fn is_storage_full(&self) -> bool {
        matches!(self, StageError::Io(IoError::Io { source, .. })
            if source.kind() == std::io::ErrorKind::StorageFull)
    }
}

/// What one stage sees while it runs.
pub struct StageContext<'a> {
    pub inputs: &'a StageInputs,
    /// The job's work directory; earlier stages' outputs are in `<work_dir>/<stage>/`.
    pub work_dir: &'a Path,
    /// This stage's (temporary) output folder, empty when the stage starts.
    pub out_dir: &'a Path,
    pub params: &'a PipelineParams,
    pub progress: &'a dyn Progress,
}

/// The LiDAR cloud stage ingest leaves in its folder (local coordinates, PLY).
pub const INGEST_CLOUD: &str = "cloud.ply";

impl StageContext<'_> {
    /// The LiDAR cloud stage ingest wrote in its folder `ingest`, read with progress over the
    /// first `share` of this stage.
    pub fn read_ingest_cloud(
        &self,
        ingest: &Path,
        share: f64,
    ) -> Result<crate::io::pointcloud::PointCloud, StageError> {
        let progress = crate::progress::SubProgress::new(self.progress, 0.0, share);
        Ok(crate::io::pointcloud::read_point_cloud(
            &ingest.join(INGEST_CLOUD),
            &progress,
        )?)
    }

    /// The job's CRS as stage `ingest` settled it (its `crs.json`), for a stage that writes
    /// georeferenced outputs; the caller writes it again beside them.
    pub fn crs(&self, me: Stage) -> Result<crate::io::crs::CrsRecord, StageError> {
        let ingest = self.output_of(Stage::Ingest, me)?;
        Ok(crate::forest::read_crs(&ingest)?)
    }

    /// The folder holding the job's SfM model in the SfM frame, as text: `sfm/sparse` when
    /// stage `sfm` reconstructed one from photos, else `ingest/sparse` (the uploaded
    /// project, copied by stage `ingest`).
    pub fn sfm_model_dir(&self, me: Stage) -> Result<PathBuf, StageError> {
        let ingest = self.output_of(Stage::Ingest, me)?;
        let from_photos = self.work_dir.join(Stage::Sfm.name()).join("sparse");
        if self.inputs.photos.is_some() {
            self.output_of(Stage::Sfm, me)?;
            return Ok(from_photos);
        }
        Ok(ingest.join("sparse"))
    }

    /// The folder of the job's photos, as the SfM model names them: the uploaded project's
    /// `images/`, or the folder of photos stage `sfm` reconstructed.
    pub fn images_dir(&self) -> Result<PathBuf, StageError> {
        match (&self.inputs.photos, &self.inputs.colmap) {
            (Some(photos), _) => Ok(crate::io::photos::find_photos_dir(photos)?),
            (None, Some(colmap)) => colmap::find_project(colmap)?.images_dir.ok_or_else(|| {
                StageError::Input(
                    "COLMAP project: no images/ folder beside the sparse model".into(),
                )
            }),
            (None, None) => Err(StageError::Input(NO_PHOTOS.into())),
        }
    }

    /// The finished output folder of an earlier stage, or a clear error if it is missing.
    pub fn output_of(&self, stage: Stage, me: Stage) -> Result<PathBuf, StageError> {
        let dir = self.work_dir.join(stage.name());
        if dir.join(REPORT_FILE).is_file() {
            Ok(dir)
        } else {
            Err(StageError::MissingPredecessor {
                stage: me,
                needs: stage,
            })
        }
    }
}

/// What a job without either source of photos is told.
pub const NO_PHOTOS: &str =
    "the job has neither photos nor a COLMAP project; give one of `photos` and `colmap`";

/// Name of the report every stage leaves in its folder.
pub const REPORT_FILE: &str = "report.json";

/// The result of a finished stage: its report (also written as `<stage>/report.json`) and
/// every file it left.
#[derive(Debug, Clone)]
pub struct StageOutcome {
    pub report: serde_json::Value,
    pub files: Vec<OutputFile>,
}

/// Runs one stage function.
pub fn run_stage(stage: Stage, ctx: &StageContext<'_>) -> Result<serde_json::Value, StageError> {
    match stage {
        Stage::Ingest => ingest::run(ctx),
        Stage::Sfm => sfm::run(ctx),
        Stage::Register => register::run(ctx),
        Stage::Anchors => anchors::run(ctx),
        Stage::Segment => segment::run(ctx),
        Stage::Train => train::run(ctx),
        Stage::Dbh => dbh::run(ctx),
        Stage::Export => export::run(ctx),
    }
}

fn io_err(path: &Path, source: std::io::Error) -> StageError {
    StageError::Io(IoError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Runs `stage` for a job whose files live in `work_dir`: output goes to a fresh
/// `<stage>.partial/`, which becomes `<stage>/` (replacing any older one) only on success,
/// after the report is written and synced.
pub fn execute_stage(
    stage: Stage,
    inputs: &StageInputs,
    work_dir: &Path,
    params: &PipelineParams,
    progress: &dyn Progress,
) -> Result<StageOutcome, StageError> {
    let partial = work_dir.join(format!("{}.partial", stage.name()));
    let done = work_dir.join(stage.name());
    if partial.exists() {
        fs::remove_dir_all(&partial).map_err(|e| io_err(&partial, e))?;
    }
    fs::create_dir_all(&partial).map_err(|e| io_err(&partial, e))?;
    let ctx = StageContext {
        inputs,
        work_dir,
        out_dir: &partial,
        params,
        progress,
    };
    let result = run_stage(stage, &ctx);
    release_freed_memory();
    let report = match result {
        Ok(r) => r,
        Err(e) => {
            let _ = fs::remove_dir_all(&partial);
            return Err(e);
        }
    };
    let report_path = partial.join(REPORT_FILE);
    let text = serde_json::to_vec_pretty(&report).unwrap_or_default();
    write_synced(&report_path, &text).map_err(|e| io_err(&report_path, e))?;
    if done.exists() {
        fs::remove_dir_all(&done).map_err(|e| io_err(&done, e))?;
    }
    fs::rename(&partial, &done).map_err(|e| io_err(&done, e))?;
    sync_dir(work_dir);
    let files = list_outputs(stage, work_dir)?;
    Ok(StageOutcome { report, files })
}

/// Hands the memory a stage freed back to the system (glibc keeps freed heap in its arenas, so
/// a worker that ran a paper-size stage would otherwise hold its peak into every later stage
/// and job: measured 10.9 GB carried from stage `train` into `dbh` on the paper-size plot,
/// docs/results/scale.md). Nothing to do where the allocator is not glibc's.
fn release_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free pages of glibc's heap to the kernel.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Writes a file and syncs it to disk before returning.
pub fn write_synced(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let mut f = fs::File::create(path)?;
    f.write_all(bytes)?;
    f.sync_all()
}

/// Best-effort sync of a directory entry (so a rename survives power loss).
pub fn sync_dir(dir: &Path) {
    if let Ok(d) = fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

/// Every regular file under `<work_dir>/<stage>/`, with size, hash and content type.
pub fn list_outputs(stage: Stage, work_dir: &Path) -> Result<Vec<OutputFile>, StageError> {
    let root = work_dir.join(stage.name());
    let mut out = Vec::new();
    let mut stack = vec![root.clone()];
    while let Some(dir) = stack.pop() {
        let entries = fs::read_dir(&dir).map_err(|e| io_err(&dir, e))?;
        for entry in entries {
            let entry = entry.map_err(|e| io_err(&dir, e))?;
            let path = entry.path();
            let ft = entry.file_type().map_err(|e| io_err(&path, e))?;
            if ft.is_dir() {
                stack.push(path);
            } else if ft.is_file() {
                let rel = crate::io::relative_name(&path, work_dir);
                let (size, sha256) = hash_file(&path).map_err(|e| io_err(&path, e))?;
                let (kind, content_type) = classify(&rel);
                out.push(OutputFile {
                    name: rel,
                    stage,
                    kind: kind.to_string(),
                    size,
                    sha256,
                    content_type: content_type.to_string(),
                });
            }
        }
    }
    out.sort_by(|a, b| a.name.cmp(&b.name));
    Ok(out)
}

/// Size in bytes and hex SHA-256 of a file, read in 1 MiB blocks.
pub fn hash_file(path: &Path) -> std::io::Result<(u64, String)> {
    let mut f = fs::File::open(path)?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut size = 0u64;
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        size += n as u64;
        hasher.update(&buf[..n]);
    }
    Ok((size, hex::encode(hasher.finalize())))
}

/// Artifact kind and MIME type from a file name.
pub fn classify(name: &str) -> (&'static str, &'static str) {
    let lower = name.to_ascii_lowercase();
    let ext = lower.rsplit('.').next().unwrap_or("");
    if lower.ends_with(REPORT_FILE) {
        return ("report", "application/json");
    }
    match ext {
        "json" => ("json", "application/json"),
        "geojson" => ("geojson", "application/geo+json"),
        "csv" => ("csv", "text/csv"),
        "ply" => ("point_cloud", "application/octet-stream"),
        "las" | "laz" => ("point_cloud", "application/octet-stream"),
        "splat" | "ksplat" | "spz" => ("splat", "application/octet-stream"),
        // glTF 2.0 binary (IANA media type `model/gltf-binary`); Sylva's are splats.
        "glb" => ("splat", "model/gltf-binary"),
        "png" => ("image", "image/png"),
        "jpg" | "jpeg" => ("image", "image/jpeg"),
        "svg" => ("image", "image/svg+xml"),
        "txt" => ("text", "text/plain; charset=utf-8"),
        "bin" => ("binary", "application/octet-stream"),
        _ => ("file", "application/octet-stream"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stage_names_round_trip_and_weights_sum_to_one() {
        for s in Stage::ALL {
            assert_eq!(Stage::from_name(s.name()), Some(s));
        }
        let total: f64 = Stage::ALL.iter().map(|s| s.weight()).sum();
        assert!((total - 1.0).abs() < 1e-9);
    }

    #[test]
    fn a_gltf_binary_is_served_as_one() {
        assert_eq!(classify("splats.glb"), ("splat", "model/gltf-binary"));
        assert_eq!(classify("tiles/0.GLB").1, "model/gltf-binary");
    }
}
