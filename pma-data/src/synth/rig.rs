//! A ring of pinhole cameras around the subject, all looking at one point,
//! in the training world convention (head toward −y, ground plane x–z).

use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::camera::Camera;
use crate::error::Result;

/// Ring geometry (metres, world frame with −y up).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Ring {
    /// Horizontal distance from the y axis.
    pub radius: f64,
    /// Camera height: world y (negative is above the pelvis).
    pub height: f64,
    /// The seed moves each camera's height by up to ± this.
    pub height_jitter: f64,
    /// The point every camera looks at.
    pub target: [f64; 3],
    /// Vertical extent (metres) that fills the image height at the target.
    pub window: f64,
}

impl Default for Ring {
    fn default() -> Self {
        Ring {
            radius: 4.0,
            height: -0.35,
            height_jitter: 0.15,
            target: [0.0, 0.12, 0.0],
            window: 2.5,
        }
    }
}

/// `n` square `res`-pixel cameras evenly spaced in azimuth around the ring.
/// The seed rotates the whole ring (by less than one spacing) and jitters
/// the heights, so different seeds see the figure from different places.
pub fn ring_cameras(n: usize, res: usize, seed: u64, ring: &Ring) -> Result<Vec<Camera>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x0CA4_E2A5);
    let spacing = std::f64::consts::TAU / n.max(1) as f64;
    let offset = rng.gen_range(0.0..spacing);
    let target = DVec3::from(ring.target);
    // World up is −y: the head direction.
    let up = DVec3::NEG_Y;
    (0..n)
        .map(|k| {
            let theta = offset + spacing * k as f64;
            let height = ring.height + rng.gen_range(-1.0..1.0) * ring.height_jitter;
            let eye = DVec3::new(ring.radius * theta.sin(), height, ring.radius * theta.cos());
            // OpenGL axes: the camera looks along −z.
            let z = (eye - target).normalize();
            let x = up.cross(z).normalize();
            let y = z.cross(x);
            let focal = res as f64 * (eye - target).length() / ring.window;
            let c2w = [
                [x.x as f32, y.x as f32, z.x as f32, eye.x as f32],
                [x.y as f32, y.y as f32, z.y as f32, eye.y as f32],
                [x.z as f32, y.z as f32, z.z as f32, eye.z as f32],
                [0.0, 0.0, 0.0, 1.0],
            ];
            let centre = res as f32 / 2.0;
            Camera::new(res, res, focal as f32, focal as f32, centre, centre, c2w)
        })
        .collect()
}
