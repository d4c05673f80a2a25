//! The trainable tensors that cross the wire, and the spec (names and shapes) they are checked against.

use std::collections::BTreeMap;

use safetensors::{Dtype, SafeTensors, tensor::TensorView};

use crate::error::TensorError;

/// One f32 tensor: row-major values and their shape.
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub values: Vec<f32>,
}

impl Tensor {
    /// Builds a tensor, checking that the number of values matches the shape.
    pub fn new(shape: Vec<usize>, values: Vec<f32>) -> Result<Self, TensorError> {
        let expected = shape.iter().product::<usize>();
        if expected != values.len() {
            return Err(TensorError::LengthMismatch { shape, expected, got: values.len() });
        }
        Ok(Self { shape, values })
    }
}

/// Trainable tensors by name, in name order (so every encoding and every sum is deterministic).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct NamedTensors {
    tensors: BTreeMap<String, Tensor>,
}

/// Names and shapes the exchanged tensors must have.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct TensorSpec {
    shapes: BTreeMap<String, Vec<usize>>,
}

impl NamedTensors {
    pub fn new() -> Self {
        Self::default()
    }

    /// Inserts (or replaces) a tensor, checking its length against its shape.
    pub fn insert(&mut self, name: impl Into<String>, shape: Vec<usize>, values: Vec<f32>) -> Result<(), TensorError> {
        self.tensors.insert(name.into(), Tensor::new(shape, values)?);
        Ok(())
    }

    pub fn get(&self, name: &str) -> Option<&Tensor> {
        self.tensors.get(name)
    }

    pub fn get_mut(&mut self, name: &str) -> Option<&mut Tensor> {
        self.tensors.get_mut(name)
    }

    /// These tensors but those `names` (a wrapping strategy's own scalars taken out of what it hands its rule).
    pub fn without(mut self, names: &[&str]) -> Self {
        self.tensors.retain(|name, _| !names.contains(&name.as_str()));
        self
    }

    /// Tensors in name order.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &Tensor)> {
        self.tensors.iter().map(|(name, t)| (name.as_str(), t))
    }

    pub fn len(&self) -> usize {
        self.tensors.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tensors.is_empty()
    }

    /// Tensors in name order, values writable (names and shapes are not).
    pub fn iter_mut(&mut self) -> impl Iterator<Item = (&str, &mut [f32])> {
        self.tensors.iter_mut().map(|(name, t)| (name.as_str(), t.values.as_mut_slice()))
    }

    /// `f(self, other)` value by value, for two sets of the same names and shapes (deltas from a global model and
    /// back).
    pub fn zip_map(&self, other: &NamedTensors, f: impl Fn(f32, f32) -> f32) -> Result<NamedTensors, TensorError> {
        let mut out = NamedTensors::new();
        for (name, t, o) in self.paired(other)? {
            let values = t.values.iter().zip(&o.values).map(|(&a, &b)| f(a, b)).collect();
            out.tensors.insert(name.to_owned(), Tensor { shape: t.shape.clone(), values });
        }
        Ok(out)
    }

    /// The L2 norm of `self - other` over every value, in f64: how far a client's update moved from the global
    /// model it started from.
    pub fn distance(&self, other: &NamedTensors) -> Result<f64, TensorError> {
        let squares = self.paired(other)?.into_iter().flat_map(|(_, t, o)| t.values.iter().zip(&o.values));
        Ok(squares.map(|(&a, &b)| (f64::from(a) - f64::from(b)).powi(2)).sum::<f64>().sqrt())
    }

    /// Each tensor beside `other`'s of the same name, in name order, once both sets hold the same names and shapes.
    fn paired<'a>(&'a self, other: &'a NamedTensors) -> Result<Vec<(&'a str, &'a Tensor, &'a Tensor)>, TensorError> {
        if let Some(name) = other.tensors.keys().find(|n| !self.tensors.contains_key(*n)) {
            return Err(TensorError::Unexpected(name.clone()));
        }
        self.tensors
            .iter()
            .map(|(name, t)| {
                let o = other.tensors.get(name).ok_or_else(|| TensorError::Missing(name.clone()))?;
                if o.shape != t.shape {
                    return Err(TensorError::ShapeMismatch {
                        name: name.clone(),
                        expected: t.shape.clone(),
                        got: o.shape.clone(),
                    });
                }
                Ok((name.as_str(), t, o))
            })
            .collect()
    }

    /// Number of f32 values over all tensors.
    pub fn num_values(&self) -> usize {
        self.tensors.values().map(|t| t.values.len()).sum()
    }

    /// Bytes of tensor data (f32 values only, no names or shapes).
    pub fn byte_size(&self) -> usize {
        self.num_values() * size_of::<f32>()
    }

    /// CRC32 over names, shapes and little-endian values, in name order.
    pub fn checksum(&self) -> u32 {
        let mut hasher = crc32fast::Hasher::new();
        for (name, t) in &self.tensors {
            hasher.update(&(name.len() as u64).to_le_bytes());
            hasher.update(name.as_bytes());
            hasher.update(&(t.shape.len() as u64).to_le_bytes());
            for &d in &t.shape {
                hasher.update(&(d as u64).to_le_bytes());
            }
            for v in &t.values {
                hasher.update(&v.to_le_bytes());
            }
        }
        hasher.finalize()
    }

    /// The names and shapes of these tensors.
    pub fn spec(&self) -> TensorSpec {
        TensorSpec { shapes: self.tensors.iter().map(|(n, t)| (n.clone(), t.shape.clone())).collect() }
    }

    /// Checks these tensors against `spec`: same names, same shapes, finite values.
    pub fn validate(&self, spec: &TensorSpec) -> Result<(), TensorError> {
        if let Some(name) = spec.shapes.keys().find(|n| !self.tensors.contains_key(*n)) {
            return Err(TensorError::Missing(name.clone()));
        }
        if let Some(name) = self.tensors.keys().find(|n| !spec.shapes.contains_key(*n)) {
            return Err(TensorError::Unexpected(name.clone()));
        }
        for (name, t) in &self.tensors {
            let expected = &spec.shapes[name];
            if &t.shape != expected {
                return Err(TensorError::ShapeMismatch {
                    name: name.clone(),
                    expected: expected.clone(),
                    got: t.shape.clone(),
                });
            }
            if let Some(index) = t.values.iter().position(|v| !v.is_finite()) {
                return Err(TensorError::NonFinite { name: name.clone(), index });
            }
        }
        Ok(())
    }

    /// Serializes to safetensors bytes (F32, names as keys).
    pub fn to_safetensors(&self) -> Result<Vec<u8>, TensorError> {
        let bytes: Vec<(&str, Vec<u8>, &[usize])> = self
            .tensors
            .iter()
            .map(|(n, t)| (n.as_str(), t.values.iter().flat_map(|v| v.to_le_bytes()).collect(), &t.shape[..]))
            .collect();
        let views = bytes
            .iter()
            .map(|(n, data, shape)| Ok((*n, TensorView::new(Dtype::F32, shape.to_vec(), data)?)))
            .collect::<Result<Vec<_>, safetensors::SafeTensorError>>()?;
        Ok(safetensors::serialize(views, None)?)
    }

    /// Parses safetensors bytes; every tensor must be F32.
    pub fn from_safetensors(bytes: &[u8]) -> Result<Self, TensorError> {
        let st = SafeTensors::deserialize(bytes)?;
        let mut out = Self::new();
        for (name, view) in st.tensors() {
            if view.dtype() != Dtype::F32 {
                return Err(TensorError::Dtype { name, dtype: format!("{:?}", view.dtype()) });
            }
            let values = view.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
            out.insert(name, view.shape().to_vec(), values)?;
        }
        Ok(out)
    }
}

impl FromIterator<(String, Vec<usize>)> for TensorSpec {
    /// A spec of these names and shapes (without allocating their values).
    fn from_iter<I: IntoIterator<Item = (String, Vec<usize>)>>(iter: I) -> Self {
        Self { shapes: iter.into_iter().collect() }
    }
}

impl TensorSpec {
    /// Shape expected for `name`.
    pub fn shape(&self, name: &str) -> Option<&[usize]> {
        self.shapes.get(name).map(Vec::as_slice)
    }

    /// Names and shapes in name order.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &[usize])> {
        self.shapes.iter().map(|(n, s)| (n.as_str(), s.as_slice()))
    }

    pub fn len(&self) -> usize {
        self.shapes.len()
    }

    pub fn is_empty(&self) -> bool {
        self.shapes.is_empty()
    }

    /// Bytes of f32 data a conforming set of tensors holds.
    pub fn byte_size(&self) -> usize {
        self.shapes.values().map(|s| s.iter().product::<usize>()).sum::<usize>() * size_of::<f32>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> NamedTensors {
        let mut t = NamedTensors::new();
        t.insert("b", vec![2], vec![1.0, -2.0]).unwrap();
        t.insert("a", vec![2, 2], vec![0.5, 1.5, 2.5, 3.5]).unwrap();
        t
    }

    #[test]
    fn insert_checks_length() {
        let err = NamedTensors::new().insert("x", vec![2, 3], vec![0.0; 5]).unwrap_err();
        assert!(matches!(err, TensorError::LengthMismatch { expected: 6, got: 5, .. }));
    }

    #[test]
    fn byte_size_and_order() {
        let t = sample();
        assert_eq!(t.byte_size(), 24);
        assert_eq!(t.spec().byte_size(), 24);
        assert_eq!(t.iter().map(|(n, _)| n).collect::<Vec<_>>(), ["a", "b"]);
    }

    #[test]
    fn distance_is_the_l2_norm_of_the_difference_over_every_tensor() {
        let mut a = NamedTensors::new();
        a.insert("x", vec![2], vec![1.0, 2.0]).unwrap();
        a.insert("y", vec![1], vec![-1.0]).unwrap();
        let mut b = NamedTensors::new();
        b.insert("x", vec![2], vec![1.0, -2.0]).unwrap();
        b.insert("y", vec![1], vec![2.0]).unwrap();
        // (0, 4, -3): norm 5, either way round.
        assert_eq!(a.distance(&b).unwrap(), 5.0);
        assert_eq!(b.distance(&a).unwrap(), 5.0);
        assert!(matches!(a.distance(&sample()), Err(TensorError::Unexpected(_) | TensorError::Missing(_))));
    }

    #[test]
    fn checksum_sees_values_and_shapes() {
        let t = sample();
        let mut changed = t.clone();
        changed.get_mut("b").unwrap().values[1] = -2.0001;
        assert_ne!(t.checksum(), changed.checksum());
        let mut reshaped = t.clone();
        reshaped.insert("a", vec![4], vec![0.5, 1.5, 2.5, 3.5]).unwrap();
        assert_ne!(t.checksum(), reshaped.checksum());
        assert_eq!(t.checksum(), sample().checksum());
    }

    #[test]
    fn validate_reports_each_problem() {
        let spec = sample().spec();
        let mut missing = sample();
        missing.tensors.remove("a");
        assert_eq!(missing.validate(&spec), Err(TensorError::Missing("a".into())));
        let mut extra = sample();
        extra.insert("c", vec![1], vec![0.0]).unwrap();
        assert_eq!(extra.validate(&spec), Err(TensorError::Unexpected("c".into())));
        let mut shaped = sample();
        shaped.insert("a", vec![4], vec![0.0; 4]).unwrap();
        assert!(matches!(shaped.validate(&spec), Err(TensorError::ShapeMismatch { .. })));
        let mut nan = sample();
        nan.get_mut("b").unwrap().values[1] = f32::NAN;
        assert_eq!(nan.validate(&spec), Err(TensorError::NonFinite { name: "b".into(), index: 1 }));
        assert_eq!(sample().validate(&spec), Ok(()));
    }

    #[test]
    fn safetensors_round_trip() {
        let t = sample();
        let bytes = t.to_safetensors().unwrap();
        assert_eq!(NamedTensors::from_safetensors(&bytes).unwrap(), t);
    }
}
