//! Validation placeholder (being written).
use super::{Dataset, ReadOptions};
use crate::error::Result;

pub(crate) fn validate(_ds: &mut Dataset, _opts: &ReadOptions) -> Result<()> {
    Ok(())
}
