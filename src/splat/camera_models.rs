//! COLMAP camera models and their distortion (formulas of COLMAP's `src/colmap/sensor/models.h`),
//! on normalised image coordinates u = (x − cx) / fx, v = (y − cy) / fy.

/// A COLMAP camera model with its parameters (pixels; distortion coefficients unitless).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CameraModel {
    /// `PINHOLE`: fx, fy, cx, cy.
    Pinhole { fx: f64, fy: f64, cx: f64, cy: f64 },
    /// `SIMPLE_PINHOLE`: f, cx, cy.
    SimplePinhole { f: f64, cx: f64, cy: f64 },
    /// `SIMPLE_RADIAL`: f, cx, cy, k.
    SimpleRadial { f: f64, cx: f64, cy: f64, k: f64 },
    /// `RADIAL`: f, cx, cy, k1, k2.
    Radial {
        f: f64,
        cx: f64,
        cy: f64,
        k1: f64,
        k2: f64,
    },
    /// `OPENCV`: fx, fy, cx, cy, k1, k2, p1, p2.
    OpenCv {
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        k1: f64,
        k2: f64,
        p1: f64,
        p2: f64,
    },
}

/// Why a COLMAP camera or image could not be used.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error(
        "COLMAP camera model {0:?} is not supported; use PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, \
         RADIAL or OPENCV (re-run COLMAP's image_undistorter for other models)"
    )]
    UnsupportedModel(String),
    #[error("COLMAP camera model {model} takes {expected} parameters, got {got}")]
    WrongParamCount {
        model: &'static str,
        expected: usize,
        got: usize,
    },
    #[error("image {name:?} is {got_w}×{got_h} px but its COLMAP camera says {want_w}×{want_h}")]
    SizeMismatch {
        name: String,
        got_w: u32,
        got_h: u32,
        want_w: u32,
        want_h: u32,
    },
    #[error("camera of image {0:?} has a non-finite or zero focal length or quaternion")]
    Degenerate(String),
}

impl CameraModel {
    /// Parses a COLMAP model name (as in `cameras.txt`) and its parameter list.
    pub fn from_colmap(name: &str, p: &[f64]) -> Result<Self, CameraError> {
        let want = |model: &'static str, n: usize| {
            if p.len() == n {
                Ok(())
            } else {
                Err(CameraError::WrongParamCount {
                    model,
                    expected: n,
                    got: p.len(),
                })
            }
        };
        Ok(match name {
            "PINHOLE" => {
                want("PINHOLE", 4)?;
                CameraModel::Pinhole {
                    fx: p[0],
                    fy: p[1],
                    cx: p[2],
                    cy: p[3],
                }
            }
            "SIMPLE_PINHOLE" => {
                want("SIMPLE_PINHOLE", 3)?;
                CameraModel::SimplePinhole {
                    f: p[0],
                    cx: p[1],
                    cy: p[2],
                }
            }
            "SIMPLE_RADIAL" => {
                want("SIMPLE_RADIAL", 4)?;
                CameraModel::SimpleRadial {
                    f: p[0],
                    cx: p[1],
                    cy: p[2],
                    k: p[3],
                }
            }
            "RADIAL" => {
                want("RADIAL", 5)?;
                CameraModel::Radial {
                    f: p[0],
                    cx: p[1],
                    cy: p[2],
                    k1: p[3],
                    k2: p[4],
                }
            }
            "OPENCV" => {
                want("OPENCV", 8)?;
                CameraModel::OpenCv {
                    fx: p[0],
                    fy: p[1],
                    cx: p[2],
                    cy: p[3],
                    k1: p[4],
                    k2: p[5],
                    p1: p[6],
                    p2: p[7],
                }
            }
            other => return Err(CameraError::UnsupportedModel(other.to_string())),
        })
    }

    /// (fx, fy, cx, cy) in pixels.
    pub fn intrinsics(&self) -> [f64; 4] {
        match *self {
            CameraModel::Pinhole { fx, fy, cx, cy }
            | CameraModel::OpenCv { fx, fy, cx, cy, .. } => [fx, fy, cx, cy],
            CameraModel::SimplePinhole { f, cx, cy }
            | CameraModel::SimpleRadial { f, cx, cy, .. }
            | CameraModel::Radial { f, cx, cy, .. } => [f, f, cx, cy],
        }
    }

    /// True for models with distortion terms (whether or not they are zero).
    pub fn is_distorted(&self) -> bool {
        !matches!(
            self,
            CameraModel::Pinhole { .. } | CameraModel::SimplePinhole { .. }
        )
    }

    /// Distorts normalised image coordinates (u, v) as COLMAP does: returns (u + du, v + dv).
    pub fn distort(&self, u: f64, v: f64) -> (f64, f64) {
        let r2 = u * u + v * v;
        let (du, dv) = match *self {
            CameraModel::Pinhole { .. } | CameraModel::SimplePinhole { .. } => (0.0, 0.0),
            CameraModel::SimpleRadial { k, .. } => (u * k * r2, v * k * r2),
            CameraModel::Radial { k1, k2, .. } => {
                let radial = k1 * r2 + k2 * r2 * r2;
                (u * radial, v * radial)
            }
            CameraModel::OpenCv { k1, k2, p1, p2, .. } => {
                let radial = k1 * r2 + k2 * r2 * r2;
                let uv = u * v;
                (
                    u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u * u),
                    v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v * v),
                )
            }
        };
        (u + du, v + dv)
    }
}
