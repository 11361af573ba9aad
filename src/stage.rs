//! The vocabulary the pipeline and the job queue share: the stages of a job, the kinds of
//! upload, and the files a finished stage leaves. A base module, so that `jobs` (the queue)
//! and `pipeline` (the science) both use these words without either importing the other.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// The stages of a job, in order (docs/api.md).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize, JsonSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    Ingest,
    /// Structure from motion: COLMAP run on the job's photos (nothing to do when the job
    /// gave a COLMAP project).
    Sfm,
    Register,
    Anchors,
    Segment,
    Train,
    Dbh,
    Export,
}

impl Stage {
    pub const ALL: [Stage; 8] = [
        Stage::Ingest,
        Stage::Sfm,
        Stage::Register,
        Stage::Anchors,
        Stage::Segment,
        Stage::Train,
        Stage::Dbh,
        Stage::Export,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Stage::Ingest => "ingest",
            Stage::Sfm => "sfm",
            Stage::Register => "register",
            Stage::Anchors => "anchors",
            Stage::Segment => "segment",
            Stage::Train => "train",
            Stage::Dbh => "dbh",
            Stage::Export => "export",
        }
    }

    pub fn from_name(name: &str) -> Option<Stage> {
        Stage::ALL.into_iter().find(|s| s.name() == name)
    }

    pub fn index(self) -> usize {
        self as usize
    }

    /// The stages that run before this one, in order.
    pub fn predecessors(self) -> &'static [Stage] {
        &Stage::ALL[..self.index()]
    }

    /// Share of a whole job's progress bar this stage takes; training dominates a real run,
    /// and COLMAP on the CPU takes about as long as a short training where it runs (18 drone
    /// photos: 12 min on 2 cores, docs/results/photos.md).
    pub fn weight(self) -> f64 {
        match self {
            Stage::Ingest => 0.05,
            Stage::Sfm => 0.15,
            Stage::Register => 0.05,
            Stage::Anchors => 0.05,
            Stage::Segment => 0.10,
            Stage::Train => 0.45,
            Stage::Dbh => 0.05,
            Stage::Export => 0.10,
        }
    }

    /// Whether the stage needs the GPU slot while it runs.
    pub fn uses_gpu(self) -> bool {
        matches!(self, Stage::Train)
    }
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One file a finished stage produced.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct OutputFile {
    /// Path relative to the job's work directory, with `/` separators (e.g. `ingest/report.json`).
    pub name: String,
    pub stage: Stage,
    pub kind: String,
    pub size: u64,
    pub sha256: String,
    pub content_type: String,
}

/// What an upload holds (docs/api.md "Kinds").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UploadKind {
    /// A point cloud: LAS/LAZ/PLY/XYZ.
    Lidar,
    /// A zip or tar(.gz) of a COLMAP project: images/ and sparse/0 or sparse/.
    Colmap,
    /// A zip or tar(.gz) of photos (JPEG, PNG or TIFF) for stage `sfm` to reconstruct.
    Photos,
    /// Control point pairs (CSV).
    ControlPoints,
    /// Field-measured DBH (CSV).
    FieldDbh,
}

impl UploadKind {
    pub const ALL: &'static [UploadKind] = &[
        UploadKind::Lidar,
        UploadKind::Colmap,
        UploadKind::Photos,
        UploadKind::ControlPoints,
        UploadKind::FieldDbh,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            UploadKind::Lidar => "lidar",
            UploadKind::Colmap => "colmap",
            UploadKind::Photos => "photos",
            UploadKind::ControlPoints => "control_points",
            UploadKind::FieldDbh => "field_dbh",
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.iter().copied().find(|k| k.as_str() == s)
    }

    /// True for the kinds uploaded as a zip or tar and unpacked once, on inspection.
    pub fn is_archive(self) -> bool {
        matches!(self, UploadKind::Colmap | UploadKind::Photos)
    }
}
