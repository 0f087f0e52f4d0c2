//! Smooth closed primitives (capsules and oriented ellipsoids) with exact
//! ray intersection, an inside test and surface normals. All coordinates
//! are in the owning joint's local frame (metres).

use glam::{DMat3, DVec3};

/// A solid primitive.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// All points within `radius` of the segment `a → b`.
    Capsule { a: DVec3, b: DVec3, radius: f64 },
    /// `{ p : |diag(1/radii)·axesᵀ·(p − centre)| ≤ 1 }`; the columns of
    /// `axes` are the ellipsoid's orthonormal principal directions.
    Ellipsoid {
        centre: DVec3,
        axes: DMat3,
        radii: DVec3,
    },
}

impl Shape {
    /// Smallest parameter `t > 0` at which the ray `o + t·d` enters the
    /// solid, if it does. `d` need not be unit length.
    pub fn intersect(&self, o: DVec3, d: DVec3) -> Option<f64> {
        match *self {
            Shape::Capsule { a, b, radius } => capsule_hit(o, d, a, b, radius),
            Shape::Ellipsoid {
                centre,
                axes,
                radii,
            } => {
                // In the ellipsoid's normalised frame it is the unit sphere.
                let o = (axes.transpose() * (o - centre)) / radii;
                let d = (axes.transpose() * d) / radii;
                sphere_hit(o, d, DVec3::ZERO, 1.0)
            }
        }
    }

    /// Whether `p` lies inside or on the surface.
    pub fn contains(&self, p: DVec3) -> bool {
        match *self {
            Shape::Capsule { a, b, radius } => {
                (p - closest_on_segment(p, a, b)).length_squared() <= radius * radius
            }
            Shape::Ellipsoid {
                centre,
                axes,
                radii,
            } => ((axes.transpose() * (p - centre)) / radii).length_squared() <= 1.0,
        }
    }

    /// Outward unit normal at a surface point `p`.
    pub fn normal(&self, p: DVec3) -> DVec3 {
        match *self {
            Shape::Capsule { a, b, .. } => (p - closest_on_segment(p, a, b)).normalize_or_zero(),
            Shape::Ellipsoid {
                centre,
                axes,
                radii,
            } => {
                // Gradient of the implicit function |q/r|², q = axesᵀ(p − c).
                let q = axes.transpose() * (p - centre);
                (axes * (q / (radii * radii))).normalize_or_zero()
            }
        }
    }

    /// Centre and radius of a sphere enclosing the solid.
    pub fn bounding_sphere(&self) -> (DVec3, f64) {
        match *self {
            Shape::Capsule { a, b, radius } => ((a + b) * 0.5, (b - a).length() * 0.5 + radius),
            Shape::Ellipsoid { centre, radii, .. } => (centre, radii.max_element()),
        }
    }
}

fn closest_on_segment(p: DVec3, a: DVec3, b: DVec3) -> DVec3 {
    let ab = b - a;
    let len2 = ab.length_squared();
    if len2 == 0.0 {
        return a;
    }
    a + ab * ((p - a).dot(ab) / len2).clamp(0.0, 1.0)
}

/// Entry parameter of a ray into a sphere (centre `c`, radius `r`).
fn sphere_hit(o: DVec3, d: DVec3, c: DVec3, r: f64) -> Option<f64> {
    let oc = o - c;
    let a = d.length_squared();
    let b = oc.dot(d);
    let cc = oc.length_squared() - r * r;
    let disc = b * b - a * cc;
    if disc < 0.0 || a == 0.0 {
        return None;
    }
    let s = disc.sqrt();
    // Nearest positive root: the entry point, or the exit if the origin is
    // inside (cameras never are, but stay well-defined).
    let t0 = (-b - s) / a;
    let t1 = (-b + s) / a;
    if t0 > 0.0 {
        Some(t0)
    } else if t1 > 0.0 {
        Some(t1)
    } else {
        None
    }
}

/// Entry parameter of a ray into a capsule: the nearest hit among the
/// finite cylinder's side and the two end spheres. The solid is their
/// union, so the first surface crossing is the minimum over the pieces.
fn capsule_hit(o: DVec3, d: DVec3, a: DVec3, b: DVec3, r: f64) -> Option<f64> {
    let mut best: Option<f64> = None;
    let mut take = |t: Option<f64>| {
        if let Some(t) = t {
            if best.is_none_or(|b| t < b) {
                best = Some(t);
            }
        }
    };
    take(sphere_hit(o, d, a, r));
    take(sphere_hit(o, d, b, r));
    let axis = b - a;
    let len = axis.length();
    if len > 0.0 {
        let u = axis / len;
        // Project out the axis: a 2-D circle problem for the side.
        let oa = o - a;
        let dp = d - u * d.dot(u);
        let op = oa - u * oa.dot(u);
        let qa = dp.length_squared();
        let qb = op.dot(dp);
        let qc = op.length_squared() - r * r;
        let disc = qb * qb - qa * qc;
        if qa > 0.0 && disc >= 0.0 {
            let s = disc.sqrt();
            for t in [(-qb - s) / qa, (-qb + s) / qa] {
                let h = (oa + d * t).dot(u);
                if t > 0.0 && (0.0..=len).contains(&h) {
                    take(Some(t));
                    break;
                }
            }
        }
    }
    best
}
