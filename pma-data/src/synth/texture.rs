//! Procedural albedo in bone-local coordinates.
//!
//! Each pattern is a function of a surface point expressed in its part's
//! frames, so it moves rigidly with the bone. Low-frequency patterns
//! (solids, gradients, a belt) sit beside high-frequency ones (rings,
//! longitudinal stripes, a 3-D checker, text-like glyphs, a face) because
//! the model's pose-dependent frequency modulation is what the scene has
//! to exercise. Edges are hard (no filtering): the renderer point-samples
//! one ray per pixel, exactly as the NeRF does.

use glam::DVec3;

/// Linear RGB in [0, 1].
pub type Rgb = [f64; 3];

/// A surface point in the frames a pattern may use.
#[derive(Clone, Copy, Debug)]
pub struct TexPoint {
    /// Offset from the part centre in the joint's axes (x: subject's left,
    /// y: up, z: forward in the rest pose), metres.
    pub local: DVec3,
    /// The same offset in the part's bone frame (z along the bone, x/y
    /// across), metres.
    pub bone: DVec3,
    /// Half the part's length along its bone (metres), for gradients.
    pub half_len: f64,
}

/// A surface pattern.
#[derive(Clone, Debug, PartialEq)]
pub enum Texture {
    Solid(Rgb),
    /// `a` at one end of the bone blending smoothly into `b` at the other.
    Gradient {
        a: Rgb,
        b: Rgb,
    },
    /// Bands across the bone, `period` metres apart.
    Rings {
        a: Rgb,
        b: Rgb,
        period: f64,
    },
    /// `count` stripes running along the bone, around its circumference.
    Stripes {
        a: Rgb,
        b: Rgb,
        count: u32,
    },
    /// 3-D checkerboard of `size`-metre cells in joint axes.
    Checker {
        a: Rgb,
        b: Rgb,
        size: f64,
    },
    /// Rows of 3×5-cell glyphs (`cell` metres) printed on the front
    /// (`local.z > 0`) over a vertical gradient.
    Glyphs {
        base: Rgb,
        base_low: Rgb,
        ink: Rgb,
        cell: f64,
        /// One 15-bit bitmap per glyph, row-major from the top-left cell.
        glyphs: Vec<u16>,
        per_row: usize,
    },
    /// Skin with two eyes and a mouth on the front, hair on top and back.
    Face {
        skin: Rgb,
        hair: Rgb,
        features: Rgb,
    },
    /// A low-frequency band (`band`, between heights `y0..y1`) on `base`.
    Belt {
        base: Rgb,
        band: Rgb,
        y0: f64,
        y1: f64,
    },
    /// A shoe: `upper` with a `sole` colour below `sole_y` (joint axes).
    Shoe {
        upper: Rgb,
        sole: Rgb,
        sole_y: f64,
    },
}

fn mix(a: Rgb, b: Rgb, t: f64) -> Rgb {
    std::array::from_fn(|c| a[c] + (b[c] - a[c]) * t)
}

fn pick(a: Rgb, b: Rgb, first: bool) -> Rgb {
    if first {
        a
    } else {
        b
    }
}

impl Texture {
    /// The albedo at a surface point.
    pub fn albedo(&self, p: &TexPoint) -> Rgb {
        match self {
            Texture::Solid(c) => *c,
            Texture::Gradient { a, b } => {
                let u = (p.bone.z / p.half_len.max(1e-9)).clamp(-1.0, 1.0);
                // Smoothstep over the whole part: the lowest frequency there is.
                let t = 0.5 + 0.5 * u;
                mix(*a, *b, t * t * (3.0 - 2.0 * t))
            }
            Texture::Rings { a, b, period } => {
                pick(*a, *b, (p.bone.z / period).rem_euclid(1.0) < 0.5)
            }
            Texture::Stripes { a, b, count } => {
                let phi = p.bone.y.atan2(p.bone.x) / std::f64::consts::TAU + 0.5;
                pick(*a, *b, ((phi * *count as f64).floor() as i64) % 2 == 0)
            }
            Texture::Checker { a, b, size } => {
                let q = p.local / *size;
                let parity = q.x.floor() as i64 + q.y.floor() as i64 + q.z.floor() as i64;
                pick(*a, *b, parity.rem_euclid(2) == 0)
            }
            Texture::Glyphs {
                base,
                base_low,
                ink,
                cell,
                glyphs,
                per_row,
            } => {
                let background = mix(*base_low, *base, (0.5 + 2.5 * p.local.y).clamp(0.0, 1.0));
                if p.local.z > 0.0 && glyph_ink(p.local.x, p.local.y, *cell, glyphs, *per_row) {
                    *ink
                } else {
                    background
                }
            }
            Texture::Face {
                skin,
                hair,
                features,
            } => {
                let l = p.local;
                if l.y > 0.07 || (l.z < 0.0 && l.y > -0.04) {
                    return *hair;
                }
                if l.z > 0.0 {
                    let eye = |x0: f64| (l.x - x0).hypot(l.y - 0.025) < 0.014;
                    let mouth = l.x.abs() < 0.028 && (-0.04..-0.028).contains(&l.y);
                    if eye(0.032) || eye(-0.032) || mouth {
                        return *features;
                    }
                }
                *skin
            }
            Texture::Belt { base, band, y0, y1 } => {
                pick(*band, *base, (*y0..*y1).contains(&p.local.y))
            }
            Texture::Shoe {
                upper,
                sole,
                sole_y,
            } => pick(*sole, *upper, p.local.y < *sole_y),
        }
    }
}

/// Whether `(x, y)` (front-facing plane, metres from the part centre) falls
/// on an inked cell. Glyphs are laid out in rows of `per_row`, centred
/// horizontally, the first row's top at y = +2.5 cells.
fn glyph_ink(x: f64, y: f64, cell: f64, glyphs: &[u16], per_row: usize) -> bool {
    if glyphs.is_empty() || per_row == 0 {
        return false;
    }
    // A glyph is 3 cells wide plus 1 cell of spacing; a line 5 tall plus 1.
    let width = (per_row * 4 - 1) as f64 * cell;
    let cx = ((x + 0.5 * width) / cell).floor();
    let cy = ((2.5 * cell - y) / cell).floor();
    if cx < 0.0 || cy < 0.0 {
        return false;
    }
    let (cx, cy) = (cx as usize, cy as usize);
    let (col, gx) = (cx / 4, cx % 4);
    let (row, gy) = (cy / 6, cy % 6);
    if col >= per_row || gx == 3 || gy == 5 {
        return false;
    }
    let Some(bits) = glyphs.get(row * per_row + col) else {
        return false;
    };
    bits >> (gy * 3 + gx) & 1 == 1
}
