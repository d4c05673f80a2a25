//! Closed-loop rollouts of a SmolVLA policy in the SO-100 simulation: render the policy's cameras,
//! normalise the state, sample an action chunk, un-normalise it and execute `n_action_steps` of it
//! (LeRobot's `select_action` queue), until the task succeeds or the frame budget runs out. Which
//! task each episode of a rollout sets, and the instruction the policy is told, tokenised, are
//! [`SimTasks`]'.

use std::collections::BTreeMap;

use burn::tensor::Device;
use fedvla_federation::{InstructionTokens, RolloutTasks};
use fedvla_policy::batch::{Prepared, rgb_hwc_to_chw};
use fedvla_policy::smolvla::gaussian_noise;
use fedvla_policy::weights::{HostTensor, ParamStore, WeightMap};
use fedvla_policy::{Batch, NormStats, PolicyError, SmolVla, SmolVlaConfig, Tokenizer};
use fedvla_sim::{Camera, JOINT_COUNT, Scene, TaskKind, render};
use rand::SeedableRng;
use rand::rngs::StdRng;

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

/// What a run's rollouts ask of a policy: the tasks their episodes cycle through (episode k on task `k mod n`),
/// and every instruction those tasks give (the right ones and, where the instruction decides the goal, the wrong
/// ones the language check tells), tokenised by the run's tokenizer. The wire form is [`RolloutTasks`].
#[derive(Debug, Clone, PartialEq)]
pub struct SimTasks {
    tasks: Vec<TaskKind>,
    tokens: BTreeMap<String, TaskTokens>,
}

impl SimTasks {
    /// `tasks` (at least one), every instruction they give tokenised by `tokenizer` as the policy of `cfg` reads
    /// them.
    pub fn tokenize(tasks: &[TaskKind], tokenizer: &Tokenizer, cfg: &SmolVlaConfig) -> Result<Self, PolicyError> {
        if tasks.is_empty() {
            return Err(PolicyError::Input("rollouts need at least one sim task".into()));
        }
        let pad_to_max = cfg.pad_language_to == "max_length";
        let tokens = tasks
            .iter()
            .flat_map(|task| task.instructions())
            .map(|instruction| {
                let tokens = tokenizer.encode_batch(&[&instruction], cfg.tokenizer_max_length, pad_to_max)?;
                Ok((instruction, tokens))
            })
            .collect::<Result<_, PolicyError>>()?;
        Ok(Self { tasks: tasks.to_vec(), tokens })
    }

    /// As a volunteer received them; unknown task names and ids without their mask are refused.
    pub fn from_wire(wire: &RolloutTasks) -> Result<Self, PolicyError> {
        let tasks = wire
            .tasks
            .iter()
            .map(|name| TaskKind::from_name(name).map_err(|e| PolicyError::Input(format!("rollout tasks: {e}"))))
            .collect::<Result<Vec<_>, _>>()?;
        if tasks.is_empty() {
            return Err(PolicyError::Input("the server names no sim task to roll out".into()));
        }
        let tokens = wire
            .instructions
            .iter()
            .map(|i| {
                if i.ids.len() != i.mask.len() {
                    return Err(PolicyError::Input(format!(
                        "instruction {:?}: {} token ids but {} mask entries",
                        i.instruction,
                        i.ids.len(),
                        i.mask.len()
                    )));
                }
                let ids: Vec<i64> = i.ids.iter().map(|&id| i64::from(id)).collect();
                Ok((i.instruction.clone(), (ids, i.mask.clone(), i.ids.len())))
            })
            .collect::<Result<_, PolicyError>>()?;
        Ok(Self { tasks, tokens })
    }

    /// As the server offers them to volunteers.
    pub fn to_wire(&self) -> RolloutTasks {
        RolloutTasks {
            tasks: self.tasks.iter().map(|task| task.name().to_owned()).collect(),
            instructions: self
                .tokens
                .iter()
                .map(|(instruction, (ids, mask, _))| InstructionTokens {
                    instruction: instruction.clone(),
                    ids: ids.iter().map(|&id| id as u32).collect(),
                    mask: mask.clone(),
                })
                .collect(),
        }
    }

    pub fn tasks(&self) -> &[TaskKind] {
        &self.tasks
    }

    /// The task of a rollout's episode `episode`.
    pub fn task_of(&self, episode: usize) -> TaskKind {
        self.tasks[episode % self.tasks.len()]
    }

    /// `instruction` tokenised.
    fn tokens(&self, instruction: &str) -> Result<&TaskTokens, PolicyError> {
        self.tokens.get(instruction).ok_or_else(|| {
            PolicyError::Input(format!("the instruction {instruction:?} is not among the run's rollout instructions"))
        })
    }
}

/// A policy ready to act in the sim.
pub struct SimPolicy {
    model: SmolVla,
    stats: NormStats,
    cameras: Vec<(Camera, usize, usize)>,
    tasks: SimTasks,
    device: Device,
}

impl SimPolicy {
    /// `weights` holds every tensor of `cfg`; the instructions of `tasks` are tokenised once with `tokenizer`.
    pub fn new(
        cfg: &SmolVlaConfig,
        weights: &WeightMap,
        stats: NormStats,
        tokenizer: &Tokenizer,
        tasks: &[TaskKind],
        device: &Device,
    ) -> Result<Self, PolicyError> {
        fedvla_policy::weights::check_keys(&cfg.param_specs(), weights, "rollout policy")?;
        let tasks = SimTasks::tokenize(tasks, tokenizer, cfg)?;
        let store = ParamStore::upload(weights.iter(), device, false);
        Self::from_model(SmolVla::new(cfg, &store), stats, tasks)
    }

    /// A model already on its device (without autodiff) as a sim policy of `tasks`.
    pub fn from_model(model: SmolVla, stats: NormStats, tasks: SimTasks) -> Result<Self, PolicyError> {
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
        Ok(Self { model, stats, cameras, tasks, device })
    }

    /// The tasks its rollouts set.
    pub fn tasks(&self) -> &SimTasks {
        &self.tasks
    }

    /// Camera images of the current scene as the policy sees them (`[1, 3, H, W]` in [0, 1]), told `tokens`.
    fn observe(&self, scene: &Scene, tokens: &TaskTokens) -> Result<Batch, PolicyError> {
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
        let (ids, mask, len) = tokens.clone();
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

    /// One action chunk (goal positions in robot units) for the current scene, told the instruction of `tokens`.
    fn act(
        &self,
        scene: &Scene,
        tokens: &TaskTokens,
        rng: &mut StdRng,
    ) -> Result<Vec<[f32; JOINT_COUNT]>, PolicyError> {
        let cfg = &self.model.cfg;
        let batch = self.observe(scene, tokens)?;
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
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeResult {
    pub task: TaskKind,
    pub seed: u64,
    pub success: bool,
    /// Frames executed (30 fps) until success or the budget.
    pub length: usize,
}

/// An episode in progress: the scene and the queue of actions left from the last chunk.
pub struct Episode<'a> {
    policy: &'a SimPolicy,
    scene: Scene,
    /// The instruction the policy is told, tokenised.
    tokens: TaskTokens,
    rng: StdRng,
    queue: std::vec::IntoIter<[f32; JOINT_COUNT]>,
    seed: u64,
    length: usize,
    max_frames: usize,
}

impl<'a> Episode<'a> {
    /// The episode on `Scene::with_task(task, seed)`, the policy told the scene's own instruction, at most
    /// `max_frames` frames long.
    pub fn new(policy: &'a SimPolicy, task: TaskKind, seed: u64, max_frames: usize) -> Result<Self, PolicyError> {
        let scene = Scene::with_task(task, seed);
        let instruction = scene.instruction();
        Self::on(policy, scene, &instruction, seed, max_frames)
    }

    /// The same episode (scene and sampling noise) with the policy told `instruction` instead: the language check.
    pub fn told(
        policy: &'a SimPolicy,
        task: TaskKind,
        seed: u64,
        instruction: &str,
        max_frames: usize,
    ) -> Result<Self, PolicyError> {
        Self::on(policy, Scene::with_task(task, seed), instruction, seed, max_frames)
    }

    fn on(
        policy: &'a SimPolicy,
        scene: Scene,
        instruction: &str,
        seed: u64,
        max_frames: usize,
    ) -> Result<Self, PolicyError> {
        let tokens = policy.tasks.tokens(instruction)?.clone();
        let rng = StdRng::seed_from_u64(seed ^ 0x5_eed0_fa11);
        Ok(Self { policy, scene, tokens, rng, queue: Vec::new().into_iter(), seed, length: 0, max_frames })
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
                self.queue = self.policy.act(&self.scene, &self.tokens, &mut self.rng)?.into_iter();
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
        EpisodeResult { task: self.scene.task(), seed: self.seed, success: self.scene.success(), length: self.length }
    }
}

/// Runs `episode` to its end. `on_frame` sees the scene before the first step and after every step (to film it).
pub fn run_episode(mut episode: Episode<'_>, mut on_frame: impl FnMut(&Scene)) -> Result<EpisodeResult, PolicyError> {
    on_frame(episode.scene());
    while episode.step()? {
        on_frame(episode.scene());
    }
    Ok(episode.result())
}
