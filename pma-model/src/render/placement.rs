//! Coarse samples where the body is (`PassOptions::coarse_from_grid`): with an occupancy
//! grid, each ray's coarse samples are placed in the intervals along it that the grid marks
//! occupied, instead of evenly over its whole box interval.
//!
//! A ray is probed at [`PROBES_PER_SAMPLE`] points per coarse sample, evenly over its
//! interval; a probe is occupied when it would run the network ([`WindowTest`]'s fate with
//! the grid). Each run of occupied probes becomes an interval that reaches one probe past the
//! run on both sides, so both of its ends lie where the grid sees no density; nearby
//! intervals merge until there are at most Sc / 2. Every interval gets two samples at its
//! ends and a share of the others by its length, evenly spaced. A sample's segment in volume
//! rendering reaches to the next sample, so the gap between two intervals belongs to the
//! end sample of the first: a sample in an empty cell, which the pass fills with the
//! network's far-away constant like any other sample it leaves out.
//!
//! Rays that cross no bone box, rays whose probes all lie in empty cells (their samples are
//! left out anyway), and rays occupied from end to end keep the even placement, as does
//! every ray before the grid is built.

use crate::error::Result;
use crate::network::occupancy::OccupancyGrid;
use crate::render::cull::WindowTest;
use crate::render::raycast::CastInputs;
use pma_data::skeleton::N_JOINTS;

/// Probes per coarse sample when a ray's occupied intervals are looked for.
pub const PROBES_PER_SAMPLE: usize = 4;

/// The coarse ray parameters [R,Sc] of the rays of `inputs` (`even`: the evenly spaced ones,
/// kept for the rays described in the module docs), placed in the intervals `grid` marks
/// occupied as `test` (the pass's window test, for the same poses) sees them.
pub fn coarse_in_occupied(
    test: &WindowTest,
    grid: &OccupancyGrid,
    inputs: &CastInputs,
    even: Vec<f32>,
    sc: usize,
) -> Result<Vec<f32>> {
    let b = inputs.bounds;
    let n_rays = b.near.len();
    let n_poses = inputs.skts.len() / (N_JOINTS * 16);
    if sc < 2 || n_rays == 0 || n_poses == 0 || !grid.is_built() {
        return Ok(even);
    }
    let per_pose = n_rays / n_poses;
    let m = PROBES_PER_SAMPLE * sc;
    let mut z = even;
    let mut xs = vec![0f32; 3 * m];
    for r in 0..n_rays {
        let (near, far) = (b.near[r], b.far[r]);
        // A NaN bound counts as an empty interval.
        if !b.ray_hits_body[r] || far.partial_cmp(&near) != Some(std::cmp::Ordering::Greater) {
            continue;
        }
        let t = |j: usize| near + (far - near) * (j as f32 / (m - 1) as f32);
        let (o, d) = (
            &inputs.rays_o[3 * r..3 * r + 3],
            &inputs.rays_d[3 * r..3 * r + 3],
        );
        for j in 0..m {
            let tj = t(j);
            for c in 0..3 {
                xs[3 * j + c] = o[c] + d[c] * tj;
            }
        }
        let occupied = test.evaluated_along(r / per_pose.max(1), &xs, grid);
        let spans = occupied_spans(&occupied, sc / 2);
        if spans.is_empty() || spans == [(0, m - 1)] {
            continue;
        }
        let row = place(&spans, sc, t);
        z[r * sc..(r + 1) * sc].copy_from_slice(&row);
    }
    Ok(z)
}

/// The probe spans (first, last probe) of the runs of `occupied` probes, each widened by
/// one probe on both sides, overlapping ones merged, then the closest merged until at most
/// `max` remain.
fn occupied_spans(occupied: &[bool], max: usize) -> Vec<(usize, usize)> {
    let m = occupied.len();
    let mut spans: Vec<(usize, usize)> = Vec::new();
    let mut j = 0;
    while j < m {
        if !occupied[j] {
            j += 1;
            continue;
        }
        let start = j;
        while j < m && occupied[j] {
            j += 1;
        }
        let (a, b) = (start.saturating_sub(1), j.min(m - 1));
        match spans.last_mut() {
            Some(last) if a <= last.1 => last.1 = b,
            _ => spans.push((a, b)),
        }
    }
    while spans.len() > max.max(1) {
        let k = (0..spans.len() - 1)
            .min_by_key(|&k| spans[k + 1].0 - spans[k].1)
            .expect("two spans or more");
        spans[k].1 = spans[k + 1].1;
        spans.remove(k + 1);
    }
    spans
}

/// `sc` ascending ray parameters over the probe spans (probe j at `t(j)`): both ends of every
/// span, the rest shared by length (largest remainders first), evenly spaced in each.
fn place(spans: &[(usize, usize)], sc: usize, t: impl Fn(usize) -> f32) -> Vec<f32> {
    let lengths: Vec<f64> = spans.iter().map(|&(a, b)| (b - a) as f64).collect();
    let total: f64 = lengths.iter().sum();
    let extra = sc - 2 * spans.len();
    let shares: Vec<f64> = lengths
        .iter()
        .map(|l| extra as f64 * l / total.max(1e-30))
        .collect();
    let mut counts: Vec<usize> = shares.iter().map(|s| 2 + s.floor() as usize).collect();
    let mut left = sc - counts.iter().sum::<usize>();
    let mut order: Vec<usize> = (0..spans.len()).collect();
    order.sort_by(|&i, &j| {
        let (fi, fj) = (shares[i].fract(), shares[j].fract());
        fj.total_cmp(&fi).then(i.cmp(&j))
    });
    for &i in order.iter().cycle() {
        if left == 0 {
            break;
        }
        counts[i] += 1;
        left -= 1;
    }
    let mut z = Vec::with_capacity(sc);
    for (&(a, b), &n) in spans.iter().zip(&counts) {
        let (za, zb) = (t(a), t(b));
        z.extend((0..n).map(|k| za + (zb - za) * (k as f32 / (n - 1) as f32)));
    }
    z
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spans_pad_each_run_and_merge_down_to_the_limit() {
        let o = |s: &str| s.chars().map(|c| c == '#').collect::<Vec<_>>();
        assert_eq!(occupied_spans(&o("...##....#.."), 8), [(2, 5), (8, 10)]);
        // Padding makes runs one probe apart overlap.
        assert_eq!(occupied_spans(&o("##.##......."), 8), [(0, 5)]);
        assert_eq!(occupied_spans(&o("............"), 8), []);
        assert_eq!(occupied_spans(&o("############"), 8), [(0, 11)]);
        // Three spans, at most two: the closest pair merges.
        assert_eq!(
            occupied_spans(&o("#....#...#.........."), 2),
            [(0, 1), (4, 10)]
        );
    }

    #[test]
    fn samples_cover_both_ends_of_every_span_by_length() {
        let t = |j: usize| j as f32;
        let z = place(&[(2, 5), (8, 20)], 8, t);
        assert_eq!(z.len(), 8);
        assert!(z.windows(2).all(|w| w[0] < w[1]), "{z:?}");
        // Four extra samples shared 3 : 12 → 0.8 and 3.2: one and three.
        assert_eq!(z, [2.0, 3.5, 5.0, 8.0, 11.0, 14.0, 17.0, 20.0]);
    }
}
