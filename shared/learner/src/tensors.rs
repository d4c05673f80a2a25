//! The federation's `NamedTensors` and the policy's `WeightMap` are the same data by LeRobot key.

use fedvla_federation::{NamedTensors, TensorError};
use fedvla_policy::WeightMap;
use fedvla_policy::weights::HostTensor;

pub fn to_named(weights: &WeightMap) -> Result<NamedTensors, TensorError> {
    into_named(weights.clone())
}

/// [`to_named`] of weights it takes: their values move, not copied (a base-size update is 0.4 GB).
pub fn into_named(weights: WeightMap) -> Result<NamedTensors, TensorError> {
    let mut out = NamedTensors::new();
    for (name, t) in weights {
        out.insert(name, t.shape, t.data)?;
    }
    Ok(out)
}

pub fn to_weights(tensors: &NamedTensors) -> WeightMap {
    tensors.iter().map(|(name, t)| (name.to_string(), HostTensor::new(t.shape.clone(), t.values.clone()))).collect()
}
