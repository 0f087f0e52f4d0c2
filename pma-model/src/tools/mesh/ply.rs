//! Binary PLY files of meshes.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use super::*;
use crate::error::{ModelError, Result};
use pma_data::FileError;

fn to_u8(c: f32) -> u8 {
    (c.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Write `mesh` as a binary little-endian PLY (vertices `x y z nx ny nz [red green blue]`,
/// faces `vertex_indices`), atomically (temporary file + rename).
pub fn write_ply(mesh: &Mesh, path: &Path) -> Result<()> {
    pma_data::fsio::write_atomic_with(path, |w| write_ply_to(mesh, w))
        .map_err(|e| FileError::write(path, e).into())
}

fn write_ply_to(mesh: &Mesh, w: &mut impl Write) -> std::io::Result<()> {
    let normals = mesh.vertex_normals();
    writeln!(w, "ply\nformat binary_little_endian 1.0")?;
    writeln!(
        w,
        "comment pma mesh: world coordinates (scene units), normals toward lower density"
    )?;
    writeln!(w, "element vertex {}", mesh.vertices.len())?;
    for p in ["x", "y", "z", "nx", "ny", "nz"] {
        writeln!(w, "property float {p}")?;
    }
    if mesh.colours.is_some() {
        for p in ["red", "green", "blue"] {
            writeln!(w, "property uchar {p}")?;
        }
    }
    writeln!(w, "element face {}", mesh.triangles.len())?;
    writeln!(w, "property list uchar int vertex_indices\nend_header")?;
    for (i, (p, n)) in mesh.vertices.iter().zip(&normals).enumerate() {
        for x in p.iter().chain(n) {
            w.write_all(&x.to_le_bytes())?;
        }
        if let Some(c) = &mesh.colours {
            w.write_all(&c[i].map(to_u8))?;
        }
    }
    for t in &mesh.triangles {
        w.write_all(&[3u8])?;
        for &i in t {
            w.write_all(&(i as i32).to_le_bytes())?;
        }
    }
    Ok(())
}

/// Read a binary little-endian PLY with float vertex coordinates (other float/uchar vertex
/// properties are allowed; `red green blue` become colours) and triangle faces.
pub fn read_ply(path: &Path) -> Result<Mesh> {
    let bad = |msg: String| ModelError::Input(format!("{}: {msg}", path.display()));
    let file = pma_data::fsio::open_input(path).map_err(FileError::reading(path))?;
    let mut r = BufReader::new(file);
    let mut line = String::new();
    let mut header = Vec::new();
    loop {
        line.clear();
        if r.read_line(&mut line).map_err(FileError::reading(path))? == 0 {
            return Err(bad("no end_header".into()));
        }
        let l = line.trim_end().to_string();
        if l == "end_header" {
            break;
        }
        header.push(l);
    }
    if header.first().map(String::as_str) != Some("ply")
        || !header
            .iter()
            .any(|l| l == "format binary_little_endian 1.0")
    {
        return Err(bad("not a binary little-endian PLY".into()));
    }
    let (mut nv, mut nf) = (None, None);
    let mut vprops: Vec<(String, usize)> = Vec::new();
    let mut in_vertex = false;
    for l in &header {
        let f: Vec<&str> = l.split_whitespace().collect();
        match f.as_slice() {
            ["element", "vertex", n] => {
                nv = n.parse::<usize>().ok();
                in_vertex = true;
            }
            ["element", "face", n] => {
                nf = n.parse::<usize>().ok();
                in_vertex = false;
            }
            ["property", ty, name] if in_vertex => {
                let size = match *ty {
                    "float" | "float32" => 4,
                    "uchar" | "uint8" => 1,
                    other => return Err(bad(format!("unsupported vertex property type {other}"))),
                };
                vprops.push((name.to_string(), size));
            }
            ["property", "list", "uchar" | "uint8", "int" | "int32" | "uint" | "uint32", _] => {}
            ["element", other, _] => return Err(bad(format!("unsupported element {other}"))),
            _ => {}
        }
    }
    let (nv, nf) = (
        nv.ok_or_else(|| bad("no vertex element".into()))?,
        nf.ok_or_else(|| bad("no face element".into()))?,
    );
    let pos = |name: &str| vprops.iter().position(|(n, _)| n == name);
    let (Some(px), Some(py), Some(pz)) = (pos("x"), pos("y"), pos("z")) else {
        return Err(bad("vertices lack x, y, z".into()));
    };
    let rgb = match (pos("red"), pos("green"), pos("blue")) {
        (Some(a), Some(b), Some(c)) => Some([a, b, c]),
        _ => None,
    };
    let stride: usize = vprops.iter().map(|p| p.1).sum();
    let offsets: Vec<usize> = vprops
        .iter()
        .scan(0, |o, p| {
            let here = *o;
            *o += p.1;
            Some(here)
        })
        .collect();
    let mut buf = vec![0u8; stride];
    let mut mesh = Mesh {
        colours: rgb.map(|_| Vec::with_capacity(nv)),
        ..Default::default()
    };
    let truncated = |e: std::io::Error| bad(format!("truncated data: {e}"));
    for _ in 0..nv {
        r.read_exact(&mut buf).map_err(truncated)?;
        let f = |p: usize| {
            let o = offsets[p];
            f32::from_le_bytes([buf[o], buf[o + 1], buf[o + 2], buf[o + 3]])
        };
        mesh.vertices.push([f(px), f(py), f(pz)]);
        if let (Some(c), Some(cols)) = (rgb, mesh.colours.as_mut()) {
            cols.push(c.map(|p| buf[offsets[p]] as f32 / 255.0));
        }
    }
    for t in 0..nf {
        let mut n = [0u8; 1];
        r.read_exact(&mut n).map_err(truncated)?;
        if n[0] != 3 {
            return Err(bad(format!(
                "face {t} has {} vertices; only triangles",
                n[0]
            )));
        }
        let mut idx = [0u8; 12];
        r.read_exact(&mut idx).map_err(truncated)?;
        let tri: [u32; 3] = std::array::from_fn(|k| {
            i32::from_le_bytes([idx[4 * k], idx[4 * k + 1], idx[4 * k + 2], idx[4 * k + 3]]) as u32
        });
        if tri.iter().any(|&i| i as usize >= nv) {
            return Err(bad(format!("face {t} indexes past {nv} vertices: {tri:?}")));
        }
        mesh.triangles.push(tri);
    }
    Ok(mesh)
}
