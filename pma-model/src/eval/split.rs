//! Which images of a dataset form a split (see the module docs of [`super`]).

use std::path::{Path, PathBuf};

use pma_data::dataset::Dataset;

use super::{EvalError, Result};

/// Which images of a file form the split.
#[derive(Debug, Clone, PartialEq)]
pub struct Split {
    pub name: String,
    /// The split's `eval_tag` value (0 train, 1 novel view, 2 novel pose, 3 val).
    pub tag: i8,
    /// Every image of the file belongs to the split (a `<split>.npz` of a scene directory).
    pub whole_file: bool,
}

impl Split {
    /// The split `name` (`train`, `novel_view`, `novel_pose` or `val`), filtered by tag.
    pub fn named(name: &str) -> Result<Self> {
        let tag = match name {
            "train" => 0,
            "novel_view" => 1,
            "novel_pose" => 2,
            "val" => 3,
            other => return Err(EvalError::UnknownSplit(other.to_string())),
        };
        Ok(Self {
            name: name.to_string(),
            tag,
            whole_file: false,
        })
    }

    /// Every image of a file that holds only this split.
    pub fn whole_file(name: &str) -> Result<Self> {
        Ok(Self {
            whole_file: true,
            ..Self::named(name)?
        })
    }
}

/// The file to read for `split` of `data` (a file, or a directory holding `<split>.npz`).
/// A path that is neither (a FIFO, a device) is refused saying what it is.
pub fn resolve_split(data: &Path, split: &str) -> Result<(PathBuf, Split)> {
    let not_data = |path: &Path, what: String| EvalError::NotData {
        path: path.to_path_buf(),
        what,
    };
    let kind = |m: &std::fs::Metadata| pma_data::fsio::file_type_name(&m.file_type());
    match std::fs::metadata(data) {
        Ok(m) if m.is_dir() => {
            let split = Split::whole_file(split)?;
            let path = data.join(format!("{}.npz", split.name));
            match std::fs::metadata(&path) {
                Ok(m) if m.is_file() => Ok((path, split)),
                Ok(m) => Err(not_data(
                    &path,
                    format!(
                        "{}, expected the {} split's pma-npz file",
                        kind(&m),
                        split.name
                    ),
                )),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(EvalError::NoSplitFile {
                    dir: data.to_path_buf(),
                    split: split.name,
                }),
                Err(e) => Err(not_data(&path, e.to_string())),
            }
        }
        m => {
            let split = Split::named(split)?;
            match m {
                Ok(m) if m.is_file() => Ok((data.to_path_buf(), split)),
                Ok(m) => Err(not_data(
                    data,
                    format!(
                        "{}, expected a pma-npz file or a directory holding {}.npz",
                        kind(&m),
                        split.name
                    ),
                )),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    Err(EvalError::NoData(data.to_path_buf()))
                }
                Err(e) => Err(not_data(data, e.to_string())),
            }
        }
    }
}

/// A split read by [`read_split`].
#[derive(Debug, Clone)]
pub struct SplitData {
    /// The file read (see [`resolve_split`]).
    pub file: PathBuf,
    /// Its `warnings` are for the caller to show.
    pub data: Dataset,
    /// The split's images in `data`.
    pub images: Vec<usize>,
}

/// The images of `split` in `path` (a file, or a directory holding `<split>.npz`), read for
/// `profile`. With `camera_only` (the images lend only their cameras), a file that does not
/// hold the split lends all its images instead of being refused.
pub fn read_split(
    path: &Path,
    split: &str,
    profile: pma_data::dataset::Profile,
    camera_only: bool,
) -> Result<SplitData> {
    let (file, split) = resolve_split(path, split)?;
    let data = super::read_dataset(&file, profile)?;
    let images = match split_images(&data, &file, &split) {
        Ok(images) => images,
        Err(_) if camera_only => split_images(&data, &file, &Split::whole_file(&split.name)?)?,
        Err(e) => return Err(e),
    };
    Ok(SplitData { file, data, images })
}

/// Image indices of `split` in `data`, read from `path`.
pub fn split_images(data: &Dataset, path: &Path, split: &Split) -> Result<Vec<usize>> {
    let n = data.n_images();
    let not_in_file = |why: String| EvalError::SplitNotInFile {
        path: path.to_path_buf(),
        split: split.name.clone(),
        why,
    };
    let images: Vec<usize> = match (&data.eval_tag, split.whole_file) {
        (_, true) => (0..n).collect(),
        (Some(tags), false) => (0..n).filter(|&i| tags[i] == split.tag).collect(),
        (None, false) => {
            if file_split_name(path).as_deref() != Some(split.name.as_str()) {
                return Err(not_in_file(format!(
                    "the file has no eval_tag; without one a file holds only the split its name \
                     gives, {}.npz",
                    split.name
                )));
            }
            (0..n).collect()
        }
    };
    if images.is_empty() {
        return Err(not_in_file(match &data.eval_tag {
            Some(_) => format!("no image has eval_tag {}", split.tag),
            None => "the file has no images".into(),
        }));
    }
    Ok(images)
}

/// `novel_pose` for `DIR/novel_pose.npz` or `DIR/novel_pose.scene.npz`.
fn file_split_name(path: &Path) -> Option<String> {
    let name = path.file_name()?.to_str()?;
    let stem = name
        .strip_suffix(".scene.npz")
        .or_else(|| name.strip_suffix(".npz"))?;
    Some(stem.to_string())
}

/// The held-out images a training run scores: those tagged novel view when the file has
/// any, otherwise all of them.
pub fn held_out_images(data: &Dataset) -> Vec<usize> {
    match &data.eval_tag {
        Some(t) if t.iter().any(|&v| v == 1) => {
            (0..data.n_images()).filter(|&i| t[i] == 1).collect()
        }
        _ => (0..data.n_images()).collect(),
    }
}

/// At most `k` of `items`, evenly spread, first and last included.
pub fn spread(items: &[usize], k: usize) -> Vec<usize> {
    if k >= items.len() {
        return items.to_vec();
    }
    if k == 0 {
        return Vec::new();
    }
    if k == 1 {
        return vec![items[0]];
    }
    let mut out: Vec<usize> = (0..k)
        .map(|i| items[i * (items.len() - 1) / (k - 1)])
        .collect();
    out.dedup();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_names_and_files() {
        assert!(matches!(
            Split::named("holdout"),
            Err(EvalError::UnknownSplit(_))
        ));
        assert_eq!(Split::named("novel_pose").unwrap().tag, 2);
        assert_eq!(
            file_split_name(Path::new("a/novel_pose.npz")).as_deref(),
            Some("novel_pose")
        );
        assert_eq!(
            file_split_name(Path::new("train.scene.npz")).as_deref(),
            Some("train")
        );
        assert_eq!(file_split_name(Path::new("x.h5")), None);
    }
}
