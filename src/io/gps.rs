//! GPS positions of photos from their EXIF tags (JPEG, PNG, TIFF, HEIF, WebP), read with
//! the `kamadak-exif` crate, and the EXIF block that carries one (written by `sylva synth`
//! to make GPS-tagged test photos).
//!
//! A position is WGS84 longitude and latitude in degrees (EXIF GPSLongitude/GPSLatitude as
//! degrees, minutes, seconds with their E/W and N/S references) and the altitude in metres
//! (GPSAltitude; below sea level when GPSAltitudeRef is 1). EXIF does not say which
//! vertical datum the altitude uses (cameras mix ellipsoidal and sea-level heights), so
//! stage `register` takes heights from the terrain and uses the GPS positions horizontally
//! (docs/method.md, georeferenced starts).

use std::io::{BufReader, Cursor};
use std::path::Path;

use exif::{Field, In, Rational, Tag, Value};
use serde::{Deserialize, Serialize};

/// Where a photo was taken, WGS84.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GpsFix {
    /// Degrees east (negative west).
    pub lon: f64,
    /// Degrees north (negative south).
    pub lat: f64,
    /// Metres, in the camera's own vertical datum; `None` when the photo has none.
    pub alt: Option<f64>,
}

/// The GPS position in a photo's EXIF: `Ok(None)` when the file has no EXIF or no GPS
/// latitude and longitude; `Err` names what is malformed (an unreadable file, a position off
/// the Earth).
pub fn read_fix(path: &Path) -> Result<Option<GpsFix>, String> {
    let file = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let exif = match exif::Reader::new().read_from_container(&mut BufReader::new(file)) {
        Ok(x) => x,
        Err(exif::Error::NotFound(_)) | Err(exif::Error::BlankValue(_)) => return Ok(None),
        Err(e) => return Err(format!("EXIF: {e}")),
    };
    let degrees = |tag: Tag, reference: Tag, negative: u8| -> Result<Option<f64>, String> {
        let Some(f) = exif.get_field(tag, In::PRIMARY) else {
            return Ok(None);
        };
        let Value::Rational(v) = &f.value else {
            return Err(format!("EXIF {tag} is not three rationals"));
        };
        if v.is_empty() || v.iter().any(|r| r.denom == 0) {
            return Err(format!("EXIF {tag} is empty or divides by zero"));
        }
        let d = v
            .iter()
            .zip([1.0, 60.0, 3600.0])
            .map(|(r, div)| r.to_f64() / div)
            .sum::<f64>();
        let sign = match exif.get_field(reference, In::PRIMARY).map(|f| &f.value) {
            Some(Value::Ascii(a)) if a.first().and_then(|s| s.first()) == Some(&negative) => -1.0,
            _ => 1.0,
        };
        Ok(Some(sign * d))
    };
    let lat = degrees(Tag::GPSLatitude, Tag::GPSLatitudeRef, b'S')?;
    let lon = degrees(Tag::GPSLongitude, Tag::GPSLongitudeRef, b'W')?;
    let (Some(lat), Some(lon)) = (lat, lon) else {
        return Ok(None);
    };
    if !(lat.abs() <= 90.0 && lon.abs() <= 180.0) {
        return Err(format!("EXIF GPS position ({lat}, {lon}) is off the Earth"));
    }
    let alt = match exif
        .get_field(Tag::GPSAltitude, In::PRIMARY)
        .map(|f| &f.value)
    {
        Some(Value::Rational(v)) if v.first().is_some_and(|r| r.denom != 0) => {
            let below = matches!(
                exif.get_field(Tag::GPSAltitudeRef, In::PRIMARY).map(|f| &f.value),
                Some(Value::Byte(b)) if b.first() == Some(&1)
            );
            let a = v[0].to_f64();
            Some(if below { -a } else { a })
        }
        _ => None,
    };
    Ok(Some(GpsFix { lon, lat, alt }))
}

/// An EXIF block (TIFF structure, without the JPEG "Exif\0\0" header) holding `fix` as GPS
/// tags, to embed with the `image` crate's `set_exif_metadata`. Degrees are written as
/// whole degrees, whole minutes and seconds to 1e-4 s (3 mm), the altitude to 1 mm.
pub fn exif_block(fix: &GpsFix) -> Result<Vec<u8>, String> {
    let dms = |v: f64| {
        let v = v.abs();
        let d = v.floor();
        let m = ((v - d) * 60.0).floor();
        let s = ((v - d) * 60.0 - m) * 60.0;
        vec![
            Rational::from((d as u32, 1)),
            Rational::from((m as u32, 1)),
            Rational::from(((s * 1e4).round() as u32, 10_000)),
        ]
    };
    let ascii = |c: u8| Value::Ascii(vec![vec![c]]);
    let field = |tag: Tag, value: Value| Field {
        tag,
        ifd_num: In::PRIMARY,
        value,
    };
    let mut fields = vec![
        field(Tag::GPSVersionID, Value::Byte(vec![2, 3, 0, 0])),
        field(
            Tag::GPSLatitudeRef,
            ascii(if fix.lat < 0.0 { b'S' } else { b'N' }),
        ),
        field(Tag::GPSLatitude, Value::Rational(dms(fix.lat))),
        field(
            Tag::GPSLongitudeRef,
            ascii(if fix.lon < 0.0 { b'W' } else { b'E' }),
        ),
        field(Tag::GPSLongitude, Value::Rational(dms(fix.lon))),
    ];
    if let Some(a) = fix.alt {
        fields.push(field(
            Tag::GPSAltitudeRef,
            Value::Byte(vec![u8::from(a < 0.0)]),
        ));
        fields.push(field(
            Tag::GPSAltitude,
            Value::Rational(vec![Rational::from(((a.abs() * 1e3).round() as u32, 1000))]),
        ));
    }
    let mut writer = exif::experimental::Writer::new();
    for f in &fields {
        writer.push_field(f);
    }
    let mut out = Cursor::new(Vec::new());
    writer
        .write(&mut out, false)
        .map_err(|e| format!("EXIF: {e}"))?;
    Ok(out.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::ImageEncoder;

    fn jpeg_with(exif: Option<Vec<u8>>, path: &Path) {
        let mut out = Vec::new();
        let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 90);
        if let Some(e) = exif {
            enc.set_exif_metadata(e).expect("jpeg takes EXIF");
        }
        enc.write_image(&[90u8; 8 * 8 * 3], 8, 8, image::ExtendedColorType::Rgb8)
            .expect("encode");
        std::fs::write(path, out).expect("write");
    }

    #[test]
    fn a_written_position_reads_back_in_every_quadrant() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("a.jpg");
        for fix in [
            GpsFix {
                lon: 9.123_456_7,
                lat: 36.098_765_4,
                alt: Some(412.345),
            },
            GpsFix {
                lon: -122.5,
                lat: -33.25,
                alt: Some(-12.5),
            },
            GpsFix {
                lon: 0.000_01,
                lat: 0.5,
                alt: None,
            },
        ] {
            jpeg_with(Some(exif_block(&fix).expect("block")), &path);
            let back = read_fix(&path).expect("reads").expect("has a fix");
            // 1e-4 s of arc is 3 mm.
            assert!((back.lon - fix.lon).abs() < 1e-7, "{back:?} vs {fix:?}");
            assert!((back.lat - fix.lat).abs() < 1e-7, "{back:?} vs {fix:?}");
            match (back.alt, fix.alt) {
                (Some(a), Some(b)) => assert!((a - b).abs() < 1e-3, "{a} vs {b}"),
                (None, None) => {}
                other => panic!("altitude {other:?}"),
            }
        }
    }

    #[test]
    fn a_photo_without_gps_has_no_fix_and_garbage_is_an_error() {
        let dir = tempfile::tempdir().expect("tempdir");
        let plain = dir.path().join("plain.jpg");
        jpeg_with(None, &plain);
        assert_eq!(read_fix(&plain).expect("reads"), None);
        let junk = dir.path().join("junk.jpg");
        std::fs::write(
            &junk,
            b"\xff\xd8\xff\xe1\x00\x10Exif\0\0MM\0*\0\0\0\x08garbage",
        )
        .expect("w");
        assert!(read_fix(&junk).is_err());
        assert!(read_fix(&dir.path().join("missing.jpg")).is_err());
    }
}
