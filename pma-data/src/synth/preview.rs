//! A contact sheet of rendered views for eyeballing the scene:
//! row 1 the first training frame from every camera, row 2 training frames
//! over time from the first training camera, row 3 novel poses (walk, then
//! dance) from the same camera.

use std::path::Path;

use super::{ScenePlan, SplitPlan, SynthError};
use crate::dataset::Dataset;

/// Tiles per row at most.
const COLUMNS: usize = 6;
/// Grey gap between tiles, pixels.
const GAP: usize = 2;

pub(crate) struct Sheet {
    width: usize,
    height: usize,
    rgb: Vec<u8>,
}

impl Sheet {
    pub(crate) fn encode_png(&self, path: &Path) -> Result<Vec<u8>, SynthError> {
        let err = |msg: String| SynthError::Encode {
            path: path.to_path_buf(),
            msg,
        };
        let img =
            image::RgbImage::from_raw(self.width as u32, self.height as u32, self.rgb.clone())
                .ok_or_else(|| err("contact sheet buffer does not match its size".into()))?;
        let mut bytes = std::io::Cursor::new(Vec::new());
        img.write_to(&mut bytes, image::ImageFormat::Png)
            .map_err(|e| err(e.to_string()))?;
        Ok(bytes.into_inner())
    }
}

/// Image index of pose row `pose` seen by camera `cam` in a split.
fn image_index(split: &SplitPlan, pose: usize, cam: usize) -> Option<usize> {
    let k = split.cams.iter().position(|&c| c == cam)?;
    Some(pose * split.cams.len() + k)
}

/// Up to `n` indices spread over `0..len`, including the first.
fn pick(len: usize, n: usize) -> Vec<usize> {
    let n = n.min(len);
    (0..n).map(|k| k * len / n.max(1)).collect()
}

pub(crate) fn contact_sheet(plan: &ScenePlan, datasets: &[Dataset]) -> Sheet {
    let res = plan.config.res;
    let [train, view, pose] = [0, 1, 2].map(|i| (&plan.splits[i], &datasets[i]));
    let cam0 = plan.train_cams[0];

    let mut rows: Vec<Vec<(&Dataset, usize)>> = Vec::new();
    let mut first: Vec<(&Dataset, usize)> = Vec::new();
    for cam in 0..plan.cameras.len() {
        let tile = image_index(train.0, 0, cam)
            .map(|n| (train.1, n))
            .or_else(|| image_index(view.0, 0, cam).map(|n| (view.1, n)));
        first.extend(tile);
    }
    rows.extend(first.chunks(COLUMNS).map(<[_]>::to_vec));
    rows.push(
        pick(train.0.poses.len(), COLUMNS)
            .into_iter()
            .filter_map(|p| image_index(train.0, p, cam0).map(|n| (train.1, n)))
            .collect(),
    );
    rows.push(
        pick(pose.0.poses.len(), COLUMNS)
            .into_iter()
            .filter_map(|p| image_index(pose.0, p, cam0).map(|n| (pose.1, n)))
            .collect(),
    );

    let cols = rows.iter().map(Vec::len).max().unwrap_or(1).max(1);
    let width = cols * res + (cols + 1) * GAP;
    let height = rows.len() * res + (rows.len() + 1) * GAP;
    let mut rgb = vec![64u8; width * height * 3];
    for (r, row) in rows.iter().enumerate() {
        for (c, &(ds, n)) in row.iter().enumerate() {
            let Some(img) = ds.image(n) else { continue };
            let (x0, y0) = (GAP + c * (res + GAP), GAP + r * (res + GAP));
            for y in 0..res {
                for x in 0..res {
                    let dst = ((y0 + y) * width + x0 + x) * 3;
                    for k in 0..3 {
                        rgb[dst + k] = img[[y * res + x, k]];
                    }
                }
            }
        }
    }
    Sheet { width, height, rgb }
}
