//! Weights by LeRobot key name: host-side tensors, safetensors in and out (F32/BF16/F16 converted
//! on load), the check of a checkpoint against the configuration's tensor list, seeded random
//! initialisation, and the on-device store the model's layers are built from.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::sync::{Arc, Mutex};

use burn::tensor::{Device, Tensor, TensorCreationOptions, TensorData};
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, Normal};
use safetensors::{Dtype, SafeTensors, serialize, serialize_to_file};

use crate::config::ParamSpec;
use crate::error::PolicyError;

/// A tensor in host memory, row-major f32.
#[derive(Debug, Clone, PartialEq)]
pub struct HostTensor {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

impl HostTensor {
    pub fn new(shape: Vec<usize>, data: Vec<f32>) -> Self {
        debug_assert_eq!(shape.iter().product::<usize>(), data.len());
        Self { shape, data }
    }

    pub fn from_tensor<const D: usize>(t: Tensor<D>) -> Self {
        let shape = t.dims().to_vec();
        let data = t.into_data().convert::<f32>().try_into_vec::<f32>().expect("f32 tensor data");
        Self { shape, data }
    }

    pub fn to_tensor<const D: usize>(&self, device: &Device) -> Tensor<D> {
        Tensor::<1>::from_data(TensorData::new(self.data.clone(), [self.data.len()]), device)
            .reshape(<[usize; D]>::try_from(self.shape.as_slice()).expect("tensor rank matches the requested rank"))
    }
}

/// Tensors by LeRobot key (`model.…`), sorted by name.
pub type WeightMap = BTreeMap<String, HostTensor>;

/// Keys LeRobot <= 0.3 stored inside model.safetensors for normalisation; the stats now live in the
/// processor files, so these are ignored on load.
const NORMALIZER_PREFIXES: [&str; 3] = ["normalize_inputs", "normalize_targets", "unnormalize_outputs"];

/// Reads every tensor of a safetensors file, converting BF16/F16 to f32, stripping the
/// `model._orig_mod.` prefix torch.compile leaves and dropping legacy normaliser buffers.
pub fn read_safetensors(path: &Path) -> Result<WeightMap, PolicyError> {
    read_checkpoint(path).map(|(weights, _)| weights)
}

/// [`read_safetensors`], with the dtype the file stores its tensors in, from the same read.
pub fn read_checkpoint(path: &Path) -> Result<(WeightMap, StoredDtype), PolicyError> {
    let bytes = std::fs::read(path).map_err(|e| PolicyError::io(path, e))?;
    parse_checkpoint(&bytes, path)
}

/// [`read_safetensors`] of bytes already in memory (a download); `path` only names the source in errors.
pub fn parse_safetensors(bytes: &[u8], path: &Path) -> Result<WeightMap, PolicyError> {
    parse_checkpoint(bytes, path).map(|(weights, _)| weights)
}

fn parse_checkpoint(bytes: &[u8], path: &Path) -> Result<(WeightMap, StoredDtype), PolicyError> {
    let mut out = WeightMap::new();
    // Every tensor read is a float one (any other dtype is refused): bf16 when all of them are.
    let mut all_bf16 = true;
    for (key, view) in checkpoint_tensors(bytes, path)? {
        all_bf16 &= view.dtype() == Dtype::BF16;
        let data = decode_floats(view.dtype(), view.data()).ok_or_else(|| dtype_error(path, &key, view.dtype()))?;
        out.insert(key, HostTensor::new(view.shape().to_vec(), data));
    }
    let dtype = if all_bf16 && !out.is_empty() { StoredDtype::Bf16 } else { StoredDtype::F32 };
    Ok((out, dtype))
}

/// The tensors of a safetensors file by the names the model asks for: the `model._orig_mod.` prefix torch.compile
/// leaves stripped, legacy normaliser buffers dropped.
fn checkpoint_tensors<'a>(
    bytes: &'a [u8],
    path: &Path,
) -> Result<Vec<(String, safetensors::tensor::TensorView<'a>)>, PolicyError> {
    let st = SafeTensors::deserialize(bytes)
        .map_err(|e| PolicyError::Safetensors { path: path.into(), message: e.to_string() })?;
    Ok(st
        .tensors()
        .into_iter()
        .filter(|(key, _)| !NORMALIZER_PREFIXES.iter().any(|p| key.starts_with(p)))
        .map(|(key, view)| match key.strip_prefix("model._orig_mod.") {
            Some(rest) => (format!("model.{rest}"), view),
            None => (key, view),
        })
        .collect())
}

fn dtype_error(path: &Path, key: &str, dtype: Dtype) -> PolicyError {
    PolicyError::Dtype { path: path.into(), key: key.into(), dtype: format!("{dtype:?}") }
}

/// Little-endian F32/BF16/F16 bytes to f32; None for any other dtype.
pub fn decode_floats(dtype: Dtype, bytes: &[u8]) -> Option<Vec<f32>> {
    let words = |n: usize| bytes.chunks_exact(n);
    Some(match dtype {
        Dtype::F32 => words(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
        Dtype::BF16 => words(2).map(|b| half::bf16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
        Dtype::F16 => words(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
        _ => return None,
    })
}

/// The dtype a checkpoint's tensors are stored in: f32, or bf16 (LeRobot's `smolvla_base` is bf16, half the bytes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StoredDtype {
    #[default]
    F32,
    Bf16,
}

impl StoredDtype {
    fn safetensors(self) -> Dtype {
        match self {
            Self::F32 => Dtype::F32,
            Self::Bf16 => Dtype::BF16,
        }
    }

    /// Bytes per value.
    fn bytes(self) -> usize {
        match self {
            Self::F32 => 4,
            Self::Bf16 => 2,
        }
    }

    fn encode(self, values: &[f32]) -> Vec<u8> {
        match self {
            Self::F32 => values.iter().flat_map(|x| x.to_le_bytes()).collect(),
            // Round to nearest even, as torch's `.to(torch.bfloat16)` does.
            Self::Bf16 => values.iter().flat_map(|&x| half::bf16::from_f32(x).to_le_bytes()).collect(),
        }
    }
}

/// A tensor of a checkpoint to be written, where it is held: on the host, or on a device. Its values are read and
/// encoded only when the writer reaches it, so a checkpoint is written (or serialised) holding one tensor's bytes at
/// a time beside its weights, never a copy of them all (1.8 GB of f32 at the base size).
#[derive(Debug, Clone, Copy)]
pub enum TensorRef<'a> {
    Host(&'a HostTensor),
    Device { flat: &'a Tensor<1>, shape: &'a [usize] },
}

impl TensorRef<'_> {
    pub fn shape(&self) -> &[usize] {
        match self {
            Self::Host(t) => &t.shape,
            Self::Device { shape, .. } => shape,
        }
    }

    fn numel(&self) -> usize {
        self.shape().iter().product()
    }

    fn encode(&self, dtype: StoredDtype) -> Vec<u8> {
        match self {
            Self::Host(t) => dtype.encode(&t.data),
            Self::Device { flat, .. } => {
                dtype.encode(&flat.to_data().convert::<f32>().try_into_vec::<f32>().expect("f32 tensor data"))
            }
        }
    }
}

/// Every tensor of `weights`, as [`TensorRef`]s.
pub fn host_refs(weights: &WeightMap) -> impl Iterator<Item = (&String, TensorRef<'_>)> + Clone {
    weights.iter().map(|(k, t)| (k, TensorRef::Host(t)))
}

/// A [`TensorRef`] as safetensors' writers see it, encoded in `dtype` when its bytes are asked for.
struct Encoded<'a> {
    tensor: TensorRef<'a>,
    dtype: StoredDtype,
}

impl safetensors::View for Encoded<'_> {
    fn dtype(&self) -> Dtype {
        self.dtype.safetensors()
    }

    fn shape(&self) -> &[usize] {
        self.tensor.shape()
    }

    fn data(&self) -> std::borrow::Cow<'_, [u8]> {
        self.tensor.encode(self.dtype).into()
    }

    fn data_len(&self) -> usize {
        self.tensor.numel() * self.dtype.bytes()
    }
}

fn encoded<'a>(
    tensors: impl IntoIterator<Item = (&'a String, TensorRef<'a>)>,
    dtype: StoredDtype,
) -> impl Iterator<Item = (&'a String, Encoded<'a>)> {
    tensors.into_iter().map(move |(k, tensor)| (k, Encoded { tensor, dtype }))
}

/// Writes tensors as F32 safetensors (the dtype LeRobot's `save_pretrained` uses for fp32 models), atomically,
/// so a crash never leaves a half-written checkpoint.
pub fn write_safetensors(path: &Path, tensors: &WeightMap) -> Result<(), PolicyError> {
    write_safetensors_as(path, host_refs(tensors), StoredDtype::F32)
}

/// [`write_safetensors`] in `dtype`, streamed to the file tensor by tensor.
pub fn write_safetensors_as<'a>(
    path: &Path,
    tensors: impl IntoIterator<Item = (&'a String, TensorRef<'a>)>,
    dtype: StoredDtype,
) -> Result<(), PolicyError> {
    let views = encoded(tensors, dtype);
    fedvla_fs::write_atomic_with(path, |tmp| serialize_to_file(views, None, tmp).map_err(std::io::Error::other))
        .map_err(|e| PolicyError::io(path, e))
}

/// Serialises tensors as F32 safetensors bytes.
pub fn safetensors_bytes(tensors: &WeightMap) -> Result<Vec<u8>, PolicyError> {
    safetensors_bytes_as(host_refs(tensors), StoredDtype::F32)
}

/// Serialises tensors as safetensors bytes of `dtype`, encoding one tensor at a time into the result.
pub fn safetensors_bytes_as<'a>(
    tensors: impl IntoIterator<Item = (&'a String, TensorRef<'a>)>,
    dtype: StoredDtype,
) -> Result<Vec<u8>, PolicyError> {
    serialize(encoded(tensors, dtype), None)
        .map_err(|e| PolicyError::Safetensors { path: "<memory>".into(), message: e.to_string() })
}

/// Compares a checkpoint with the configuration's tensor list and reports, in one error, every
/// missing key, unexpected key and shape mismatch.
pub fn check_keys(specs: &[ParamSpec], weights: &WeightMap, source_name: &str) -> Result<(), PolicyError> {
    check_shapes(specs, weights.iter().map(|(k, t)| (k.as_str(), t.shape.as_slice())), source_name)
}

/// [`check_keys`] of a checkpoint given as its tensors' names and shapes (one held in parts, or on a device).
pub fn check_shapes<'a>(
    specs: &[ParamSpec],
    shapes: impl IntoIterator<Item = (&'a str, &'a [usize])>,
    source_name: &str,
) -> Result<(), PolicyError> {
    let shapes: BTreeMap<&str, &[usize]> = shapes.into_iter().collect();
    let mut report = Vec::new();
    for spec in specs {
        match shapes.get(spec.name.as_str()) {
            None => report.push(format!("  missing key {} (expected shape {:?})", spec.name, spec.shape)),
            Some(shape) if *shape != spec.shape.as_slice() => report.push(format!(
                "  wrong shape for {}: file has {:?}, config expects {:?}",
                spec.name, shape, spec.shape
            )),
            Some(_) => {}
        }
    }
    let known: std::collections::HashSet<&str> = specs.iter().map(|s| s.name.as_str()).collect();
    for key in shapes.keys().filter(|k| !known.contains(*k)) {
        report.push(format!("  unexpected key {key}"));
    }
    if report.is_empty() {
        Ok(())
    } else {
        Err(PolicyError::KeyMismatch { source_name: source_name.into(), report: report.join("\n") })
    }
}

/// Seeded initialisation in the spirit of transformers' `_init_weights`: N(0, 0.02) for matrices
/// and embeddings, ones for norm scales, zeros for biases.
pub fn init_random(specs: &[ParamSpec], seed: u64) -> WeightMap {
    let mut rng = StdRng::seed_from_u64(seed);
    let normal = Normal::new(0.0f32, 0.02).expect("valid normal");
    specs
        .iter()
        .map(|s| {
            let n = s.numel();
            let is_norm = s.name.contains("norm") && s.name.ends_with(".weight");
            let data = if is_norm {
                vec![1.0; n]
            } else if s.name.ends_with(".bias") {
                vec![0.0; n]
            } else {
                (0..n).map(|_| normal.sample(&mut rng)).collect()
            };
            (s.name.clone(), HostTensor::new(s.shape.clone(), data))
        })
        .collect()
}

/// `weight` in f32 for computing with it: a no-op for an f32 tensor, a copy of a bf16 one (exact: every bf16 is an
/// f32) that lives as long as the operation using it.
pub fn as_f32<const D: usize>(weight: Tensor<D>) -> Tensor<D> {
    weight.cast(burn::tensor::FloatDType::F32)
}

/// Tensors on a device, by LeRobot key. Layers take their weights from here by name, so the
/// checkpoint's own names are the only mapping there is.
#[derive(Debug, Clone)]
pub struct ParamStore {
    tensors: BTreeMap<String, (Tensor<1>, Vec<usize>)>,
    /// Every name asked for, when recording (to check the loaders against the key list).
    reads: Option<Arc<Mutex<BTreeSet<String>>>>,
}

impl ParamStore {
    /// Uploads the given tensors; `require_grad` marks them as autodiff leaves.
    pub fn upload<'a>(
        tensors: impl IntoIterator<Item = (&'a String, &'a HostTensor)>,
        device: &Device,
        require_grad: bool,
    ) -> Self {
        // One tensor copied at a time, as it is uploaded.
        Self::upload_owned(tensors.into_iter().map(|(k, t)| (k.clone(), t.clone())), device, require_grad)
    }

    /// [`ParamStore::upload`] of tensors it takes: each one's values move to the device, and on the CPU they stay
    /// where they are (no copy: a checkpoint read is never held twice while it is uploaded).
    pub fn upload_owned(
        tensors: impl IntoIterator<Item = (String, HostTensor)>,
        device: &Device,
        require_grad: bool,
    ) -> Self {
        let tensors = tensors
            .into_iter()
            .map(|(k, t)| {
                let len = t.data.len();
                let flat = Tensor::<1>::from_data(TensorData::new(t.data, [len]), device);
                let flat = if require_grad { flat.require_grad() } else { flat };
                (k, (flat, t.shape))
            })
            .collect();
        Self { tensors, reads: None }
    }

    /// The tensors of a safetensors file's bytes (`path` names it in errors) as constants on `device`, read one at
    /// a time (no f32 copy of the whole file is ever held). With `keep_bf16` a BF16 tensor stays BF16 there: half
    /// the memory of f32 (0.7 GB instead of 1.4 for `smolvla_base`'s frozen tensors, in a browser's 4 GiB), and
    /// the same results, the layers casting each weight to f32 where they use it (see [`ParamStore::get`]); every
    /// other float tensor becomes f32. Only for a device with bf16 storage: the CPU's.
    pub fn from_safetensors(bytes: &[u8], path: &Path, device: &Device, keep_bf16: bool) -> Result<Self, PolicyError> {
        let mut tensors = BTreeMap::new();
        for (key, view) in checkpoint_tensors(bytes, path)? {
            let len = view.shape().iter().product::<usize>();
            let data = if keep_bf16 && view.dtype() == Dtype::BF16 {
                let words = view.data().chunks_exact(2).map(|b| half::bf16::from_le_bytes([b[0], b[1]])).collect();
                TensorData::new::<half::bf16, _>(words, [len])
            } else {
                let values =
                    decode_floats(view.dtype(), view.data()).ok_or_else(|| dtype_error(path, &key, view.dtype()))?;
                TensorData::new(values, [len])
            };
            let options = TensorCreationOptions::new(device.clone()).with_dtype(data.dtype());
            tensors.insert(key, (Tensor::<1>::from_data(data, options), view.shape().to_vec()));
        }
        Ok(Self { tensors, reads: None })
    }

    pub fn from_flat(tensors: BTreeMap<String, (Tensor<1>, Vec<usize>)>) -> Self {
        Self { tensors, reads: None }
    }

    /// This store, recording every name the layers ask it for into the returned set.
    pub fn recording(&self) -> (Self, Arc<Mutex<BTreeSet<String>>>) {
        let reads = Arc::new(Mutex::new(BTreeSet::new()));
        (Self { tensors: self.tensors.clone(), reads: Some(Arc::clone(&reads)) }, reads)
    }

    /// This store with `other`'s tensors added, replacing any of the same name.
    pub fn overlaid(&self, other: &ParamStore) -> Self {
        let mut tensors = self.tensors.clone();
        tensors.extend(other.tensors.iter().map(|(k, v)| (k.clone(), v.clone())));
        Self { tensors, reads: self.reads.clone() }
    }

    /// The tensor `name` in its checkpoint shape and stored dtype (f32, or bf16 from
    /// [`ParamStore::from_safetensors`]: a layer holding one computes with [`as_f32`] of it, at use). Panics on an
    /// unknown name: every name asked for comes from `SmolVlaConfig::param_specs`, which the loader has already
    /// checked against.
    pub fn get<const D: usize>(&self, name: &str) -> Tensor<D> {
        if let Some(reads) = &self.reads {
            reads.lock().expect("reads lock").insert(name.to_owned());
        }
        let (flat, shape) = self.tensors.get(name).unwrap_or_else(|| panic!("parameter {name} not in store"));
        let dims: [usize; D] =
            shape.as_slice().try_into().unwrap_or_else(|_| panic!("parameter {name} has rank {}", shape.len()));
        flat.clone().reshape(dims)
    }

    pub fn contains(&self, name: &str) -> bool {
        self.tensors.contains_key(name)
    }

    pub fn flat(&self) -> impl Iterator<Item = (&String, &Tensor<1>, &Vec<usize>)> {
        self.tensors.iter().map(|(k, (t, s))| (k, t, s))
    }

    /// Every tensor, as [`TensorRef`]s (to write them without reading them all at once).
    pub fn refs(&self) -> impl Iterator<Item = (&String, TensorRef<'_>)> + Clone {
        self.tensors.iter().map(|(k, (flat, shape))| (k, TensorRef::Device { flat, shape }))
    }

    /// [`ParamStore::to_host`], read asynchronously (a browser's WebGPU device cannot read synchronously).
    pub async fn to_host_async(&self) -> Result<WeightMap, PolicyError> {
        let mut out = WeightMap::new();
        for (k, (t, s)) in &self.tensors {
            let data =
                t.to_data_async().await.map_err(|e| PolicyError::Input(format!("reading {k} from the device: {e}")))?;
            out.insert(
                k.clone(),
                HostTensor::new(s.clone(), data.convert::<f32>().try_into_vec::<f32>().expect("f32 tensor data")),
            );
        }
        Ok(out)
    }

    pub fn to_host(&self) -> WeightMap {
        self.tensors
            .iter()
            .map(|(k, (t, s))| {
                let data = t.to_data().convert::<f32>().try_into_vec::<f32>().expect("f32 tensor data");
                (k.clone(), HostTensor::new(s.clone(), data))
            })
            .collect()
    }
}
