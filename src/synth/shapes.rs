//! The ray-traceable primitives of a synthetic plot and their exact ray intersections.
//!
//! All coordinates are metres in the scene's local frame (z up, origin near the plot centre),
//! in `f32`: the plot spans less than 200 m, so `f32` keeps ~10 µm precision. Quadratics are
//! solved about the ray's point of closest approach to the primitive, which removes the
//! catastrophic cancellation a far ray (80 m) and a thin twig (1 cm) would otherwise cause.

use glam::Vec3;

/// A ray-parameter interval (metres along a unit direction).
#[derive(Debug, Clone, Copy)]
pub struct Interval {
    pub min: f32,
    pub max: f32,
}

/// A tapered cylinder with elliptical cross-sections (a truncated elliptical cone).
///
/// Local frame: `axis` from `origin` over `len` metres, `e1`, `e2` spanning the cross-section.
/// At axial distance z the section is an ellipse with semi-axes `a·r(z)` along `e1` and
/// `b·r(z)` along `e2`, with `r(z) = r0 + k·z`. Caps are not modelled (segments are chained,
/// stem bases sit below ground, twig tips are tiny).
#[derive(Debug, Clone, Copy)]
pub struct Cone {
    pub origin: Vec3,
    pub e1: Vec3,
    pub e2: Vec3,
    pub axis: Vec3,
    pub a: f32,
    pub b: f32,
    pub r0: f32,
    pub k: f32,
    pub len: f32,
    /// Axial distance of `origin` from the start of the stem or branch (metres), so that bark
    /// texture runs on across segments.
    pub s0: f32,
}

/// A flat, two-sided disc (a leaf).
#[derive(Debug, Clone, Copy)]
pub struct Disc {
    pub center: Vec3,
    pub normal: Vec3,
    pub radius: f32,
}

/// An ellipsoid rotated about the vertical only (a stone, partly buried).
#[derive(Debug, Clone, Copy)]
pub struct Ellipsoid {
    pub center: Vec3,
    /// (cos, sin) of the yaw of the first semi-axis.
    pub yaw: (f32, f32),
    pub radii: Vec3,
}

/// A terrain triangle: vertex `v0` and edges `e1 = v1 - v0`, `e2 = v2 - v0`.
#[derive(Debug, Clone, Copy)]
pub struct Triangle {
    pub v0: Vec3,
    pub e1: Vec3,
    pub e2: Vec3,
}

/// One primitive shape.
#[derive(Debug, Clone, Copy)]
pub enum Shape {
    Cone(Cone),
    Disc(Disc),
    Ellipsoid(Ellipsoid),
    Triangle(Triangle),
}

/// Smallest root of A s² + B s + C = 0 with s + base inside `span`, numerically stable.
fn quadratic_hit(
    a: f32,
    b: f32,
    c: f32,
    base: f32,
    span: Interval,
    ok: impl Fn(f32) -> bool,
) -> Option<f32> {
    let (s1, s2) = if a.abs() < 1e-12 {
        if b.abs() < 1e-20 {
            return None;
        }
        let s = -c / b;
        (s, s)
    } else {
        let disc = b * b - 4.0 * a * c;
        if disc < 0.0 {
            return None;
        }
        let q = -0.5 * (b + disc.sqrt().copysign(b));
        let (x1, x2) = if q == 0.0 { (0.0, 0.0) } else { (q / a, c / q) };
        (x1.min(x2), x1.max(x2))
    };
    [s1, s2]
        .into_iter()
        .map(|s| s + base)
        .find(|&t| t > span.min && t < span.max && ok(t))
}

impl Cone {
    fn local(&self, p: Vec3) -> Vec3 {
        let q = p - self.origin;
        Vec3::new(
            q.dot(self.e1) / self.a,
            q.dot(self.e2) / self.b,
            q.dot(self.axis),
        )
    }

    /// Nearest hit distance in `span`.
    pub fn intersect(&self, o: Vec3, d: Vec3, span: Interval) -> Option<f32> {
        let p = self.local(o);
        let dl = Vec3::new(
            d.dot(self.e1) / self.a,
            d.dot(self.e2) / self.b,
            d.dot(self.axis),
        );
        let dd = dl.x * dl.x + dl.y * dl.y;
        if dd < 1e-12 {
            return None;
        }
        let tc = -(p.x * dl.x + p.y * dl.y) / dd;
        let q = p + dl * tc;
        let r = self.r0 + self.k * q.z;
        let kz = self.k * dl.z;
        let a = dd - kz * kz;
        let b = -2.0 * r * kz;
        let c = q.x * q.x + q.y * q.y - r * r;
        let (len, r0, k) = (self.len, self.r0, self.k);
        quadratic_hit(a, b, c, tc, span, |t| {
            let z = p.z + dl.z * t;
            (0.0..=len).contains(&z) && r0 + k * z > 0.0
        })
    }

    /// Outward unit normal at surface point `p`.
    pub fn normal(&self, p: Vec3) -> Vec3 {
        let q = self.local(p);
        let r = self.r0 + self.k * q.z;
        let n = self.e1 * (q.x / self.a) + self.e2 * (q.y / self.b) - self.axis * (self.k * r);
        n.normalize_or(self.e1)
    }

    /// (angle around the axis in radians, axial distance from the stem start in metres).
    pub fn surface_coords(&self, p: Vec3) -> (f32, f32) {
        let q = self.local(p);
        (q.y.atan2(q.x), q.z + self.s0)
    }

    fn bounds(&self) -> (Vec3, Vec3) {
        let ext = |r: f32| {
            let (u, v) = (self.e1 * (self.a * r), self.e2 * (self.b * r));
            Vec3::new(u.x.hypot(v.x), u.y.hypot(v.y), u.z.hypot(v.z))
        };
        let end = self.origin + self.axis * self.len;
        let (x0, x1) = (ext(self.r0), ext(self.r0 + self.k * self.len));
        (
            (self.origin - x0).min(end - x1),
            (self.origin + x0).max(end + x1),
        )
    }
}

impl Disc {
    pub fn intersect(&self, o: Vec3, d: Vec3, span: Interval) -> Option<f32> {
        let den = d.dot(self.normal);
        if den.abs() < 1e-9 {
            return None;
        }
        let t = (self.center - o).dot(self.normal) / den;
        if t <= span.min || t >= span.max {
            return None;
        }
        let off = o + d * t - self.center;
        (off.length_squared() <= self.radius * self.radius).then_some(t)
    }

    fn bounds(&self) -> (Vec3, Vec3) {
        let n2 = self.normal * self.normal;
        let ext = (Vec3::ONE - n2).max(Vec3::ZERO).powf(0.5) * self.radius;
        (self.center - ext, self.center + ext)
    }
}

impl Ellipsoid {
    fn local(&self, v: Vec3) -> Vec3 {
        let (c, s) = self.yaw;
        Vec3::new(c * v.x + s * v.y, -s * v.x + c * v.y, v.z) / self.radii
    }

    pub fn intersect(&self, o: Vec3, d: Vec3, span: Interval) -> Option<f32> {
        let p = self.local(o - self.center);
        let dl = self.local(d);
        let a = dl.length_squared();
        if a < 1e-20 {
            return None;
        }
        let tc = -p.dot(dl) / a;
        let q = p + dl * tc;
        quadratic_hit(a, 0.0, q.length_squared() - 1.0, tc, span, |_| true)
    }

    pub fn normal(&self, p: Vec3) -> Vec3 {
        let q = self.local(p - self.center) / self.radii;
        let (c, s) = self.yaw;
        Vec3::new(c * q.x - s * q.y, s * q.x + c * q.y, q.z).normalize_or(Vec3::Z)
    }

    fn bounds(&self) -> (Vec3, Vec3) {
        let (c, s) = self.yaw;
        let ex = (c * self.radii.x).hypot(s * self.radii.y);
        let ey = (s * self.radii.x).hypot(c * self.radii.y);
        let e = Vec3::new(ex, ey, self.radii.z);
        (self.center - e, self.center + e)
    }
}

impl Triangle {
    /// Möller–Trumbore with a tiny tolerance on the barycentric bounds so rays cannot slip
    /// between neighbouring terrain triangles.
    pub fn intersect(&self, o: Vec3, d: Vec3, span: Interval) -> Option<f32> {
        const EPS: f32 = 1e-5;
        let p = d.cross(self.e2);
        let det = self.e1.dot(p);
        if det.abs() < 1e-12 {
            return None;
        }
        let inv = 1.0 / det;
        let s = o - self.v0;
        let u = s.dot(p) * inv;
        if !(-EPS..=1.0 + EPS).contains(&u) {
            return None;
        }
        let q = s.cross(self.e1);
        let v = d.dot(q) * inv;
        if v < -EPS || u + v > 1.0 + EPS {
            return None;
        }
        let t = self.e2.dot(q) * inv;
        (t > span.min && t < span.max).then_some(t)
    }

    /// Upward unit normal.
    pub fn normal(&self) -> Vec3 {
        let n = self.e1.cross(self.e2).normalize_or(Vec3::Z);
        if n.z < 0.0 { -n } else { n }
    }

    fn bounds(&self) -> (Vec3, Vec3) {
        let (v1, v2) = (self.v0 + self.e1, self.v0 + self.e2);
        (self.v0.min(v1).min(v2), self.v0.max(v1).max(v2))
    }
}

impl Shape {
    /// Nearest hit distance in `span` along the unit direction `d` from `o`.
    #[inline]
    pub fn intersect(&self, o: Vec3, d: Vec3, span: Interval) -> Option<f32> {
        match self {
            Shape::Cone(c) => c.intersect(o, d, span),
            Shape::Disc(c) => c.intersect(o, d, span),
            Shape::Ellipsoid(c) => c.intersect(o, d, span),
            Shape::Triangle(c) => c.intersect(o, d, span),
        }
    }

    /// Geometric unit normal at surface point `p` (discs: their stored normal, either side).
    pub fn normal(&self, p: Vec3) -> Vec3 {
        match self {
            Shape::Cone(c) => c.normal(p),
            Shape::Disc(c) => c.normal,
            Shape::Ellipsoid(c) => c.normal(p),
            Shape::Triangle(c) => c.normal(),
        }
    }

    /// Axis-aligned bounds (min, max), conservative and tight for these shapes.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        match self {
            Shape::Cone(c) => c.bounds(),
            Shape::Disc(c) => c.bounds(),
            Shape::Ellipsoid(c) => c.bounds(),
            Shape::Triangle(c) => c.bounds(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ALL: Interval = Interval {
        min: 0.0,
        max: f32::INFINITY,
    };

    fn column(r: f32, a: f32, b: f32) -> Cone {
        Cone {
            origin: Vec3::ZERO,
            e1: Vec3::X,
            e2: Vec3::Y,
            axis: Vec3::Z,
            a,
            b,
            r0: r,
            k: 0.0,
            len: 2.0,
            s0: 0.0,
        }
    }

    #[test]
    fn cone_hits_elliptical_section_from_far_away() {
        let c = column(0.1, 1.0, 0.9);
        let t = c
            .intersect(Vec3::new(-80.0, 0.0, 1.0), Vec3::X, ALL)
            .unwrap_or(-1.0);
        assert!((t - 79.9).abs() < 1e-4, "{t}");
        let t = c
            .intersect(Vec3::new(0.0, -80.0, 1.0), Vec3::Y, ALL)
            .unwrap_or(-1.0);
        assert!((t - 79.91).abs() < 1e-4, "{t}");
        assert!(
            c.intersect(Vec3::new(-80.0, 0.0, 2.5), Vec3::X, ALL)
                .is_none()
        );
        let n = c.normal(Vec3::new(-0.1, 0.0, 1.0));
        assert!((n - Vec3::NEG_X).length() < 1e-5);
    }

    #[test]
    fn tapered_cone_radius_follows_height() {
        let mut c = column(0.2, 1.0, 1.0);
        c.k = -0.05;
        let t = c
            .intersect(Vec3::new(-5.0, 0.0, 2.0), Vec3::X, ALL)
            .unwrap_or(-1.0);
        assert!((t - 4.9).abs() < 1e-5, "{t}");
    }

    #[test]
    fn disc_ellipsoid_triangle_hits() {
        let d = Disc {
            center: Vec3::new(0.0, 0.0, 3.0),
            normal: Vec3::Z,
            radius: 0.05,
        };
        assert_eq!(d.intersect(Vec3::ZERO, Vec3::Z, ALL), Some(3.0));
        assert!(
            d.intersect(Vec3::new(0.06, 0.0, 0.0), Vec3::Z, ALL)
                .is_none()
        );
        let e = Ellipsoid {
            center: Vec3::ZERO,
            yaw: (0.0, 1.0),
            radii: Vec3::new(2.0, 1.0, 0.5),
        };
        // Rotated by 90°: the 2 m semi-axis now lies along y.
        let t = e
            .intersect(Vec3::new(0.0, -10.0, 0.0), Vec3::Y, ALL)
            .unwrap_or(-1.0);
        assert!((t - 8.0).abs() < 1e-5, "{t}");
        let tri = Triangle {
            v0: Vec3::ZERO,
            e1: Vec3::X,
            e2: Vec3::Y,
        };
        assert_eq!(
            tri.intersect(Vec3::new(0.2, 0.2, 5.0), Vec3::NEG_Z, ALL),
            Some(5.0)
        );
        assert!(
            tri.intersect(Vec3::new(0.8, 0.8, 5.0), Vec3::NEG_Z, ALL)
                .is_none()
        );
    }
}
