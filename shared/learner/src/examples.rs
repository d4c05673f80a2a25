//! Policy batches from a client shard: camera frames to [0, 1] CHW, state and action chunks
//! normalised with the dataset statistics the shard carries, LeRobot's `action_is_pad`, and the
//! task's token ids.

use std::collections::BTreeMap;

use fedvla_data::{ClientShard, DatasetInfo, ShardSpec};
use fedvla_federation::OpeningFrames;
use fedvla_federation::data_report::{
    DataReport, DatasetSignature, FeatureMoments, NORMALISED_FEATURES, NormalizationStats, OwnDataset,
};
use fedvla_policy::batch::rgb_hwc_to_chw;
use fedvla_policy::tokenizer::PAD_ID;
use fedvla_policy::weights::HostTensor;
use fedvla_policy::{Batch, FeatureStats, NormStats, PolicyError, SmolVlaConfig, Tokenizer};
use fedvla_sim::TaskKind;
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

/// A shard with the policy-side view of its rows.
#[derive(Debug, Clone)]
pub struct ShardExamples {
    shard: ClientShard,
    stats: NormStats,
    cameras: Vec<String>,
    /// Rows of training episodes and of held-out episodes.
    pub train_rows: Vec<usize>,
    pub held_out_rows: Vec<usize>,
    /// The row whose action chunk labels each row: itself, unless [`ShardExamples::shuffle_labels`] poisoned them.
    label_rows: Vec<usize>,
}

/// MEAN_STD statistics of `observation.state` and `action` as the shard carries them.
pub fn shard_stats(shard: &ClientShard) -> Result<NormStats, PolicyError> {
    let mut stats = NormStats::default();
    for feature in ["observation.state", "action"] {
        let s = shard
            .stats
            .get(feature)
            .ok_or_else(|| PolicyError::Input(format!("shard has no statistics for {feature}")))?;
        let get = |k: &str| {
            s.get(k).cloned().ok_or_else(|| PolicyError::Input(format!("shard statistics of {feature} lack {k}")))
        };
        stats.features.insert(feature.into(), FeatureStats { mean: get("mean")?, std: get("std")? });
    }
    Ok(stats)
}

/// How a shard for a policy of `cfg` is packed: frames at its input size, tasks as token ids of its length.
pub fn shard_spec(cfg: &SmolVlaConfig) -> ShardSpec {
    let (w, h) = cfg.resize_imgs_with_padding;
    ShardSpec {
        image_width: w as u32,
        image_height: h as u32,
        tokenizer_max_length: cfg.tokenizer_max_length,
        pad_token_id: PAD_ID as u32,
    }
}

/// Every task of `tasks`, and "" (rows without one), as `tokenizer`'s ids for a policy of `cfg`: tokenized up
/// front, so that a task the tokenizer refuses stops the packing of a shard, named.
pub fn task_token_ids(
    tokenizer: &Tokenizer,
    tasks: &[String],
    cfg: &SmolVlaConfig,
) -> Result<BTreeMap<String, Vec<u32>>, PolicyError> {
    tasks
        .iter()
        .map(String::as_str)
        .chain([""])
        .map(|task| {
            let (ids, _, _) = tokenizer
                .encode_batch(&[task], cfg.tokenizer_max_length, false)
                .map_err(|e| PolicyError::Tokenizer(format!("tokenizing the task {task:?}: {e}")))?;
            Ok((task.to_owned(), ids.into_iter().map(|i| i as u32).collect()))
        })
        .collect()
}

/// What a dataset must share with a run's for a policy to read both alike, from its `meta/info.json`: robot
/// type, fps, state and action dimensions and names, and cameras (video features) in order.
pub fn dataset_signature(info: &DatasetInfo) -> DatasetSignature {
    let vector = |key: &str| {
        let Some(feature) = info.features.get(key) else { return (0, Vec::new()) };
        // Names are a list, or in older datasets a map such as {"motors": [...]}, or null.
        let list = match &feature.names {
            serde_json::Value::Object(map) => map.values().next().cloned().unwrap_or_default(),
            other => other.clone(),
        };
        let names = list.as_array().map(|a| a.iter().map(|n| n.as_str().unwrap_or_default().to_owned()).collect());
        (feature.shape.iter().product(), names.unwrap_or_default())
    };
    let (state_dim, state_names) = vector(NORMALISED_FEATURES[0]);
    let (action_dim, action_names) = vector(NORMALISED_FEATURES[1]);
    DatasetSignature {
        robot_type: info.robot_type.clone(),
        fps: info.fps,
        state_dim,
        state_names,
        action_dim,
        action_names,
        cameras: info.features.video_keys(),
    }
}

/// The policy's view of the run's statistics: mean and std of [`NORMALISED_FEATURES`].
pub fn norm_stats(stats: &NormalizationStats) -> Result<NormStats, PolicyError> {
    let mut out = NormStats::default();
    for feature in NORMALISED_FEATURES {
        let s = stats
            .features
            .get(feature)
            .ok_or_else(|| PolicyError::Input(format!("the run's normalisation statistics lack {feature}")))?;
        let to_f32 = |v: &[f64]| v.iter().map(|&x| x as f32).collect();
        out.features.insert(feature.into(), FeatureStats { mean: to_f32(&s.mean), std: to_f32(&s.std) });
    }
    Ok(out)
}

impl ShardExamples {
    pub fn new(shard: ClientShard, cfg: &SmolVlaConfig) -> Result<Self, PolicyError> {
        let cameras = cfg.camera_keys();
        for key in &cameras {
            if !shard.manifest.cameras.contains(key) {
                return Err(PolicyError::Input(format!(
                    "shard has cameras {:?} but the policy reads {key}",
                    shard.manifest.cameras
                )));
            }
        }
        if shard.task_tokens.is_none() {
            return Err(PolicyError::Input("shard carries no task token ids".into()));
        }
        let stats = shard_stats(&shard)?;
        let rows = |held_out: bool| -> Vec<usize> {
            shard.episodes.iter().filter(|e| e.held_out == held_out).flat_map(|e| e.start..e.end).collect()
        };
        let (train_rows, held_out_rows) = (rows(false), rows(true));
        let label_rows = (0..shard.frame_index.len()).collect();
        Ok(Self { stats, cameras, train_rows, held_out_rows, label_rows, shard })
    }

    pub fn stats(&self) -> &NormStats {
        &self.stats
    }

    /// Normalises with the run's statistics from now on instead of those the shard carries.
    pub fn set_norm_stats(&mut self, stats: &NormalizationStats) -> Result<(), PolicyError> {
        self.stats = norm_stats(stats)?;
        Ok(())
    }

    /// What the client tells the server of this data on join: the moments of its state and action over every
    /// row (its training and held-out episodes), and `own` when it is the client's own dataset.
    pub fn data_report(&self, own: Option<OwnDataset>) -> DataReport {
        let m = &self.shard.manifest;
        let moments = [
            (NORMALISED_FEATURES[0], &self.shard.state, m.state_dim),
            (NORMALISED_FEATURES[1], &self.shard.action, m.action_dim),
        ]
        .into_iter()
        .map(|(feature, values, dim)| {
            (feature.to_owned(), FeatureMoments::of_rows(dim, values.chunks_exact(dim.max(1))))
        })
        .collect();
        DataReport { own, moments }
    }

    /// The SHA-256 of the shard's content (frames, vectors, tokens), as its manifest records it.
    pub fn content_sha256(&self) -> &str {
        &self.shard.manifest.content_sha256
    }

    /// The task (instruction) row `row` records.
    pub fn task_of(&self, row: usize) -> &str {
        self.shard.manifest.tasks.get(self.task_index(row)).map_or("", String::as_str)
    }

    /// The index of row `row`'s task among the shard's tasks.
    pub(crate) fn task_index(&self, row: usize) -> usize {
        self.shard.task_index.get(row).map_or(0, |&t| t as usize)
    }

    /// The index among the shard's tasks of the instruction told in place of row `row`'s to check that a policy
    /// reads it ([`TaskKind::another_goal`]); `None` where its task's instruction does not decide the goal, or the
    /// shard has no token ids for that other instruction ([`ShardExamples::add_other_goals`] adds them).
    pub fn another_goal_task(&self, row: usize) -> Option<usize> {
        let another = TaskKind::another_goal(self.task_of(row))?;
        self.shard.manifest.tasks.iter().position(|task| *task == another)
    }

    /// Adds to the shard's instructions every other goal's ([`TaskKind::another_goal`]) that none of its rows
    /// records, tokenized by `tokenizer` and padded as the shard's own were packed, so that every row of a task
    /// whose instruction decides the goal can be told another (the held-out language check); a shard holds the
    /// instructions of its own rows only.
    pub fn add_other_goals(&mut self, tokenizer: &Tokenizer, cfg: &SmolVlaConfig) -> Result<(), PolicyError> {
        let tasks = &self.shard.manifest.tasks;
        let mut missing: Vec<String> =
            tasks.iter().filter_map(|task| TaskKind::another_goal(task)).filter(|o| !tasks.contains(o)).collect();
        missing.sort();
        missing.dedup();
        let ids = task_token_ids(tokenizer, &missing, cfg)?;
        // Padded to the length the shard's own were packed at, which its batches slice by.
        let spec = ShardSpec { tokenizer_max_length: self.shard.manifest.tokenizer_max_length, ..shard_spec(cfg) };
        let (all_ids, all_mask) = self.shard.task_tokens.as_mut().expect("checked in new");
        for task in missing {
            for (id, is_task) in spec.padded_task_tokens(&ids[&task]) {
                all_ids.push(id);
                all_mask.push(is_task);
            }
            self.shard.manifest.tasks.push(task);
        }
        Ok(())
    }

    /// The training rows one pass of local steps draws from: each once, except that with `opening` the opening
    /// frames of episodes whose instruction decides the goal come `opening.repeat` times.
    pub fn training_draws(&self, opening: Option<OpeningFrames>) -> Vec<usize> {
        let Some(OpeningFrames { frames, repeat }) = opening else { return self.train_rows.clone() };
        let decides: Vec<bool> = self
            .shard
            .manifest
            .tasks
            .iter()
            .map(|task| TaskKind::of_instruction(task).is_some_and(TaskKind::instruction_decides))
            .collect();
        let opens = |row: usize| {
            decides.get(self.task_index(row)).copied().unwrap_or(false)
                && self.shard.frame_index.get(row).is_some_and(|&i| (0..i64::from(frames)).contains(&i))
        };
        self.train_rows
            .iter()
            .flat_map(|&row| std::iter::repeat_n(row, if opens(row) { repeat as usize } else { 1 }))
            .collect()
    }

    /// The frames of its training episodes.
    pub fn train_examples(&self) -> u64 {
        self.train_rows.len() as u64
    }

    /// Data poisoning, for simulated attackers: every training row is labelled from then on with the action chunk
    /// of another training row, a permutation drawn from `seed`; held-out rows keep their own.
    pub fn shuffle_labels(&mut self, seed: u64) {
        let mut shuffled = self.train_rows.clone();
        shuffled.shuffle(&mut StdRng::seed_from_u64(seed));
        for (&row, &label) in self.train_rows.iter().zip(&shuffled) {
            self.label_rows[row] = label;
        }
    }

    /// The batch of `rows` for a policy with chunk size `chunk`.
    pub fn batch(&self, rows: &[usize], chunk: usize) -> Result<Batch, PolicyError> {
        let m = &self.shard.manifest;
        let (w, h) = (m.image_width as usize, m.image_height as usize);
        let b = rows.len();
        let images = self
            .cameras
            .iter()
            .map(|cam| {
                let mut chw = vec![0.0f32; b * 3 * h * w];
                for (n, &row) in rows.iter().enumerate() {
                    let hwc = self
                        .shard
                        .image(cam, row)
                        .ok_or_else(|| PolicyError::Input(format!("shard row {row} has no {cam} image")))?;
                    rgb_hwc_to_chw(hwc, &mut chw[n * 3 * h * w..(n + 1) * 3 * h * w]);
                }
                Ok(HostTensor::new(vec![b, 3, h, w], chw))
            })
            .collect::<Result<Vec<_>, PolicyError>>()?;
        let (sd, ad) = (m.state_dim, m.action_dim);
        let state_stats = self.stats.get("observation.state")?;
        let action_stats = self.stats.get("action")?;
        let mut state = Vec::with_capacity(b * sd);
        let mut actions = Vec::with_capacity(b * chunk * ad);
        let mut is_pad = Vec::with_capacity(b * chunk);
        for &row in rows {
            state.extend(state_stats.normalize(&self.shard.state[row * sd..(row + 1) * sd]));
            let (chunk_values, pad) = self
                .shard
                .action_chunk(self.label_rows[row], chunk)
                .ok_or_else(|| PolicyError::Input(format!("shard row {row} is in no episode")))?;
            actions.extend(action_stats.normalize(&chunk_values));
            is_pad.extend(pad);
        }
        let tasks: Vec<usize> = rows.iter().map(|&row| self.task_index(row)).collect();
        let (lang_tokens, lang_mask) = self.instructions(&tasks);
        Ok(Batch {
            images,
            lang_tokens,
            lang_mask,
            lang_len: m.tokenizer_max_length,
            state: HostTensor::new(vec![b, sd], state),
            actions: Some(HostTensor::new(vec![b, chunk, ad], actions)),
            action_is_pad: Some(is_pad),
        })
    }

    /// `batch` (its frames, state and actions) with each row told the instruction of the shard's task of the same
    /// place in `tasks` (an index among the shard's tasks) instead of its own.
    pub fn told(&self, batch: &Batch, tasks: &[usize]) -> Batch {
        assert_eq!(batch.state.shape[0], tasks.len(), "one task a row");
        let (lang_tokens, lang_mask) = self.instructions(tasks);
        Batch { lang_tokens, lang_mask, ..batch.clone() }
    }

    /// The token ids and attention mask of each of `tasks` (indices among the shard's tasks), one after another.
    fn instructions(&self, tasks: &[usize]) -> (Vec<i64>, Vec<bool>) {
        let (all_ids, all_mask) = self.shard.task_tokens.as_ref().expect("checked in new");
        let len = self.shard.manifest.tokenizer_max_length;
        let ids = tasks.iter().flat_map(|&task| all_ids[task * len..(task + 1) * len].iter().copied()).collect();
        let mask =
            tasks.iter().flat_map(|&task| all_mask[task * len..(task + 1) * len].iter().map(|&m| m != 0)).collect();
        (ids, mask)
    }
}
