//! Closed-loop rollouts of a SmolVLA policy in the SO-100 simulation: render the policy's cameras,
//! normalise the state, sample an action chunk, un-normalise it and execute `n_action_steps` of it
//! (LeRobot's `select_action` queue), until the task succeeds or the frame budget runs out.

use burn::tensor::Device;
use fedvla_policy::batch::{Prepared, rgb_hwc_to_chw};
use fedvla_policy::smolvla::gaussian_noise;
use fedvla_policy::weights::{HostTensor, ParamStore, WeightMap};
use fedvla_policy::{Batch, NormStats, PolicyError, SmolVla, SmolVlaConfig, Tokenizer};
use fedvla_sim::{Camera, JOINT_COUNT, Scene, TASK, render};
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde::Serialize;

/// The sim camera that feeds each policy camera: by name (`…top`, `…wrist`), else by slot order.
fn camera_for(key: &str, slot: usize) -> Result<Camera, PolicyError> {
    Camera::ALL
        .into_iter()
        .find(|c| key.rsplit('.').next() == Some(c.name()))
        .or_else(|| Camera::ALL.get(slot).copied())
        .ok_or_else(|| PolicyError::Input(format!("policy camera {key} has no simulated counterpart (the sim has top and wrist)")))
}

/// A policy ready to act in the sim.
pub struct SimPolicy {
    model: SmolVla,
    stats: NormStats,
    cameras: Vec<(Camera, usize, usize)>,
    tokens: (Vec<i64>, Vec<bool>, usize),
    device: Device,
}

impl SimPolicy {
    /// `weights` holds every tensor of `cfg`; the policy is tokenised once for the sim's task.
    pub fn new(cfg: &SmolVlaConfig, weights: &WeightMap, stats: NormStats, tokenizer: &Tokenizer, device: &Device) -> Result<Self, PolicyError> {
        fedvla_policy::weights::check_keys(&cfg.param_specs(), weights, "rollout policy")?;
        let store = ParamStore::upload(weights.iter(), device, false);
        let cameras = cfg
            .input_features
            .iter()
            .filter(|f| f.kind == "VISUAL")
            .enumerate()
            .map(|(slot, f)| {
                let (h, w) = (f.shape.get(1).copied().unwrap_or(256), f.shape.get(2).copied().unwrap_or(256));
                camera_for(&f.name, slot).map(|c| (c, h, w))
            })
            .collect::<Result<_, _>>()?;
        let tokens = tokenizer.encode_batch(&[TASK], cfg.tokenizer_max_length, cfg.pad_language_to == "max_length")?;
        Ok(Self { model: SmolVla::new(cfg, &store, &store), stats, cameras, tokens, device: device.clone() })
    }

    /// Camera images of the current scene as the policy sees them (`[1, 3, H, W]` in [0, 1]).
    fn observe(&self, scene: &Scene) -> Result<Batch, PolicyError> {
        let images = self
            .cameras
            .iter()
            .map(|&(cam, h, w)| {
                let mut chw = vec![0.0f32; 3 * h * w];
                rgb_hwc_to_chw(&render(scene, cam, w, h), &mut chw);
                HostTensor::new(vec![1, 3, h, w], chw)
            })
            .collect();
        let state = self.stats.get("observation.state")?.normalize(&scene.state());
        let (ids, mask, len) = self.tokens.clone();
        Ok(Batch {
            images,
            lang_tokens: ids,
            lang_mask: mask,
            lang_len: len,
            state: HostTensor::new(vec![1, JOINT_COUNT], state),
            actions: None,
            action_is_pad: None,
        })
    }

    /// One action chunk (goal positions in robot units) for the current scene.
    pub fn act(&self, scene: &Scene, rng: &mut StdRng) -> Result<Vec<[f32; JOINT_COUNT]>, PolicyError> {
        let cfg = &self.model.cfg;
        let batch = self.observe(scene)?;
        let obs = Prepared::new(cfg, &batch, &self.device)?;
        let noise = gaussian_noise(rng, [1, cfg.chunk_size, cfg.max_action_dim], &self.device);
        let chunk = HostTensor::from_tensor(self.model.sample_actions(&obs, noise, None).narrow(2, 0, cfg.action_dim()));
        let actions = self.stats.get("action")?.unnormalize(&chunk.data);
        Ok(actions
            .chunks_exact(cfg.action_dim())
            .take(cfg.n_action_steps.max(1))
            .map(|a| std::array::from_fn(|i| a.get(i).copied().unwrap_or(0.0)))
            .collect())
    }
}

/// How an episode went.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EpisodeResult {
    pub seed: u64,
    pub success: bool,
    /// Frames executed (30 fps) until success or the budget.
    pub length: usize,
}

/// Rolls the policy out from `Scene::new(seed)` for at most `max_frames` frames. `on_frame` sees
/// the scene after every step (to film it).
pub fn run_episode(
    policy: &SimPolicy,
    seed: u64,
    max_frames: usize,
    mut on_frame: impl FnMut(&Scene),
) -> Result<EpisodeResult, PolicyError> {
    let mut scene = Scene::new(seed);
    let mut rng = StdRng::seed_from_u64(seed ^ 0x5eed_0f_a11);
    on_frame(&scene);
    let mut length = 0;
    while length < max_frames && !scene.success() {
        for action in policy.act(&scene, &mut rng)? {
            scene.step(action);
            length += 1;
            on_frame(&scene);
            if length >= max_frames || scene.success() {
                break;
            }
        }
    }
    Ok(EpisodeResult { seed, success: scene.success(), length })
}
