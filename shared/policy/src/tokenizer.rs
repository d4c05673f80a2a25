//! Language tokens as LeRobot's tokenizer step makes them ("\n" appended, truncated, right-padded
//! with `<|im_end|>`). Two vocabularies: a checkpoint's own `tokenizer.json` (SmolVLM2's BPE)
//! through the `tokenizers` crate, natively; and, for the embedded default, a word-level
//! tokenizer built from the task strings and written as a Hugging Face `tokenizer.json` (WordLevel
//! model, Whitespace pre-tokenizer) so LeRobot loads the very same vocabulary from an exported
//! policy's `vlm/` folder. Special tokens sit at SmolVLM2's ids.

use std::collections::BTreeMap;
use std::path::Path;

use serde_json::{Value, json};

use crate::error::PolicyError;

/// `<|im_start|>`
pub const BOS_ID: i64 = 1;
/// `<|im_end|>`, SmolVLM2's pad token.
pub const PAD_ID: i64 = 2;
/// `<image>` (SmolVLA never feeds it; the backbone config names it).
pub const IMAGE_ID: i64 = 3;
const UNK_ID: i64 = 0;
const SPECIAL: [&str; 7] = [
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<image>",
    "<fake_token_around_image>",
    "<global-img>",
    "<end_of_utterance>",
];

/// Word-level vocabulary: special tokens first, then words in first-seen order.
#[derive(Debug, Clone, PartialEq)]
pub struct WordTokenizer {
    vocab: BTreeMap<String, i64>,
}

/// Whitespace pre-tokenisation as `tokenizers`' `Whitespace` does it: runs of word characters and
/// runs of other non-space characters; the text is lower-cased first.
fn words(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut current = String::new();
    let mut current_is_word = false;
    for c in text.to_lowercase().chars() {
        if c.is_whitespace() {
            if !current.is_empty() {
                out.push(std::mem::take(&mut current));
            }
            continue;
        }
        let is_word = c.is_alphanumeric() || c == '_';
        if !current.is_empty() && is_word != current_is_word {
            out.push(std::mem::take(&mut current));
        }
        current_is_word = is_word;
        current.push(c);
    }
    if !current.is_empty() {
        out.push(current);
    }
    out
}

impl WordTokenizer {
    pub fn from_texts<'a>(texts: impl IntoIterator<Item = &'a str>) -> Self {
        let mut vocab: BTreeMap<String, i64> =
            SPECIAL.iter().enumerate().map(|(i, s)| (s.to_string(), i as i64)).collect();
        for text in texts {
            for w in words(text) {
                let next = vocab.len() as i64;
                vocab.entry(w).or_insert(next);
            }
        }
        Self { vocab }
    }

    pub fn vocab_size(&self) -> usize {
        self.vocab.len()
    }

    /// Token ids and attention mask of a batch of task strings, as LeRobot's pre-processor makes
    /// them: "\n" appended, truncated to `max_length`, right-padded to the longest row
    /// (`pad_to_max = false`) or to `max_length`.
    pub fn encode_batch(&self, tasks: &[&str], max_length: usize, pad_to_max: bool) -> (Vec<i64>, Vec<bool>, usize) {
        let rows =
            tasks.iter().map(|t| words(t).iter().map(|w| *self.vocab.get(w).unwrap_or(&UNK_ID)).collect()).collect();
        pad_rows(rows, max_length, pad_to_max)
    }

    /// The Hugging Face `tokenizer.json` of this vocabulary.
    pub fn to_json(&self) -> Value {
        let added: Vec<Value> = SPECIAL
            .iter()
            .enumerate()
            .map(|(i, s)| json!({"id": i, "content": s, "single_word": false, "lstrip": false, "rstrip": false, "normalized": false, "special": true}))
            .collect();
        json!({
            "version": "1.0",
            "truncation": null,
            "padding": null,
            "added_tokens": added,
            "normalizer": {"type": "Lowercase"},
            "pre_tokenizer": {"type": "Whitespace"},
            "post_processor": null,
            "decoder": null,
            "model": {"type": "WordLevel", "vocab": self.vocab, "unk_token": SPECIAL[UNK_ID as usize]}
        })
    }

    /// `tokenizer_config.json` naming the special tokens as SmolVLM2's does.
    pub fn tokenizer_config() -> Value {
        json!({
            "backend": "tokenizers", "bos_token": SPECIAL[1], "eos_token": SPECIAL[6], "pad_token": SPECIAL[2],
            "unk_token": SPECIAL[0], "image_token": SPECIAL[3], "fake_image_token": SPECIAL[4],
            "global_image_token": SPECIAL[5], "end_of_utterance_token": SPECIAL[6], "extra_special_tokens": [],
            "model_max_length": 8192, "processor_class": "SmolVLMProcessor", "tokenizer_class": "TokenizersBackend"
        })
    }

    /// Reads a WordLevel `tokenizer.json` written by [`WordTokenizer::to_json`].
    pub fn read(path: &Path) -> Result<Self, PolicyError> {
        let bytes = std::fs::read(path).map_err(|e| PolicyError::io(path, e))?;
        Self::from_json_bytes(&bytes, path)
    }

    /// [`WordTokenizer::read`] of the file's bytes; `path` names them in errors.
    pub fn from_json_bytes(bytes: &[u8], path: &Path) -> Result<Self, PolicyError> {
        let json: Value =
            serde_json::from_slice(bytes).map_err(|e| PolicyError::Json { path: path.into(), source: e })?;
        let model = &json["model"];
        if model["type"] != "WordLevel" {
            return Err(PolicyError::Tokenizer(format!(
                "{}: model type {} is not WordLevel; tokenise with the checkpoint's own tokenizer and pass token ids",
                path.display(),
                model["type"]
            )));
        }
        let vocab = model["vocab"]
            .as_object()
            .ok_or_else(|| PolicyError::Tokenizer(format!("{}: model.vocab is not an object", path.display())))?
            .iter()
            .map(|(k, v)| (k.clone(), v.as_i64().unwrap_or(UNK_ID)))
            .collect();
        Ok(Self { vocab })
    }
}

/// Right-pads token rows into the `[B, L]` ids and mask LeRobot feeds the model.
fn pad_rows(rows: Vec<Vec<i64>>, max_length: usize, pad_to_max: bool) -> (Vec<i64>, Vec<bool>, usize) {
    let len = if pad_to_max { max_length } else { rows.iter().map(Vec::len).max().unwrap_or(0).max(1) };
    let mut ids = Vec::with_capacity(rows.len() * len);
    let mut mask = Vec::with_capacity(rows.len() * len);
    for mut row in rows {
        row.truncate(max_length);
        mask.extend((0..len).map(|i| i < row.len()));
        ids.extend(row.iter().copied().chain(std::iter::repeat(PAD_ID)).take(len));
    }
    (ids, mask, len)
}

/// The tokenizer of a policy: its checkpoint's own, or the embedded word-level one.
#[derive(Debug, Clone)]
pub enum Tokenizer {
    Word(WordTokenizer),
    #[cfg(not(target_arch = "wasm32"))]
    HuggingFace(Box<tokenizers::Tokenizer>),
}

impl Tokenizer {
    /// Reads a `tokenizer.json`: WordLevel ones natively in this crate, anything else (SmolVLM2's
    /// BPE) through the `tokenizers` crate.
    pub fn read(path: &Path) -> Result<Self, PolicyError> {
        let bytes = std::fs::read(path).map_err(|e| PolicyError::io(path, e))?;
        Self::from_json_bytes(&bytes, path)
    }

    /// [`Tokenizer::read`] of a `tokenizer.json`'s bytes (a volunteer's download); `path` names them in errors.
    pub fn from_json_bytes(bytes: &[u8], path: &Path) -> Result<Self, PolicyError> {
        match WordTokenizer::from_json_bytes(bytes, path) {
            Ok(word) => Ok(Self::Word(word)),
            #[cfg(not(target_arch = "wasm32"))]
            Err(PolicyError::Tokenizer(_)) => tokenizers::Tokenizer::from_bytes(bytes)
                .map(|t| Self::HuggingFace(Box::new(t)))
                .map_err(|e| PolicyError::Tokenizer(format!("{}: {e}", path.display()))),
            Err(e) => Err(e),
        }
    }

    /// Token ids it can produce: what the policy's token embedding must hold.
    pub fn vocab_size(&self) -> usize {
        match self {
            Self::Word(w) => w.vocab_size(),
            #[cfg(not(target_arch = "wasm32"))]
            Self::HuggingFace(t) => t.get_vocab_size(true),
        }
    }

    /// `[B, L]` token ids, attention mask and L for a batch of task strings.
    pub fn encode_batch(
        &self,
        tasks: &[&str],
        max_length: usize,
        pad_to_max: bool,
    ) -> Result<(Vec<i64>, Vec<bool>, usize), PolicyError> {
        match self {
            Self::Word(w) => Ok(w.encode_batch(tasks, max_length, pad_to_max)),
            #[cfg(not(target_arch = "wasm32"))]
            Self::HuggingFace(t) => {
                let rows = tasks
                    .iter()
                    .map(|task| {
                        let text = if task.ends_with('\n') { task.to_string() } else { format!("{task}\n") };
                        t.encode(text, true)
                            .map(|e| e.get_ids().iter().map(|&i| i as i64).collect())
                            .map_err(|e| PolicyError::Tokenizer(e.to_string()))
                    })
                    .collect::<Result<Vec<Vec<i64>>, _>>()?;
                Ok(pad_rows(rows, max_length, pad_to_max))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encodes_like_lerobot_pads_right_with_im_end() {
        let tok = WordTokenizer::from_texts(["Put the cube in the bowl", "stack"]);
        let (ids, mask, len) = tok.encode_batch(&["put the cube in the bowl", "stack!"], 48, false);
        assert_eq!(len, 6);
        assert_eq!(&ids[..6], &[7, 8, 9, 10, 8, 11]);
        assert_eq!(&ids[6..], &[12, UNK_ID, PAD_ID, PAD_ID, PAD_ID, PAD_ID]);
        assert_eq!(&mask[6..], &[true, true, false, false, false, false]);
        let (_, _, len) = tok.encode_batch(&["stack"], 48, true);
        assert_eq!(len, 48);
    }
}
