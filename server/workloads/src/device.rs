//! The burn device a native trainer runs its steps on, from the run's (or a volunteer's) [`ComputeDevice`]:
//! the CPU in every build, a GPU through burn's wgpu backend in builds with the `gpu` feature.

use burn::tensor::Device;
use fedvla_aggregator::config::ComputeDevice;
use fedvla_federation::BoxError;

/// The autodiff device for `kind`'s training steps, and the name the server's client table shows for it.
/// The GPU is opened once per process (burn's wgpu runtime is initialised once) and shared by every trainer
/// of it, e.g. all of `simulate`'s volunteers.
pub fn training_device(kind: ComputeDevice) -> Result<(Device, &'static str), BoxError> {
    match kind {
        ComputeDevice::Cpu => Ok((Device::flex().autodiff(), "cpu-flex")),
        ComputeDevice::Wgpu => Ok((gpu()?.autodiff(), "wgpu")),
    }
}

#[cfg(feature = "gpu")]
fn gpu() -> Result<Device, BoxError> {
    static GPU: std::sync::OnceLock<Result<Device, String>> = std::sync::OnceLock::new();
    GPU.get_or_init(|| Device::wgpu_options().init().map_err(|e| format!("no GPU for burn's wgpu backend: {e}")))
        .clone()
        .map_err(Into::into)
}

#[cfg(not(feature = "gpu"))]
fn gpu() -> Result<Device, BoxError> {
    Err("device wgpu: this fedvla was built without the gpu feature \
         (cargo build --release -p fedvla-server --features gpu)"
        .into())
}
