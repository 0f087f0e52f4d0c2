//! The articulated figure: one smooth closed primitive per body part, each
//! rigidly attached to an SMPL joint's local frame, each with its own
//! pattern.
//!
//! Limbs are capsules running from a joint to its child, so neighbouring
//! parts share a sphere at the joint and stay attached in every pose. The
//! torso and head are ellipsoids aligned with the joint axes (wider than
//! deep). Leaf joints (feet, head, hands) carry a part of their own, so
//! their rotations are visible.

use glam::{DMat3, DVec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::primitive::Shape;
use super::texture::{Rgb, TexPoint, Texture};
use crate::skeleton::{bone_align_rotation, Joints, N_JOINTS};

/// The SMPL rest joints hard-coded in A-NeRF (not metres: about 2.3× SMPL's
/// metric bones), `[24][3]`, y up, +x the subject's left. Transcribed from
/// `assets/skeleton/smpl_rest_pose_anerf.csv` (see its SOURCE.md).
pub const ANERF_REST_POSE: Joints = [
    [0.00000000e+00, 2.300_036_6e-9, -9.862_288e-8],
    [1.638_325_2e-1, -2.173_910_1e-1, -2.891_786e-2],
    [-1.578_554_2e-1, -2.147_617_3e-1, -2.096_420_2e-2],
    [-7.045_051e-3, 2.504_508_5e-1, -4.118_375e-2],
    [2.420_210_7e-1, -1.088_300_7, -3.149_621_2e-2],
    [-2.472_065_5e-1, -1.107_155, -3.069_707_4e-2],
    [3.951_258_5e-3, 5.948_491e-1, -4.037_542_6e-2],
    [2.126_806_2e-1, -1.993_823_5, -1.293_275_8e-1],
    [-2.108_575_3e-1, -2.012_188, -1.23002514e-01],
    [9.394_843e-3, 7.192_044e-1, 2.069_317_5e-2],
    [2.633_851_5e-1, -2.122_224_8, 1.467_756_2e-1],
    [-2.519_705_6e-1, -2.121_530_8, 1.604_504_7e-1],
    [3.837_791_7e-3, 1.225_924_5, -9.788_387e-2],
    [1.912_017_9e-1, 1.003_859_8, -6.219_645_2e-2],
    [-1.771_455_3e-1, 9.962_287e-1, -7.555_427_4e-2],
    [1.684_821e-2, 1.386_982_7, 2.440_485_5e-2],
    [4.019_851_7e-1, 1.079_284_2, -7.476_552e-2],
    [-3.988_254_7e-1, 1.075_238_7, -9.963_345_5e-2],
    [1.002_369_5, 1.052_172_2, -1.351_298e-1],
    [-9.867_286e-1, 1.045_150_5, -1.402_351_1e-1],
    [1.566_462_4, 1.069_618_9, -1.373_385_3e-1],
    [-1.569_464_8, 1.059_359_3, -1.539_058_2e-1],
    [1.752_821_1, 1.046_829_9, -1.682_310_7e-1],
    [-1.757_582, 1.042_550_8, -1.777_735_5e-1],
];

/// Metres per A-NeRF table unit for the synthetic subject: the factor the
/// golden reference case uses, giving a 1.65 m figure with a mean bone of
/// 0.19 m (SMPL's metric skeleton).
pub const REST_POSE_SCALE: f32 = 0.435;

/// The synthetic subject's rest pose: [`ANERF_REST_POSE`] moved so the
/// pelvis is exactly at the origin, times [`REST_POSE_SCALE`] (metres).
pub fn rest_pose() -> Joints {
    let r0 = ANERF_REST_POSE[0];
    ANERF_REST_POSE.map(|r| std::array::from_fn(|c| (r[c] - r0[c]) * REST_POSE_SCALE))
}

/// One body part.
#[derive(Clone, Debug, PartialEq)]
pub struct Part {
    pub name: &'static str,
    /// The joint whose local frame carries the part.
    pub joint: usize,
    /// Geometry in that joint's local frame (metres).
    pub shape: Shape,
    /// Part centre in the joint frame: the texture origin.
    pub centre: DVec3,
    /// Bone frame for textures, columns (across, across, along the bone).
    pub bone_axes: DMat3,
    /// Half the part's extent along its bone.
    pub half_len: f64,
    pub texture: Texture,
}

impl Part {
    /// Texture coordinates of a point given in the joint frame.
    pub fn tex_point(&self, p: DVec3) -> TexPoint {
        let local = p - self.centre;
        TexPoint {
            local,
            bone: self.bone_axes.transpose() * local,
            half_len: self.half_len,
        }
    }
}

/// The whole figure.
#[derive(Clone, Debug, PartialEq)]
pub struct Figure {
    pub parts: Vec<Part>,
}

/// Bone frame whose third column points along `v`.
fn bone_frame(v: DVec3) -> DMat3 {
    bone_align_rotation(v).transpose()
}

fn v3(a: [f32; 3]) -> DVec3 {
    DVec3::new(a[0] as f64, a[1] as f64, a[2] as f64)
}

/// The base palette, before the seed's jitter.
struct Palette {
    skin: Rgb,
    hair: Rgb,
    shirt: Rgb,
    shirt_dark: Rgb,
    accent: Rgb,
    light: Rgb,
    trousers: Rgb,
    trousers_light: Rgb,
    shoe: Rgb,
    ink: Rgb,
}

impl Palette {
    fn jittered(rng: &mut ChaCha8Rng) -> Palette {
        let mut j = |c: Rgb| -> Rgb {
            std::array::from_fn(|k| (c[k] + rng.gen_range(-0.06..0.06)).clamp(0.02, 0.98))
        };
        Palette {
            skin: j([0.86, 0.66, 0.52]),
            hair: j([0.18, 0.11, 0.07]),
            shirt: j([0.20, 0.45, 0.78]),
            shirt_dark: j([0.10, 0.22, 0.45]),
            accent: j([0.92, 0.78, 0.18]),
            light: j([0.93, 0.93, 0.88]),
            trousers: j([0.55, 0.18, 0.20]),
            trousers_light: j([0.85, 0.62, 0.45]),
            shoe: j([0.12, 0.12, 0.14]),
            ink: j([0.06, 0.06, 0.08]),
        }
    }
}

/// 15-bit glyph bitmaps with 5 to 10 inked cells, so every glyph shows.
fn glyphs(rng: &mut ChaCha8Rng, n: usize) -> Vec<u16> {
    (0..n)
        .map(|_| loop {
            let g: u16 = rng.gen::<u16>() & 0x7fff;
            if (5..=10).contains(&g.count_ones()) {
                break g;
            }
        })
        .collect()
}

impl Figure {
    /// Builds the figure on `rest` (metres, root-centred, y up). The seed
    /// jitters colours and draws the glyphs; the geometry depends on `rest`
    /// only.
    pub fn new(rest: &Joints, seed: u64) -> Figure {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5EED_F16E);
        let pal = Palette::jittered(&mut rng);
        let glyph_bits = glyphs(&mut rng, 6);
        let r = |j: usize| v3(rest[j]);
        let mut parts = Vec::with_capacity(N_JOINTS);

        // Torso and head: ellipsoids in joint axes (x wide, z deep).
        let ellipsoid = |name, joint, centre: DVec3, radii: DVec3, along, texture| Part {
            name,
            joint,
            shape: Shape::Ellipsoid {
                centre,
                axes: DMat3::IDENTITY,
                radii,
            },
            centre,
            bone_axes: bone_frame(along),
            half_len: radii.y,
            texture,
        };
        parts.push(ellipsoid(
            "pelvis",
            0,
            DVec3::new(0.0, -0.035, -0.01),
            DVec3::new(0.16, 0.105, 0.11),
            DVec3::Y,
            Texture::Belt {
                base: pal.trousers,
                band: pal.accent,
                y0: 0.045,
                y1: 0.09,
            },
        ));
        parts.push(ellipsoid(
            "abdomen",
            3,
            (r(6) - r(3)) * 0.5,
            DVec3::new(0.145, 0.10, 0.105),
            r(6) - r(3),
            Texture::Checker {
                a: pal.shirt,
                b: pal.light,
                size: 0.045,
            },
        ));
        parts.push(ellipsoid(
            "lower_chest",
            6,
            (r(9) - r(6)) * 0.5,
            DVec3::new(0.155, 0.09, 0.11),
            r(9) - r(6),
            Texture::Gradient {
                a: pal.shirt_dark,
                b: pal.shirt,
            },
        ));
        parts.push(ellipsoid(
            "chest",
            9,
            DVec3::new(0.0, 0.07, -0.02),
            DVec3::new(0.17, 0.13, 0.11),
            r(12) - r(9),
            Texture::Glyphs {
                base: pal.light,
                base_low: pal.shirt,
                ink: pal.ink,
                cell: 0.018,
                glyphs: glyph_bits,
                per_row: 3,
            },
        ));
        parts.push(ellipsoid(
            "head",
            15,
            DVec3::new(0.0, 0.05, 0.0),
            DVec3::new(0.085, 0.11, 0.095),
            DVec3::Y,
            Texture::Face {
                skin: pal.skin,
                hair: pal.hair,
                features: pal.ink,
            },
        ));

        // Limbs: capsules from a joint towards its child.
        let capsule = |name, joint, a: DVec3, b: DVec3, radius, texture| Part {
            name,
            joint,
            shape: Shape::Capsule { a, b, radius },
            centre: (a + b) * 0.5,
            bone_axes: bone_frame(b - a),
            half_len: (b - a).length() * 0.5,
            texture,
        };
        parts.push(capsule(
            "neck",
            12,
            DVec3::new(0.0, -0.03, 0.0),
            r(15) - r(12),
            0.05,
            Texture::Solid(pal.skin),
        ));
        for (side, [hip, knee, collar, shoulder, elbow, wrist, hand]) in [
            ("left", [1, 4, 13, 16, 18, 20, 22]),
            ("right", [2, 5, 14, 17, 19, 21, 23]),
        ] {
            let left = side == "left";
            let bone = |j: usize, c: usize| r(c) - r(j);
            parts.push(capsule(
                if left { "left_thigh" } else { "right_thigh" },
                hip,
                DVec3::ZERO,
                bone(hip, knee),
                0.07,
                Texture::Stripes {
                    a: pal.trousers,
                    b: pal.trousers_light,
                    count: 10,
                },
            ));
            parts.push(capsule(
                if left { "left_shin" } else { "right_shin" },
                knee,
                DVec3::ZERO,
                bone(knee, knee + 3),
                0.052,
                Texture::Gradient {
                    a: pal.trousers,
                    b: pal.trousers_light,
                },
            ));
            parts.push(capsule(
                if left { "left_collar" } else { "right_collar" },
                collar,
                DVec3::ZERO,
                bone(collar, shoulder),
                0.05,
                Texture::Solid(pal.shirt),
            ));
            parts.push(capsule(
                if left {
                    "left_upper_arm"
                } else {
                    "right_upper_arm"
                },
                shoulder,
                DVec3::ZERO,
                bone(shoulder, elbow),
                0.045,
                Texture::Rings {
                    a: pal.shirt,
                    b: pal.accent,
                    period: 0.06,
                },
            ));
            parts.push(capsule(
                if left {
                    "left_forearm"
                } else {
                    "right_forearm"
                },
                elbow,
                DVec3::ZERO,
                bone(elbow, wrist),
                0.037,
                Texture::Gradient {
                    a: pal.skin,
                    b: pal.trousers_light,
                },
            ));
            let palm = bone(wrist, hand);
            parts.push(capsule(
                if left { "left_palm" } else { "right_palm" },
                wrist,
                palm * 0.25,
                palm,
                0.03,
                Texture::Solid(pal.skin),
            ));
            // Fingers hang off the hand joint (a leaf), along the palm.
            let dir = palm.normalize();
            parts.push(capsule(
                if left {
                    "left_fingers"
                } else {
                    "right_fingers"
                },
                hand,
                DVec3::ZERO,
                dir * 0.05,
                0.024,
                Texture::Solid(pal.skin),
            ));
        }
        for (side, [ankle, foot]) in [("left", [7, 10]), ("right", [8, 11])] {
            let left = side == "left";
            let v = r(foot) - r(ankle);
            let axes = bone_frame(v);
            let centre = v * 0.5;
            parts.push(Part {
                name: if left { "left_foot" } else { "right_foot" },
                joint: ankle,
                shape: Shape::Ellipsoid {
                    centre,
                    axes,
                    radii: DVec3::new(0.045, 0.045, v.length() * 0.5 + 0.03),
                },
                centre,
                bone_axes: axes,
                half_len: v.length() * 0.5 + 0.03,
                texture: Texture::Shoe {
                    upper: pal.shoe,
                    sole: pal.light,
                    sole_y: -0.02,
                },
            });
            // Toe cap on the foot joint (a leaf), pointing along the foot.
            let dir = v.normalize();
            parts.push(capsule(
                if left { "left_toes" } else { "right_toes" },
                foot,
                DVec3::ZERO,
                dir * 0.04,
                0.035,
                Texture::Shoe {
                    upper: pal.shoe,
                    sole: pal.light,
                    sole_y: -0.015,
                },
            ));
        }
        Figure { parts }
    }
}
