//! A policy batch on the host and its preparation for the model, as LeRobot's SmolVLAPolicy
//! prepares it: resize-with-pad of every camera (bilinear, align_corners=false, no antialias,
//! padding on the left and top), the [0,1] → [-1,1] map, zero-padding of state and actions to the
//! model's maximum dims, and the prefix/suffix masks and position ids of the "mask_ar" rule.

use burn::tensor::{Device, Tensor, TensorData};

use crate::config::SmolVlaConfig;
use crate::error::PolicyError;
use crate::weights::HostTensor;

/// One batch of normalised policy inputs (post pre-processor), host side.
#[derive(Debug, Clone)]
pub struct Batch {
    /// One `[B, 3, H, W]` image in [0, 1] per camera, in the config's camera order.
    pub images: Vec<HostTensor>,
    /// `[B, L]` token ids and their attention mask (true = real token).
    pub lang_tokens: Vec<i64>,
    pub lang_mask: Vec<bool>,
    pub lang_len: usize,
    /// `[B, state_dim]`, normalised.
    pub state: HostTensor,
    /// `[B, T, action_dim]` normalised target actions (training only).
    pub actions: Option<HostTensor>,
    /// `[B, T]`, true where the chunk ran past the episode end.
    pub action_is_pad: Option<Vec<bool>>,
}

impl Batch {
    /// The samples `rows` of this batch, in that order (a frozen-feature cache computes each row's context alone).
    pub fn rows(&self, rows: &[usize]) -> Batch {
        let b = self.batch_size();
        let pick = |t: &HostTensor| {
            let per = t.data.len() / b.max(1);
            let mut shape = t.shape.clone();
            shape[0] = rows.len();
            HostTensor::new(shape, rows.iter().flat_map(|&n| t.data[n * per..(n + 1) * per].iter().copied()).collect())
        };
        let columns = |values: &[i64], width: usize| -> Vec<i64> {
            rows.iter().flat_map(|&n| values[n * width..(n + 1) * width].iter().copied()).collect()
        };
        let l = self.lang_len;
        Batch {
            images: self.images.iter().map(pick).collect(),
            lang_tokens: columns(&self.lang_tokens, l),
            lang_mask: rows.iter().flat_map(|&n| self.lang_mask[n * l..(n + 1) * l].iter().copied()).collect(),
            lang_len: l,
            state: pick(&self.state),
            actions: self.actions.as_ref().map(pick),
            action_is_pad: self.action_is_pad.as_ref().map(|pad| {
                let per = pad.len() / b.max(1);
                rows.iter().flat_map(|&n| pad[n * per..(n + 1) * per].iter().copied()).collect()
            }),
        }
    }

    /// `b` samples of uniform random images, state and actions with a fixed 6-token task, for benchmarks and
    /// tests (and the browser's self-test): the shapes of `cfg`, nothing of a real dataset.
    pub fn random(cfg: &SmolVlaConfig, b: usize, seed: u64) -> Self {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let (w, h) = cfg.resize_imgs_with_padding;
        let mut uniform = |n: usize| (0..n).map(|_| rng.random::<f32>()).collect::<Vec<f32>>();
        let (t, state_dim, action_dim) = (cfg.chunk_size, cfg.state_dim(), cfg.action_dim());
        Self {
            images: cfg
                .camera_keys()
                .iter()
                .map(|_| HostTensor::new(vec![b, 3, h, w], uniform(b * 3 * h * w)))
                .collect(),
            lang_tokens: (0..b * 6).map(|i| 7 + (i % 6) as i64).collect(),
            lang_mask: vec![true; b * 6],
            lang_len: 6,
            state: HostTensor::new(vec![b, state_dim], uniform(b * state_dim)),
            actions: Some(HostTensor::new(vec![b, t, action_dim], uniform(b * t * action_dim))),
            // The last step of every chunk but the first is padding, so the mask path is exercised.
            action_is_pad: Some((0..b * t).map(|i| i % t == t - 1 && i >= t).collect()),
        }
    }

    pub fn batch_size(&self) -> usize {
        self.state.shape[0]
    }
}

/// Bilinear resize of one `[C, H, W]` image with PyTorch's `align_corners=False` rule and no
/// antialiasing (what `F.interpolate(..., mode="bilinear")` does).
pub fn resize_bilinear(src: &[f32], c: usize, h: usize, w: usize, out_h: usize, out_w: usize) -> Vec<f32> {
    let coords = |out: usize, inp: usize| -> Vec<(usize, usize, f32)> {
        let scale = inp as f32 / out as f32;
        (0..out)
            .map(|o| {
                let real = ((o as f32 + 0.5) * scale - 0.5).max(0.0);
                let i0 = (real.floor() as usize).min(inp - 1);
                let i1 = (i0 + 1).min(inp - 1);
                (i0, i1, real - i0 as f32)
            })
            .collect()
    };
    let (ys, xs) = (coords(out_h, h), coords(out_w, w));
    let mut out = Vec::with_capacity(c * out_h * out_w);
    for ch in 0..c {
        let plane = &src[ch * h * w..(ch + 1) * h * w];
        for &(y0, y1, ly) in &ys {
            for &(x0, x1, lx) in &xs {
                let top = (1.0 - lx) * plane[y0 * w + x0] + lx * plane[y0 * w + x1];
                let bottom = (1.0 - lx) * plane[y1 * w + x0] + lx * plane[y1 * w + x1];
                out.push((1.0 - ly) * top + ly * bottom);
            }
        }
    }
    out
}

/// LeRobot's `resize_with_pad` followed by `x·2 − 1`: keeps the aspect ratio, pads with 0 on the
/// left and top (so padding becomes −1). `images` is `[B, 3, H, W]`; the result `[B, 3, th, tw]`.
pub fn prepare_image(images: &HostTensor, target_w: usize, target_h: usize) -> HostTensor {
    let [b, c, h, w] = <[usize; 4]>::try_from(images.shape.as_slice()).expect("images are [B, C, H, W]");
    let mut out = Vec::with_capacity(b * c * target_h * target_w);
    for n in 0..b {
        let img = &images.data[n * c * h * w..(n + 1) * c * h * w];
        if h == target_h && w == target_w {
            out.extend(img.iter().map(|x| x * 2.0 - 1.0));
            continue;
        }
        let ratio = (w as f64 / target_w as f64).max(h as f64 / target_h as f64);
        let (rh, rw) = ((h as f64 / ratio) as usize, (w as f64 / ratio) as usize);
        let resized = resize_bilinear(img, c, h, w, rh, rw);
        let (pad_top, pad_left) = (target_h - rh, target_w - rw);
        for ch in 0..c {
            for y in 0..target_h {
                for x in 0..target_w {
                    let v = if y < pad_top || x < pad_left {
                        0.0
                    } else {
                        resized[ch * rh * rw + (y - pad_top) * rw + (x - pad_left)]
                    };
                    out.push(v * 2.0 - 1.0);
                }
            }
        }
    }
    HostTensor::new(vec![b, c, target_h, target_w], out)
}

/// An RGB frame as robots and renderers store it (u8, `[H, W, 3]`) into the policy's `[3, H, W]`
/// floats in [0, 1], written to `out` (length `3·H·W`).
pub fn rgb_hwc_to_chw(rgb: &[u8], out: &mut [f32]) {
    let plane = out.len() / 3;
    for (i, px) in rgb.chunks_exact(3).enumerate() {
        for c in 0..3 {
            out[c * plane + i] = px[c] as f32 / 255.0;
        }
    }
}

/// Zero-pads the last dimension of a row-major tensor from `dim` to `max_dim`.
pub fn pad_last_dim(t: &HostTensor, max_dim: usize) -> HostTensor {
    let dim = *t.shape.last().expect("non-scalar");
    let rows = t.data.len() / dim.max(1);
    let mut data = Vec::with_capacity(rows * max_dim);
    for r in 0..rows {
        data.extend_from_slice(&t.data[r * dim..(r + 1) * dim]);
        data.extend(std::iter::repeat_n(0.0, max_dim - dim));
    }
    let mut shape = t.shape.clone();
    *shape.last_mut().expect("non-scalar") = max_dim;
    HostTensor::new(shape, data)
}

/// The 2-D attention mask of the big_vision "mask_ar" rule: with `c = cumsum(ar)`, query i may
/// attend key j iff `c[j] <= c[i]` and both are real tokens. Row-major `[B, L, L]`.
pub fn att_2d_mask(pad: &[bool], ar: &[bool], batch: usize, len: usize) -> Vec<bool> {
    let mut out = Vec::with_capacity(batch * len * len);
    for b in 0..batch {
        let (pad, ar) = (&pad[b * len..(b + 1) * len], &ar[b * len..(b + 1) * len]);
        let cum: Vec<u32> = ar
            .iter()
            .scan(0u32, |s, &a| {
                *s += a as u32;
                Some(*s)
            })
            .collect();
        for i in 0..len {
            for j in 0..len {
                out.push(cum[j] <= cum[i] && pad[i] && pad[j]);
            }
        }
    }
    out
}

/// Position ids `cumsum(pad) − 1` per row: padded tokens repeat the previous position.
pub fn position_ids(pad: &[bool], batch: usize, len: usize) -> Vec<i64> {
    let mut out = Vec::with_capacity(batch * len);
    for b in 0..batch {
        let mut count = 0i64;
        for &p in &pad[b * len..(b + 1) * len] {
            count += p as i64;
            out.push(count - 1);
        }
    }
    out
}

/// Copies the sub-block `rows × cols` out of a row-major `[B, L, L]` mask.
pub fn mask_block(
    mask: &[bool],
    batch: usize,
    len: usize,
    rows: std::ops::Range<usize>,
    cols: std::ops::Range<usize>,
) -> Vec<bool> {
    let mut out = Vec::with_capacity(batch * rows.len() * cols.len());
    for b in 0..batch {
        for i in rows.clone() {
            out.extend_from_slice(&mask[b * len * len + i * len + cols.start..b * len * len + i * len + cols.end]);
        }
    }
    out
}

/// The batch on a device, ready for the model.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// One `[B, 3, th, tw]` image in [-1, 1] per camera.
    pub images: Vec<Tensor<4>>,
    pub lang_tokens: Vec<i64>,
    pub lang_mask: Vec<bool>,
    pub lang_len: usize,
    /// `[B, max_state_dim]`.
    pub state: Tensor<2>,
    pub batch: usize,
}

impl Prepared {
    pub fn new(cfg: &SmolVlaConfig, batch: &Batch, device: &Device) -> Result<Self, PolicyError> {
        let b = batch.batch_size();
        let cams = cfg.camera_keys();
        if batch.images.len() != cams.len() {
            return Err(PolicyError::Input(format!(
                "has {} camera images, the policy expects {} ({})",
                batch.images.len(),
                cams.len(),
                cams.join(", ")
            )));
        }
        if batch.lang_tokens.len() != b * batch.lang_len || batch.lang_mask.len() != b * batch.lang_len {
            return Err(PolicyError::Input(format!("language tokens/mask are not [{b}, {}]", batch.lang_len)));
        }
        if batch.state.shape.get(1) != Some(&cfg.state_dim()) {
            return Err(PolicyError::Input(format!(
                "observation.state has shape {:?}, expected [{b}, {}]",
                batch.state.shape,
                cfg.state_dim()
            )));
        }
        let (tw, th) = cfg.resize_imgs_with_padding;
        let images = batch
            .images
            .iter()
            .zip(&cams)
            .map(|(img, key)| {
                if img.shape.len() != 4 || img.shape[0] != b || img.shape[1] != 3 {
                    return Err(PolicyError::Input(format!(
                        "{key} has shape {:?}, expected [{b}, 3, H, W]",
                        img.shape
                    )));
                }
                Ok(prepare_image(img, tw, th).to_tensor::<4>(device))
            })
            .collect::<Result<_, _>>()?;
        let lang_len = language_columns(cfg, batch);
        Ok(Self {
            images,
            lang_tokens: leading_columns(&batch.lang_tokens, batch.lang_len, lang_len),
            lang_mask: leading_columns(&batch.lang_mask, batch.lang_len, lang_len),
            lang_len,
            state: pad_last_dim(&batch.state, cfg.max_state_dim).to_tensor(device),
            batch: b,
        })
    }
}

/// How many language columns the model reads: all of them for `pad_language_to = "max_length"`; for `"longest"`,
/// as LeRobot's tokenizer step pads, up to the last column any row of the batch uses (at least one). A shard
/// stores every task padded to `tokenizer_max_length`; the columns no row uses are masked out of every attention,
/// so dropping them changes no output and spares the text layers and the expert their cost.
fn language_columns(cfg: &SmolVlaConfig, batch: &Batch) -> usize {
    if cfg.pad_language_to == "max_length" || batch.lang_len == 0 {
        return batch.lang_len;
    }
    let last_used = |row: &[bool]| row.iter().rposition(|&m| m).map_or(0, |i| i + 1);
    batch.lang_mask.chunks(batch.lang_len).map(last_used).max().unwrap_or(0).max(1)
}

/// The first `keep` columns of each `width`-long row.
fn leading_columns<T: Copy>(rows: &[T], width: usize, keep: usize) -> Vec<T> {
    if width == 0 {
        return Vec::new();
    }
    rows.chunks(width).flat_map(|row| row[..keep].iter().copied()).collect()
}

/// `[B, T, A]` normalised actions zero-padded to `[B, T, max_action_dim]`, on a device.
pub fn prepare_actions(cfg: &SmolVlaConfig, actions: &HostTensor, device: &Device) -> Tensor<3> {
    pad_last_dim(actions, cfg.max_action_dim).to_tensor(device)
}

/// Host f32 values to a device tensor of the given shape.
pub fn tensor_from<const D: usize>(data: Vec<f32>, shape: [usize; D], device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(data, shape), device)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mask_ar_rule_matches_the_spec_table() {
        // [img, lang, lang(pad), state, act0, act1]
        let pad = [true, true, false, true, true, true];
        let ar = [false, false, false, true, true, true];
        let m = att_2d_mask(&pad, &ar, 1, 6);
        let at = |i: usize, j: usize| m[i * 6 + j];
        assert!(at(0, 1) && !at(0, 3) && !at(0, 4));
        assert!(at(3, 0) && at(3, 3) && !at(3, 4));
        assert!(at(4, 3) && at(4, 4) && !at(4, 5) && at(5, 4));
        assert!((0..6).all(|j| !at(2, j) && !at(j, 2)));
        assert_eq!(position_ids(&pad, 1, 6), vec![0, 1, 1, 2, 3, 4]);
    }

    #[test]
    fn resize_with_pad_pads_left_and_top() {
        // A 2x4 all-ones image into 4x4: resized to 2x4, two rows of padding on top.
        let img = HostTensor::new(vec![1, 3, 2, 4], vec![1.0; 24]);
        let out = prepare_image(&img, 4, 4);
        assert_eq!(out.shape, vec![1, 3, 4, 4]);
        assert!(out.data[..8].iter().all(|&v| v == -1.0));
        assert!(out.data[8..16].iter().all(|&v| v == 1.0));
    }

    #[test]
    fn bilinear_upsample_matches_pytorch_align_corners_false() {
        // torch: F.interpolate(tensor([[[[0., 1.]]]]), size=(1, 4), mode="bilinear") = [0, .25, .75, 1]
        let out = resize_bilinear(&[0.0, 1.0], 1, 1, 2, 1, 4);
        assert_eq!(out, vec![0.0, 0.25, 0.75, 1.0]);
    }
}
