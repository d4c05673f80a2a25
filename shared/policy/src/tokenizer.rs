//! Token ids the exported backbone config names (SmolVLM2's layout of special tokens).

/// `<|im_start|>`
pub const BOS_ID: i64 = 1;
/// `<|im_end|>`, SmolVLM2's pad token.
pub const PAD_ID: i64 = 2;
/// `<image>` (SmolVLA never feeds it; the backbone config names it).
pub const IMAGE_ID: i64 = 3;
