//! Marching cubes without a case table (see the module docs of `mesh`).

use std::collections::HashMap;

use super::*;
use crate::error::{ModelError, Result};

/// Corner c of a cell sits at offset (c & 1, (c >> 1) & 1, (c >> 2) & 1).
const fn corner_offset(c: usize) -> [usize; 3] {
    [c & 1, (c >> 1) & 1, (c >> 2) & 1]
}

/// The 12 cell edges as corner pairs (low corner first; they differ in one bit).
const EDGES: [[usize; 2]; 12] = [
    [0, 1],
    [2, 3],
    [4, 5],
    [6, 7],
    [0, 2],
    [1, 3],
    [4, 6],
    [5, 7],
    [0, 4],
    [1, 5],
    [2, 6],
    [3, 7],
];

/// The 6 faces, corners counter-clockwise seen from outside the cell:
/// x = 0, x = 1, y = 0, y = 1, z = 0, z = 1.
const FACES: [[usize; 4]; 6] = [
    [0, 4, 6, 2],
    [1, 3, 7, 5],
    [0, 1, 5, 4],
    [2, 6, 7, 3],
    [0, 2, 3, 1],
    [4, 5, 7, 6],
];

const fn edge_between(a: usize, b: usize) -> usize {
    let mut e = 0;
    while e < 12 {
        if (EDGES[e][0] == a && EDGES[e][1] == b) || (EDGES[e][0] == b && EDGES[e][1] == a) {
            return e;
        }
        e += 1;
    }
    panic!("corners are not adjacent");
}

/// Bit mask of the two faces each edge lies on.
const fn edge_faces() -> [u8; 12] {
    let mut out = [0u8; 12];
    let mut f = 0;
    while f < 6 {
        let mut m = 0;
        while m < 4 {
            out[edge_between(FACES[f][m], FACES[f][(m + 1) % 4])] |= 1 << f;
            m += 1;
        }
        f += 1;
    }
    out
}

const EDGE_FACES: [u8; 12] = edge_faces();

/// Marching cubes on `values` (sampled on `grid`) at `threshold`; inside means
/// `value > threshold` (NaN is outside). See the module docs for the guarantees.
pub fn marching_cubes(values: &[f32], grid: &Grid, threshold: f32) -> Result<Mesh> {
    if values.len() != grid.len() {
        return Err(ModelError::Input(format!(
            "marching cubes: {} values for a grid of {:?} = {} samples",
            values.len(),
            grid.dims,
            grid.len()
        )));
    }
    if !threshold.is_finite() {
        return Err(ModelError::Input(format!(
            "threshold must be finite, found {threshold}"
        )));
    }
    let [nx, ny, nz] = grid.dims;
    let mut mesh = Mesh::default();
    if nx < 3 || ny < 3 || nz < 3 {
        // Nothing but the (outside) border layer.
        return Ok(mesh);
    }
    let inside = |i: usize, j: usize, k: usize| -> bool {
        let border = i == 0 || j == 0 || k == 0 || i == nx - 1 || j == ny - 1 || k == nz - 1;
        !border && values[grid.index(i, j, k)] > threshold
    };
    // The value marching cubes works with: strictly above the threshold inside, at or below it
    // outside (border samples and non-finite values are pulled to a finite stand-in). It depends
    // on the sample alone, so cells sharing an edge or a face see the same numbers.
    let effective = |i: usize, j: usize, k: usize| -> f32 {
        let v = values[grid.index(i, j, k)];
        match (inside(i, j, k), v.is_finite()) {
            (true, true) => v,
            (true, false) => threshold + 1.0,
            (false, true) if v <= threshold => v,
            (false, _) => threshold - 1.0,
        }
    };
    // Grid edge (low sample, axis) -> vertex index.
    let mut edge_vertex: HashMap<u64, u32> = HashMap::new();
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let mut case = 0u8;
                for c in 0..8 {
                    let o = corner_offset(c);
                    if inside(i + o[0], j + o[1], k + o[2]) {
                        case |= 1 << c;
                    }
                }
                if case == 0 || case == 0xff {
                    continue;
                }
                let v: [f32; 8] = std::array::from_fn(|c| {
                    let o = corner_offset(c);
                    effective(i + o[0], j + o[1], k + o[2])
                });
                for lp in cell_loops(case, &v, threshold) {
                    let ids: Vec<u32> = lp
                        .iter()
                        .map(|&e| {
                            let [a, b] = EDGES[e];
                            let oa = corner_offset(a);
                            let axis = (0..3)
                                .find(|&d| oa[d] != corner_offset(b)[d])
                                .expect("an edge spans one axis");
                            let key = grid.index(i + oa[0], j + oa[1], k + oa[2]) as u64 * 3
                                + axis as u64;
                            *edge_vertex.entry(key).or_insert_with(|| {
                                let t = ((threshold - v[a]) / (v[b] - v[a])).clamp(0.0, 1.0);
                                let mut p = grid.point(i + oa[0], j + oa[1], k + oa[2]);
                                p[axis] += t * grid.spacing;
                                mesh.vertices.push(p);
                                (mesh.vertices.len() - 1) as u32
                            })
                        })
                        .collect();
                    triangulate(&mut mesh, &lp, &ids);
                }
            }
        }
    }
    Ok(mesh)
}

/// The closed loops of one cell as sequences of cell edges, oriented so that the triangles
/// (in loop order) face away from the inside.
fn cell_loops(case: u8, v: &[f32; 8], threshold: f32) -> Vec<Vec<usize>> {
    let is_in = |c: usize| case & (1 << c) != 0;
    // next[e] = the edge a segment starting on edge e ends on.
    let mut next = [usize::MAX; 12];
    for face in FACES {
        let mut entries = [0usize; 2];
        let mut exits = [0usize; 2];
        let (mut ne, mut nx) = (0, 0);
        // Walk the face counter-clockwise: in→out is an exit, out→in an entry.
        for m in 0..4 {
            let (a, b) = (face[m], face[(m + 1) % 4]);
            if is_in(a) == is_in(b) {
                continue;
            }
            let e = edge_between(a, b);
            if is_in(a) {
                exits[nx] = e;
                nx += 1;
            } else {
                entries[ne] = e;
                ne += 1;
            }
        }
        match (ne, nx) {
            (0, 0) => {}
            (1, 1) => next[entries[0]] = exits[0],
            (2, 2) => {
                // Corners alternate in/out. Order the crossings along the walk: with the walk
                // starting at the face's first corner, an inside first corner gives exit,
                // entry, exit, entry; an outside one entry, exit, entry, exit.
                let walk: [usize; 4] = if is_in(face[0]) {
                    [exits[0], entries[0], exits[1], entries[1]]
                } else {
                    [entries[0], exits[0], entries[1], exits[1]]
                };
                let u = |c: usize| v[face[c]] as f64 - threshold as f64;
                let (ins, outs) = if is_in(face[0]) {
                    ((0, 2), (1, 3))
                } else {
                    ((1, 3), (0, 2))
                };
                // Asymptotic decider: the bilinear interpolant's saddle lies inside iff the
                // product of the inside diagonal's excesses beats the outside one's.
                let joined = u(ins.0) * u(ins.1) > u(outs.0) * u(outs.1);
                // Position p in `walk` is an entry at odd p (inside first corner) or even p.
                for p in 0..4 {
                    let is_entry = (p % 2 == 1) == is_in(face[0]);
                    if !is_entry {
                        continue;
                    }
                    // Separate insides: each entry pairs with the next exit (cutting off the
                    // inside corner between them); joined: with the previous exit.
                    let q = if joined { (p + 3) % 4 } else { (p + 1) % 4 };
                    next[walk[p]] = walk[q];
                }
            }
            _ => unreachable!("a face has an even number of crossings, at most 4"),
        }
    }
    let mut loops = Vec::new();
    let mut used = [false; 12];
    for start in 0..12 {
        if next[start] == usize::MAX || used[start] {
            continue;
        }
        let mut lp = Vec::with_capacity(6);
        let mut e = start;
        while !used[e] {
            used[e] = true;
            lp.push(e);
            e = next[e];
            debug_assert!(e != usize::MAX, "loop is closed");
        }
        loops.push(lp);
    }
    loops
}

/// Triangulate one loop (cell edges `lp`, vertex ids `ids`) into `mesh`, keeping its winding.
fn triangulate(mesh: &mut Mesh, lp: &[usize], ids: &[u32]) {
    let n = lp.len();
    if n == 3 {
        mesh.triangles.push([ids[0], ids[1], ids[2]]);
        return;
    }
    // A fan diagonal between two vertices on one cube face could coincide with an edge of the
    // neighbouring cell: choose an apex whose diagonals all cross the cell's interior.
    let apex =
        (0..n).find(|&a| (2..n - 1).all(|d| EDGE_FACES[lp[a]] & EDGE_FACES[lp[(a + d) % n]] == 0));
    match apex {
        Some(a) => {
            for d in 1..n - 1 {
                mesh.triangles
                    .push([ids[a], ids[(a + d) % n], ids[(a + d + 1) % n]]);
            }
        }
        None => {
            let mut c = [0f32; 3];
            for &id in ids {
                let p = mesh.vertices[id as usize];
                for k in 0..3 {
                    c[k] += p[k] / n as f32;
                }
            }
            mesh.vertices.push(c);
            let ci = (mesh.vertices.len() - 1) as u32;
            for m in 0..n {
                mesh.triangles.push([ids[m], ids[(m + 1) % n], ci]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faces_are_counter_clockwise_from_outside() {
        let pos = |c: usize| corner_offset(c).map(|x| x as f64);
        for (f, face) in FACES.iter().enumerate() {
            // Outward normal of face f: −axis for even f, +axis for odd.
            let axis = f / 2;
            let sign = if f % 2 == 0 { -1.0 } else { 1.0 };
            for m in 0..4 {
                let [a, b, c] = [0, 1, 2].map(|d| pos(face[(m + d) % 4]));
                let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                let v = [c[0] - b[0], c[1] - b[1], c[2] - b[2]];
                let n = [
                    u[1] * v[2] - u[2] * v[1],
                    u[2] * v[0] - u[0] * v[2],
                    u[0] * v[1] - u[1] * v[0],
                ];
                assert!(n[axis] * sign > 0.0, "face {f} corner {m}");
                assert_eq!(pos(face[m])[axis], if sign > 0.0 { 1.0 } else { 0.0 });
            }
        }
        for (e, faces) in EDGE_FACES.iter().enumerate() {
            assert_eq!(faces.count_ones(), 2, "edge {e}");
        }
    }

    #[test]
    fn single_corner_cases_are_one_outward_triangle() {
        for c in 0..8 {
            let case = 1u8 << c;
            let mut v = [-1f32; 8];
            v[c] = 1.0;
            let loops = cell_loops(case, &v, 0.0);
            assert_eq!(loops.len(), 1);
            assert_eq!(loops[0].len(), 3);
        }
    }
}
