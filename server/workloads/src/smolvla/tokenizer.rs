//! The run's one tokenizer: the word-level tokenizer of the dataset's task strings from random initialisation,
//! or the `init-policy` checkpoint's own, chosen once and used by shards, evaluation, rollouts and the export.

use std::path::{Path, PathBuf};

use anyhow::Context;
use fedvla_policy::policy_dir::Backbone;
use fedvla_policy::{PolicyDir, Tokenizer, WordTokenizer};

/// The run's one tokenizer, chosen once: shards, held-out evaluation, every rollout and the export use it.
#[derive(Clone)]
pub(super) enum RunTokenizer {
    /// Random initialisation: the word-level tokenizer of the dataset's task strings, exported as a generated `vlm/`.
    Generated(WordTokenizer),
    /// `init-policy`: the checkpoint's own (its ids are what its token embedding was trained on), and the
    /// checkpoint's backbone folder, copied into every export.
    Checkpoint { tokenizer: Tokenizer, backbone: PathBuf },
}

impl RunTokenizer {
    /// The checkpoint's tokenizer when `init` is given, else the word-level one of `tasks`.
    pub(super) fn choose(init: Option<(&Path, &PolicyDir)>, tasks: &[String]) -> anyhow::Result<Self> {
        let Some((path, policy)) = init else {
            return Ok(Self::Generated(WordTokenizer::from_texts(tasks.iter().map(String::as_str))));
        };
        let no_tokenizer = || {
            format!(
                "init-policy {}: no tokenizer.json in its backbone folder (vlm/, or the folder config.json's \
                 vlm_model_name {:?} names); a run from a checkpoint tokenizes with the checkpoint's own tokenizer",
                path.display(),
                policy.cfg.vlm_model_name
            )
        };
        let tokenizer = policy.tokenizer()?.with_context(no_tokenizer)?;
        let backbone = policy.vlm_dir.clone().with_context(no_tokenizer)?;
        Ok(Self::Checkpoint { tokenizer, backbone })
    }

    pub(super) fn tokenizer(&self) -> Tokenizer {
        match self {
            Self::Generated(word) => Tokenizer::Word(word.clone()),
            Self::Checkpoint { tokenizer, .. } => tokenizer.clone(),
        }
    }

    pub(super) fn vocab_size(&self) -> usize {
        match self {
            Self::Generated(word) => word.vocab_size(),
            Self::Checkpoint { tokenizer, .. } => tokenizer.vocab_size(),
        }
    }

    /// Which tokenizer this is, for a person reading the run's start or an error.
    pub(super) fn describe(&self) -> String {
        match self {
            Self::Generated(word) => format!("word-level, of the dataset's task strings ({} ids)", word.vocab_size()),
            Self::Checkpoint { backbone, .. } => format!("the checkpoint's, {}/tokenizer.json", backbone.display()),
        }
    }

    /// Its `tokenizer.json`, as volunteers download it to tokenize their own dataset's tasks.
    pub(super) fn json(&self) -> anyhow::Result<Vec<u8>> {
        match self {
            Self::Generated(word) => Ok(serde_json::to_vec(&word.to_json())?),
            Self::Checkpoint { backbone, .. } => {
                let path = backbone.join("tokenizer.json");
                std::fs::read(&path).with_context(|| format!("reading {}", path.display()))
            }
        }
    }

    pub(super) fn backbone(&self) -> Backbone<'_> {
        match self {
            Self::Generated(word) => Backbone::Generated(word),
            Self::Checkpoint { backbone, .. } => Backbone::CopyFrom(backbone),
        }
    }
}
