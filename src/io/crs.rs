//! Coordinate reference systems (issue 27): which CRS a cloud's coordinates are in, read from
//! a LAS/LAZ file's projection records or given by the user (`EPSG:32649`, WKT, or a PROJ
//! string), and the transform of its coordinates to WGS84 longitude and latitude for GeoJSON
//! (RFC 7946 §4 requires WGS84).
//!
//! The transforms are `proj4rs`'s (a pure-Rust port of PROJ.4's projections, no C library to
//! install), the EPSG definitions are `crs-definitions`' (the EPSG registry as PROJ strings and
//! WKT), and WKT without an EPSG code is turned into a PROJ string by `proj4wkt`. Nothing here
//! writes a projection formula of its own.
//!
//! LAS 1.4 (ASPRS R15, §2.5) stores the CRS either as OGC WKT (record `LASF_Projection`/2112,
//! in a VLR or an EVLR) or as GeoTIFF keys (`LASF_Projection`/34735, the GeoKeyDirectoryTag of
//! GeoTIFF 1.0 §2.4). Of the keys, `ProjectedCSTypeGeoKey` (3072) and `GeographicTypeGeoKey`
//! (2048) name an EPSG code; a user-defined CRS (code 32767) spelled out key by key is refused
//! with a message asking for `--crs`.

use proj4rs::proj::Proj;

/// User id of the LAS records that hold a CRS.
pub const LAS_PROJECTION_USER_ID: &str = "LASF_Projection";
/// LAS record id of OGC WKT (math transform or coordinate system WKT).
pub const LAS_WKT_RECORD: u16 = 2112;
/// LAS record id of the GeoTIFF GeoKeyDirectoryTag.
pub const LAS_GEOKEY_RECORD: u16 = 34735;

/// GeoTIFF key naming a projected CRS by EPSG code.
const PROJECTED_CS_TYPE_KEY: u16 = 3072;
/// GeoTIFF key naming a geographic CRS by EPSG code.
const GEOGRAPHIC_TYPE_KEY: u16 = 2048;
/// GeoTIFF's "user-defined" code: the CRS is spelled out in further keys.
const USER_DEFINED: u16 = 32767;

/// Why a CRS could not be read or used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CrsError {
    /// The text is not an EPSG code, WKT or PROJ string this module understands.
    #[error("{0}")]
    Unreadable(String),
    /// An EPSG code the registry does not list.
    #[error(
        "EPSG:{0} is not in the EPSG registry Sylva carries; give the CRS as WKT or a PROJ string"
    )]
    UnknownEpsg(u32),
    /// The CRS is in degrees; Sylva measures stems and heights in metres.
    #[error(
        "{0} is a geographic CRS (longitude and latitude in degrees), but Sylva measures in \
         metres: reproject the cloud to a projected CRS such as its UTM zone, or, if its \
         coordinates are in fact metres, give their CRS with params.crs / --crs"
    )]
    Geographic(String),
    /// The transform failed (a point outside the projection's domain, for instance).
    #[error("cannot transform coordinates from {from} to WGS84: {why}")]
    Transform { from: String, why: String },
}

/// A coordinate reference system: what a cloud's x, y (and z) mean on the Earth.
///
/// Serialised (the `crs.json` sidecars of the stages) as `{epsg, definition, proj4}`; a
/// deserialised value is checked again as [`Crs::parse`] would check it.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(try_from = "CrsFields")]
pub struct Crs {
    /// Its EPSG code, when it has one.
    pub epsg: Option<u32>,
    /// The definition as given or read (WKT, a PROJ string, or the EPSG registry's WKT).
    pub definition: String,
    /// The PROJ string `proj4rs` transforms with.
    #[serde(rename = "proj4")]
    proj: String,
}

/// [`Crs`] as read from JSON, before its PROJ string is checked.
#[derive(serde::Deserialize)]
struct CrsFields {
    epsg: Option<u32>,
    definition: String,
    proj4: String,
}

impl TryFrom<CrsFields> for Crs {
    type Error = CrsError;

    fn try_from(f: CrsFields) -> Result<Self, CrsError> {
        Proj::from_proj_string(&f.proj4).map_err(|e| {
            CrsError::Unreadable(format!("the PROJ string {:?} is not usable: {e}", f.proj4))
        })?;
        Ok(Self {
            epsg: f.epsg,
            definition: f.definition,
            proj: f.proj4,
        })
    }
}

/// Where a job's CRS came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CrsSource {
    /// The user named it (`params.crs`, `--crs`); it overrides what the file declares.
    Given,
    /// The LiDAR file declares it (LAS/LAZ projection records).
    File,
}

/// What every output says about its coordinates: the `crs.json` sidecar written beside
/// trees.csv, in the stages' folders and in results. `crs` is `None` when neither the file nor
/// the user named one; `note` then says what that means and how to give one.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CrsRecord {
    /// `EPSG:32649`, `custom (…)`, or null when unknown.
    pub label: Option<String>,
    /// Where it came from; null when unknown.
    pub source: Option<CrsSource>,
    /// The CRS itself; null when unknown.
    pub crs: Option<Crs>,
    /// What a reader should know (an unknown CRS, a declaration the user overrode, a
    /// declaration that could not be read).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

impl CrsRecord {
    /// The record of a known (or unknown) CRS from `source`, with no notes.
    pub fn new(crs: Option<Crs>, source: CrsSource) -> Self {
        Self {
            label: crs.as_ref().map(Crs::label),
            source: crs.as_ref().map(|_| source),
            crs,
            notes: Vec::new(),
        }
    }

    /// The record of a cloud with no known CRS, its note saying so.
    pub fn unknown(why: &str) -> Self {
        Self {
            label: None,
            source: None,
            crs: None,
            notes: vec![format!(
                "{why}; coordinates are the file's own and cannot be placed on the Earth. \
                 Give the CRS with the job's params.crs or --crs (EPSG:<code>, WKT or a PROJ \
                 string)"
            )],
        }
    }
}

/// The CRS of a job's or command's cloud: `given` (the user's `params.crs` / `--crs`)
/// overrides what the file declares (`declared`, from [`crate::io::pointcloud::declared_crs`]).
/// An unreadable declaration is a note, not an error, when nothing overrides it: the inventory
/// is still measured, only not placed on the Earth. A CRS in degrees is refused, as is a given
/// CRS that does not parse.
pub fn resolve(
    given: Option<&str>,
    declared: Result<Option<Crs>, CrsError>,
) -> Result<CrsRecord, CrsError> {
    let mut record = match (given, declared) {
        (Some(text), declared) => {
            let crs = Crs::parse_projected(text)?;
            let mut r = CrsRecord::new(Some(crs.clone()), CrsSource::Given);
            match declared {
                Ok(Some(d)) if d.epsg.is_some() && d.epsg == crs.epsg => {}
                Ok(Some(d)) if d.definition == crs.definition => {}
                Ok(Some(d)) => r.notes.push(format!(
                    "the file declares {}; the given {} overrides it",
                    d.label(),
                    crs.label()
                )),
                Ok(None) => {}
                Err(e) => r.notes.push(format!(
                    "the file's own CRS could not be read ({e}); the given one is used"
                )),
            }
            r
        }
        (None, Ok(Some(crs))) => CrsRecord::new(Some(crs), CrsSource::File),
        (None, Ok(None)) => CrsRecord::unknown("the LiDAR file declares no CRS"),
        (None, Err(e)) => CrsRecord::unknown(&format!("the LiDAR file's CRS is unreadable ({e})")),
    };
    if let Some(crs) = record.crs.as_ref().filter(|c| c.is_geographic()) {
        return Err(CrsError::Geographic(crs.label()));
    }
    record.notes.shrink_to_fit();
    Ok(record)
}

/// The file name of the CRS sidecar every folder of georeferenced outputs holds.
pub const CRS_FILE: &str = "crs.json";

impl Crs {
    /// The CRS with EPSG code `code`.
    pub fn from_epsg(code: u32) -> Result<Self, CrsError> {
        let code16 = u16::try_from(code).map_err(|_| CrsError::UnknownEpsg(code))?;
        let def = crs_definitions::from_code(code16).ok_or(CrsError::UnknownEpsg(code))?;
        Ok(Self {
            epsg: Some(code),
            definition: def.wkt.to_string(),
            proj: def.proj4.to_string(),
        })
    }

    /// Reads a CRS as a user writes one (`--crs`, the job's `crs` parameter): `EPSG:32649`
    /// (any case, also `epsg:32649` or a bare code), OGC WKT (1 or 2), or a PROJ string
    /// (`+proj=utm +zone=49 …`).
    pub fn parse(text: &str) -> Result<Self, CrsError> {
        let text = text.trim();
        if text.is_empty() {
            return Err(CrsError::Unreadable("the CRS is empty".into()));
        }
        let code = text
            .get(..5)
            .filter(|p| p.eq_ignore_ascii_case("epsg:"))
            .map_or(text, |_| &text[5..]);
        if let Ok(code) = code.trim().parse::<u32>() {
            return Self::from_epsg(code);
        }
        if text.starts_with('+') {
            Proj::from_proj_string(text).map_err(|e| {
                CrsError::Unreadable(format!("the PROJ string {text:?} is not usable: {e}"))
            })?;
            return Ok(Self {
                epsg: None,
                definition: text.to_string(),
                proj: text.to_string(),
            });
        }
        if text.contains('[') {
            return Self::from_wkt(text);
        }
        Err(CrsError::Unreadable(format!(
            "{text:?} is not a CRS: give EPSG:<code>, WKT or a PROJ string (+proj=…)"
        )))
    }

    /// [`Crs::parse`], refusing a CRS in degrees ([`CrsError::Geographic`]): what a cloud Sylva
    /// measures in metres can be in.
    pub fn parse_projected(text: &str) -> Result<Self, CrsError> {
        let crs = Self::parse(text)?;
        if crs.is_geographic() {
            return Err(CrsError::Geographic(crs.label()));
        }
        Ok(crs)
    }

    /// A CRS from OGC WKT: by its EPSG code when the outermost object carries one
    /// (`AUTHORITY["EPSG","32649"]` or `ID["EPSG",32649]`), else converted to a PROJ string.
    pub fn from_wkt(wkt: &str) -> Result<Self, CrsError> {
        let wkt = wkt.trim().trim_end_matches('\0').trim();
        if let Some(code) = outer_epsg(wkt)
            && let Ok(mut crs) = Self::from_epsg(code)
        {
            crs.definition = wkt.to_string();
            return Ok(crs);
        }
        let proj = proj4wkt::wkt_to_projstring(wkt)
            .map_err(|e| CrsError::Unreadable(format!("the WKT is not readable: {e}")))?
            .to_string();
        Proj::from_proj_string(&proj).map_err(|e| {
            CrsError::Unreadable(format!("the WKT's projection is not supported: {e}"))
        })?;
        Ok(Self {
            epsg: None,
            definition: wkt.to_string(),
            proj,
        })
    }

    /// A CRS from a GeoTIFF GeoKeyDirectory (the u16 words of LAS record 34735); `None` when
    /// the keys name no CRS.
    pub fn from_geokeys(words: &[u16]) -> Result<Option<Self>, CrsError> {
        // Header: key directory version, revision, minor revision, number of keys.
        let Some(&[_, _, _, count]) = words.get(..4) else {
            return Err(CrsError::Unreadable(
                "the GeoKeyDirectory is shorter than its header".into(),
            ));
        };
        let mut projected = None;
        let mut geographic = None;
        for k in 0..usize::from(count) {
            let Some(entry) = words.get(4 + 4 * k..8 + 4 * k) else {
                return Err(CrsError::Unreadable(format!(
                    "the GeoKeyDirectory declares {count} keys but holds {}",
                    (words.len() - 4) / 4
                )));
            };
            // (key id, TIFF tag location, count, value): location 0 keeps the value inline.
            let (key, location, value) = (entry[0], entry[1], entry[3]);
            if location != 0 {
                continue;
            }
            match key {
                PROJECTED_CS_TYPE_KEY => projected = Some(value),
                GEOGRAPHIC_TYPE_KEY => geographic = Some(value),
                _ => {}
            }
        }
        match projected.or(geographic) {
            None => Ok(None),
            Some(USER_DEFINED) => Err(CrsError::Unreadable(
                "the file's CRS is user-defined GeoTIFF keys, which Sylva does not read; \
                 give it with --crs (EPSG:<code>, WKT or a PROJ string)"
                    .into(),
            )),
            Some(code) => Self::from_epsg(u32::from(code)).map(Some),
        }
    }

    /// The CRS a LAS/LAZ file's records declare: WKT first (LAS 1.4 requires it for point
    /// formats 6–10), else GeoTIFF keys; `None` when the file names none. `records` yields
    /// (user id, record id, data) of every VLR and EVLR.
    pub fn from_las_records<'a>(
        records: impl IntoIterator<Item = (&'a str, u16, &'a [u8])>,
    ) -> Result<Option<Self>, CrsError> {
        let mut wkt = None;
        let mut keys = None;
        for (user, record, data) in records {
            if user.trim_end_matches('\0') != LAS_PROJECTION_USER_ID {
                continue;
            }
            match record {
                LAS_WKT_RECORD => wkt = Some(String::from_utf8_lossy(data).into_owned()),
                LAS_GEOKEY_RECORD => {
                    keys = Some(
                        data.chunks_exact(2)
                            .map(|b| u16::from_le_bytes([b[0], b[1]]))
                            .collect::<Vec<u16>>(),
                    )
                }
                _ => {}
            }
        }
        if let Some(wkt) = wkt.filter(|w| !w.trim_matches(['\0', ' ']).is_empty()) {
            return Self::from_wkt(&wkt).map(Some);
        }
        match keys {
            Some(words) => Self::from_geokeys(&words),
            None => Ok(None),
        }
    }

    /// How the CRS is named to people: `EPSG:32649`, or "custom" with the start of its
    /// definition.
    pub fn label(&self) -> String {
        match self.epsg {
            Some(code) => format!("EPSG:{code}"),
            None => {
                let short: String = self.definition.chars().take(60).collect();
                format!(
                    "custom ({short}{})",
                    if short.len() < self.definition.len() {
                        "…"
                    } else {
                        ""
                    }
                )
            }
        }
    }

    /// Whether coordinates are longitude and latitude in degrees (not metres).
    pub fn is_geographic(&self) -> bool {
        self.proj.contains("+proj=longlat") || self.proj.contains("+proj=latlong")
    }

    /// Transforms `points` (x, y in this CRS: metres, or degrees when geographic) to WGS84
    /// (longitude, latitude) in degrees, in place.
    pub fn to_wgs84(&self, points: &mut [(f64, f64)]) -> Result<(), CrsError> {
        self.transform(points, true)
    }

    /// Transforms WGS84 (longitude, latitude) in degrees to x, y in this CRS (metres, or
    /// degrees when geographic), in place: the inverse of [`Crs::to_wgs84`].
    pub fn from_wgs84(&self, points: &mut [(f64, f64)]) -> Result<(), CrsError> {
        self.transform(points, false)
    }

    fn transform(&self, points: &mut [(f64, f64)], to_wgs84: bool) -> Result<(), CrsError> {
        let fail = |why: String| CrsError::Transform {
            from: self.label(),
            why,
        };
        let this = Proj::from_proj_string(&self.proj).map_err(|e| fail(e.to_string()))?;
        let wgs84 = Proj::from_proj_string(crs_definitions::EPSG_4326.proj4)
            .map_err(|e| fail(e.to_string()))?;
        let (from, to, degrees_in, degrees_out) = if to_wgs84 {
            (&this, &wgs84, self.is_geographic(), true)
        } else {
            (&wgs84, &this, true, self.is_geographic())
        };
        for p in points.iter_mut() {
            let mut xyz = if degrees_in {
                (p.0.to_radians(), p.1.to_radians(), 0.0)
            } else {
                (p.0, p.1, 0.0)
            };
            proj4rs::transform::transform(from, to, &mut xyz).map_err(|e| fail(e.to_string()))?;
            let out = if degrees_out {
                (xyz.0.to_degrees(), xyz.1.to_degrees())
            } else {
                (xyz.0, xyz.1)
            };
            let on_earth =
                out.0.is_finite() && out.1.is_finite() && (!degrees_out || out.1.abs() <= 90.0);
            if !on_earth {
                return Err(fail(format!(
                    "({}, {}) has no place on the Earth",
                    p.0, p.1
                )));
            }
            *p = out;
        }
        Ok(())
    }
}

/// The EPSG code of a WKT's outermost object: its last `AUTHORITY["EPSG","N"]` (WKT 1) or
/// `ID["EPSG",N]` (WKT 2) at bracket depth 1.
fn outer_epsg(wkt: &str) -> Option<u32> {
    let mut depth = 0usize;
    let mut found = None;
    let bytes = wkt.as_bytes();
    for (i, &b) in bytes.iter().enumerate() {
        match b {
            b'[' | b'(' => depth += 1,
            b']' | b')' => depth = depth.saturating_sub(1),
            _ if depth == 1 => {
                let rest = &wkt[i..];
                let tail = rest
                    .strip_prefix("AUTHORITY[")
                    .or_else(|| rest.strip_prefix("ID["));
                if let Some(tail) = tail {
                    let inner = tail.split(']').next().unwrap_or("");
                    let mut parts = inner.split(',').map(|s| s.trim().trim_matches('"'));
                    if parts.next().is_some_and(|a| a.eq_ignore_ascii_case("EPSG")) {
                        found = parts.next().and_then(|c| c.parse().ok());
                    }
                }
            }
            _ => {}
        }
    }
    found
}

#[cfg(test)]
mod tests {
    use super::*;

    /// UTM zone 49N (EPSG:32649) on its central meridian: E 500 000 m lies on 111° E, and
    /// N 3 000 000 m at 27.1224696° N, the latitude whose WGS84 meridian arc is
    /// 3 000 000 / k0 (k0 = 0.9996), found independently by bisection on the arc's series.
    #[test]
    fn utm_49n_reaches_wgs84_degrees() {
        let crs = Crs::parse("EPSG:32649").expect("epsg");
        assert_eq!(crs.epsg, Some(32649));
        assert_eq!(crs.label(), "EPSG:32649");
        assert!(!crs.is_geographic());
        let mut p = [(500_000.0, 3_000_000.0), (600_000.0, 3_000_000.0)];
        crs.to_wgs84(&mut p).expect("transform");
        assert!((p[0].0 - 111.0).abs() < 1e-9, "{p:?}");
        assert!((p[0].1 - 27.122_469_6).abs() < 1e-6, "{p:?}");
        // 100 km east at 27° N is about 1.01° of longitude.
        assert!((p[1].0 - 112.0).abs() < 0.05 && p[1].1 < p[0].1, "{p:?}");
    }

    /// WGS84 back to UTM 49N lands where it started (to 1 mm), the anchor of the GPS starts
    /// of stage `register`.
    #[test]
    fn wgs84_to_utm_inverts_utm_to_wgs84() {
        let crs = Crs::parse("EPSG:32649").expect("epsg");
        let start = [(500_000.0, 3_000_000.0), (612_345.678, 3_987_654.321)];
        let mut p = start;
        crs.to_wgs84(&mut p).expect("forward");
        crs.from_wgs84(&mut p).expect("inverse");
        for (a, b) in p.iter().zip(&start) {
            assert!(
                (a.0 - b.0).abs() < 1e-3 && (a.1 - b.1).abs() < 1e-3,
                "{a:?} vs {b:?}"
            );
        }
        let mut q = [(111.0, 27.122_469_6)];
        crs.from_wgs84(&mut q).expect("inverse");
        assert!((q[0].0 - 500_000.0).abs() < 1e-3, "{q:?}");
        assert!((q[0].1 - 3_000_000.0).abs() < 0.1, "{q:?}");
    }

    #[test]
    fn users_write_a_crs_three_ways_and_bad_ones_are_refused_plainly() {
        assert_eq!(Crs::parse(" epsg:4326 ").expect("4326").epsg, Some(4326));
        assert_eq!(Crs::parse("25832").expect("code").epsg, Some(25832));
        let proj = Crs::parse("+proj=utm +zone=33 +datum=WGS84 +units=m +no_defs").expect("proj");
        assert_eq!(proj.epsg, None);
        let wkt = crs_definitions::from_code(32633).expect("def").wkt;
        assert_eq!(Crs::parse(wkt).expect("wkt").epsg, Some(32633));
        let err = Crs::parse("EPSG:99999999").expect_err("unknown");
        assert!(err.to_string().contains("EPSG:99999999"), "{err}");
        let err = Crs::parse("the plot's grid").expect_err("prose");
        assert!(err.to_string().contains("EPSG:<code>"), "{err}");
        assert!(Crs::parse("").is_err());
    }

    #[test]
    fn wkt_without_a_code_still_transforms() {
        // EPSG:32633's WKT with its authorities removed: read through proj4wkt.
        let wkt = crs_definitions::from_code(32633).expect("def").wkt;
        let bare: String = strip_authorities(wkt);
        let crs = Crs::from_wkt(&bare).expect("bare wkt");
        assert_eq!(crs.epsg, None);
        assert!(crs.label().starts_with("custom ("));
        let mut a = [(500_000.0, 5_000_000.0)];
        let mut b = a;
        crs.to_wgs84(&mut a).expect("bare");
        Crs::from_epsg(32633)
            .expect("epsg")
            .to_wgs84(&mut b)
            .expect("epsg");
        assert!(
            (a[0].0 - b[0].0).abs() < 1e-9 && (a[0].1 - b[0].1).abs() < 1e-9,
            "{a:?} {b:?}"
        );
    }

    fn strip_authorities(wkt: &str) -> String {
        let mut out = String::new();
        let mut rest = wkt;
        while let Some(i) = rest.find(",AUTHORITY[") {
            out.push_str(&rest[..i]);
            let after = &rest[i + 1..];
            let end = after.find(']').map_or(after.len(), |e| e + 1);
            rest = &after[end..];
        }
        out.push_str(rest);
        out
    }

    #[test]
    fn las_records_give_the_crs_by_wkt_or_geotiff_keys() {
        let wkt = crs_definitions::from_code(32649).expect("def").wkt;
        let crs = Crs::from_las_records([("LASF_Projection", LAS_WKT_RECORD, wkt.as_bytes())])
            .expect("wkt record")
            .expect("a crs");
        assert_eq!(crs.epsg, Some(32649));
        // GeoKeyDirectory: version 1.1.0, 3 keys: model type projected, raster type, 3072 = 32649.
        let words: [u16; 16] = [1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32649];
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        let crs = Crs::from_las_records([
            ("LASF_Spec", 3, &b"x"[..]),
            ("LASF_Projection\0", LAS_GEOKEY_RECORD, &bytes[..]),
        ])
        .expect("keys")
        .expect("a crs");
        assert_eq!(crs.epsg, Some(32649));
        assert_eq!(Crs::from_las_records([]).expect("none"), None);
        let user: [u16; 8] = [1, 1, 0, 1, 3072, 0, 1, USER_DEFINED];
        let bytes: Vec<u8> = user.iter().flat_map(|w| w.to_le_bytes()).collect();
        let err = Crs::from_las_records([("LASF_Projection", LAS_GEOKEY_RECORD, &bytes[..])])
            .expect_err("user-defined");
        assert!(err.to_string().contains("--crs"), "{err}");
        let short: Vec<u8> = [1u16, 1, 0, 5]
            .iter()
            .flat_map(|w| w.to_le_bytes())
            .collect();
        assert!(
            Crs::from_las_records([("LASF_Projection", LAS_GEOKEY_RECORD, &short[..])]).is_err()
        );
    }

    #[test]
    fn geographic_coordinates_pass_through_in_degrees() {
        let crs = Crs::from_epsg(4326).expect("4326");
        assert!(crs.is_geographic());
        let mut p = [(13.4, 52.5)];
        crs.to_wgs84(&mut p).expect("identity");
        assert!(
            (p[0].0 - 13.4).abs() < 1e-9 && (p[0].1 - 52.5).abs() < 1e-9,
            "{p:?}"
        );
    }

    #[test]
    fn a_given_crs_overrides_the_file_and_an_unknown_one_says_what_to_do() {
        let file = Crs::from_epsg(32649).expect("utm");
        let r = resolve(None, Ok(Some(file.clone()))).expect("file");
        assert_eq!(
            (r.label.as_deref(), r.source),
            (Some("EPSG:32649"), Some(CrsSource::File))
        );
        assert!(r.notes.is_empty());
        let r = resolve(Some("EPSG:32649"), Ok(Some(file.clone()))).expect("same");
        assert_eq!(r.source, Some(CrsSource::Given));
        assert!(r.notes.is_empty(), "{:?}", r.notes);
        let r = resolve(Some("epsg:32650"), Ok(Some(file))).expect("override");
        assert_eq!(r.label.as_deref(), Some("EPSG:32650"));
        assert!(r.notes[0].contains("declares EPSG:32649"), "{:?}", r.notes);
        let r = resolve(None, Ok(None)).expect("none");
        assert_eq!((r.crs.as_ref(), r.source), (None, None));
        assert!(r.notes[0].contains("declares no CRS") && r.notes[0].contains("--crs"));
        let bad = Err(CrsError::Unreadable("garbled".into()));
        let r = resolve(None, bad.clone()).expect("unreadable is a note");
        assert!(
            r.crs.is_none() && r.notes[0].contains("garbled"),
            "{:?}",
            r.notes
        );
        let r = resolve(Some("EPSG:25832"), bad).expect("given over garbled");
        assert_eq!(r.label.as_deref(), Some("EPSG:25832"));
        // Degrees are refused whoever names them; so is a given CRS that does not parse.
        let geo = resolve(None, Ok(Some(Crs::from_epsg(4326).expect("4326"))));
        assert!(matches!(geo, Err(CrsError::Geographic(_))), "{geo:?}");
        assert!(resolve(Some("EPSG:4326"), Ok(None)).is_err());
        assert!(resolve(Some("somewhere"), Ok(None)).is_err());
        // The record survives JSON, and a tampered PROJ string does not.
        let r = resolve(Some("EPSG:32633"), Ok(None)).expect("utm 33");
        let json = serde_json::to_value(&r).expect("json");
        let back: CrsRecord = serde_json::from_value(json.clone()).expect("back");
        assert_eq!(back, r);
        let mut bad = json;
        bad["crs"]["proj4"] = "+proj=nowhere".into();
        assert!(serde_json::from_value::<CrsRecord>(bad).is_err());
    }
}
