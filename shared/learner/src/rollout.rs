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
use serde::{Deserialize, Serialize};

/// The sim camera that feeds each policy camera: by name (`…top`, `…wrist`), else by slot order.
fn camera_for(key: &str, slot: usize) -> Result<Camera, PolicyError> {
    Camera::ALL
        .into_iter()
        .find(|c| key.rsplit('.').next() == Some(c.name()))
        .or_else(|| Camera::ALL.get(slot).copied())
        .ok_or_else(|| {
            PolicyError::Input(format!("policy camera {key} has no simulated counterpart (the sim has top and wrist)"))
        })
}

/// A task tokenised as the policy reads it: `(ids, mask, padded length)`.
pub type TaskTokens = (Vec<i64>, Vec<bool>, usize);

/// A policy ready to act in the sim.
pub struct SimPolicy {
    model: SmolVla,
    stats: NormStats,
    cameras: Vec<(Camera, usize, usize)>,
    tokens: TaskTokens,
    device: Device,
}

impl SimPolicy {
    /// `weights` holds every tensor of `cfg`; the policy is tokenised once for the sim's task.
    pub fn new(
        cfg: &SmolVlaConfig,
        weights: &WeightMap,
        stats: NormStats,
        tokenizer: &Tokenizer,
        device: &Device,
    ) -> Result<Self, PolicyError> {
        fedvla_policy::weights::check_keys(&cfg.param_specs(), weights, "rollout policy")?;
        let tokens = tokenizer.encode_batch(&[TASK], cfg.tokenizer_max_length, cfg.pad_language_to == "max_length")?;
        let store = ParamStore::upload(weights.iter(), device, false);
        Self::from_model(SmolVla::new(cfg, &store), stats, tokens)
    }

    /// A model already on its device (without autodiff) as a sim policy, with the sim's task tokenised.
    pub fn from_model(model: SmolVla, stats: NormStats, tokens: TaskTokens) -> Result<Self, PolicyError> {
        let cameras = model
            .cfg
            .input_features
            .iter()
            .filter(|f| f.kind == "VISUAL")
            .enumerate()
            .map(|(slot, f)| {
                let (h, w) = (f.shape.get(1).copied().unwrap_or(256), f.shape.get(2).copied().unwrap_or(256));
                camera_for(&f.name, slot).map(|c| (c, h, w))
            })
            .collect::<Result<_, _>>()?;
        let device = model.device();
        Ok(Self { model, stats, cameras, tokens, device })
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
        let chunk =
            HostTensor::from_tensor(self.model.sample_actions(&obs, noise, None).narrow(2, 0, cfg.action_dim()));
        let actions = self.stats.get("action")?.unnormalize(&chunk.data);
        Ok(actions
            .chunks_exact(cfg.action_dim())
            .take(cfg.n_action_steps.max(1))
            .map(|a| std::array::from_fn(|i| a.get(i).copied().unwrap_or(0.0)))
            .collect())
    }
}

/// How an episode went.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeResult {
    pub seed: u64,
    pub success: bool,
    /// Frames executed (30 fps) until success or the budget.
    pub length: usize,
}

/// An episode in progress: the scene and the queue of actions left from the last chunk.
pub struct Episode<'a> {
    policy: &'a SimPolicy,
    scene: Scene,
    rng: StdRng,
    queue: std::vec::IntoIter<[f32; JOINT_COUNT]>,
    seed: u64,
    length: usize,
    max_frames: usize,
}

impl<'a> Episode<'a> {
    /// The episode on `Scene::new(seed)`, at most `max_frames` frames long.
    pub fn new(policy: &'a SimPolicy, seed: u64, max_frames: usize) -> Self {
        let rng = StdRng::seed_from_u64(seed ^ 0x5_eed0_fa11);
        Self { policy, scene: Scene::new(seed), rng, queue: Vec::new().into_iter(), seed, length: 0, max_frames }
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    pub fn is_over(&self) -> bool {
        self.length >= self.max_frames || self.scene.success()
    }

    /// Executes one frame (sampling a new chunk when the last one is used up); false once the episode is over.
    pub fn step(&mut self) -> Result<bool, PolicyError> {
        if self.is_over() {
            return Ok(false);
        }
        let action = match self.queue.next() {
            Some(action) => action,
            None => {
                self.queue = self.policy.act(&self.scene, &mut self.rng)?.into_iter();
                self.queue
                    .next()
                    .ok_or_else(|| PolicyError::Input("the policy returned an empty action chunk".into()))?
            }
        };
        self.scene.step(action);
        self.length += 1;
        Ok(true)
    }

    pub fn result(&self) -> EpisodeResult {
        EpisodeResult { seed: self.seed, success: self.scene.success(), length: self.length }
    }
}

/// Rolls the policy out from `Scene::new(seed)` for at most `max_frames` frames. `on_frame` sees
/// the scene after every step (to film it).
pub fn run_episode(
    policy: &SimPolicy,
    seed: u64,
    max_frames: usize,
    mut on_frame: impl FnMut(&Scene),
) -> Result<EpisodeResult, PolicyError> {
    let mut episode = Episode::new(policy, seed, max_frames);
    on_frame(episode.scene());
    while episode.step()? {
        on_frame(episode.scene());
    }
    Ok(episode.result())
}
