//! The federation's `NamedTensors` and the policy's `WeightMap` are the same data by LeRobot key.

use fedvla_federation::{NamedTensors, TensorError};
use fedvla_policy::WeightMap;
use fedvla_policy::weights::HostTensor;

pub fn to_named(weights: &WeightMap) -> Result<NamedTensors, TensorError> {
    let mut out = NamedTensors::new();
    for (name, t) in weights {
        out.insert(name.as_str(), t.shape.clone(), t.data.clone())?;
    }
    Ok(out)
}

pub fn to_weights(tensors: &NamedTensors) -> WeightMap {
    tensors.iter().map(|(name, t)| (name.to_string(), HostTensor::new(t.shape.clone(), t.values.clone()))).collect()
}
