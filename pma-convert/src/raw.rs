//! A tensor as plain little-endian bytes, so that imported weights can be
//! written out without ever passing through a float conversion.

use std::borrow::Cow;

use candle_core::{DType, Device, Tensor};
use safetensors::{Dtype, View};

/// A dense, C-ordered, little-endian tensor.
#[derive(Clone, Debug, PartialEq)]
pub struct RawTensor {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub data: Vec<u8>,
}

impl RawTensor {
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }

    /// A candle tensor holding the same bytes.
    pub fn to_candle(&self, device: &Device) -> candle_core::Result<Tensor> {
        let dtype = match self.dtype {
            Dtype::F32 => DType::F32,
            Dtype::F64 => DType::F64,
            Dtype::F16 => DType::F16,
            Dtype::BF16 => DType::BF16,
            Dtype::I64 => DType::I64,
            Dtype::U8 => DType::U8,
            Dtype::U32 => DType::U32,
            other => candle_core::bail!("dtype {other:?} has no candle equivalent"),
        };
        Tensor::from_raw_buffer(&self.data, dtype, &self.shape, device)
    }
}

impl View for &RawTensor {
    fn dtype(&self) -> Dtype {
        self.dtype
    }

    fn shape(&self) -> &[usize] {
        &self.shape
    }

    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.data)
    }

    fn data_len(&self) -> usize {
        self.data.len()
    }
}
