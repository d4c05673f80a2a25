//! The checkpoint's tensors: every key LeRobot's SmolVLA has, its shape, and whether this configuration trains
//! it. Every loader, exporter and optimizer of this crate is driven by this list, and the loaders (`vision`,
//! `layers`, `vlm_with_expert`) read exactly its keys: the test below records what they read for every preset, so
//! a key cannot exist in one and not the other.

use crate::config::{
    CONNECTOR_KEY, EXPERT_PREFIX, LM_HEAD_KEY, PROJECTIONS, ParamSpec, SmolVlaConfig, TEXT_PREFIX, VISION_PREFIX,
};

/// The nine tensors of one Llama decoder layer `{p}.…` (the VLM's text layers and the expert's share them), with
/// the widths of its hidden state `d`, queries `q`, keys/values `kv`, its key/value input `kv_in` and MLP `mlp`.
struct DecoderDims {
    d: usize,
    q: usize,
    kv: usize,
    kv_in: usize,
    mlp: usize,
}

fn decoder_layer(add: &mut impl FnMut(String, Vec<usize>, bool), p: &str, dims: DecoderDims, trainable: bool) {
    let DecoderDims { d, q, kv, kv_in, mlp } = dims;
    add(format!("{p}.input_layernorm.weight"), vec![d], trainable);
    add(format!("{p}.self_attn.q_proj.weight"), vec![q, d], trainable);
    add(format!("{p}.self_attn.k_proj.weight"), vec![kv, kv_in], trainable);
    add(format!("{p}.self_attn.v_proj.weight"), vec![kv, kv_in], trainable);
    add(format!("{p}.self_attn.o_proj.weight"), vec![d, q], trainable);
    add(format!("{p}.post_attention_layernorm.weight"), vec![d], trainable);
    add(format!("{p}.mlp.gate_proj.weight"), vec![mlp, d], trainable);
    add(format!("{p}.mlp.up_proj.weight"), vec![mlp, d], trainable);
    add(format!("{p}.mlp.down_proj.weight"), vec![d, mlp], trainable);
}

impl SmolVlaConfig {
    /// Every tensor of the checkpoint, in LeRobot's module order, marked trainable as LeRobot's
    /// `set_requires_grad` marks it under this configuration's switches.
    pub fn param_specs(&self) -> Vec<ParamSpec> {
        let mut specs = Vec::new();
        let mut add =
            |name: String, shape: Vec<usize>, trainable: bool| specs.push(ParamSpec { name, shape, trainable });
        let add = &mut add;
        let backbone = !self.train_expert_only;
        let vision = backbone && !self.freeze_vision_encoder;
        let v = &self.vlm.vision_config;
        let t = &self.vlm.text_config;
        let e = self.expert();
        let (dv, dt, de) = (v.hidden_size, t.hidden_size, e.hidden_size);
        let kv = t.num_key_value_heads * t.head_dim;
        let q = t.num_attention_heads * t.head_dim;

        let vp = VISION_PREFIX;
        add(format!("{vp}.embeddings.patch_embedding.weight"), vec![dv, 3, v.patch_size, v.patch_size], vision);
        add(format!("{vp}.embeddings.patch_embedding.bias"), vec![dv], vision);
        let patches = (v.image_size / v.patch_size).pow(2);
        add(format!("{vp}.embeddings.position_embedding.weight"), vec![patches, dv], vision);
        for n in 0..v.num_hidden_layers {
            let p = format!("{vp}.encoder.layers.{n}");
            for norm in ["layer_norm1", "layer_norm2"] {
                add(format!("{p}.{norm}.weight"), vec![dv], vision);
                add(format!("{p}.{norm}.bias"), vec![dv], vision);
            }
            for proj in ["q_proj", "k_proj", "v_proj", "out_proj"] {
                add(format!("{p}.self_attn.{proj}.weight"), vec![dv, dv], vision);
                add(format!("{p}.self_attn.{proj}.bias"), vec![dv], vision);
            }
            add(format!("{p}.mlp.fc1.weight"), vec![v.intermediate_size, dv], vision);
            add(format!("{p}.mlp.fc1.bias"), vec![v.intermediate_size], vision);
            add(format!("{p}.mlp.fc2.weight"), vec![dv, v.intermediate_size], vision);
            add(format!("{p}.mlp.fc2.bias"), vec![dv], vision);
        }
        add(format!("{vp}.post_layernorm.weight"), vec![dv], vision);
        add(format!("{vp}.post_layernorm.bias"), vec![dv], vision);
        add(CONNECTOR_KEY.into(), vec![dt, dv * self.vlm.scale_factor.pow(2)], backbone);

        let tp = TEXT_PREFIX;
        add(format!("{tp}.embed_tokens.weight"), vec![t.vocab_size, dt], backbone);
        for n in 0..self.num_vlm_layers {
            let dims = DecoderDims { d: dt, q, kv, kv_in: dt, mlp: t.intermediate_size };
            decoder_layer(add, &format!("{tp}.layers.{n}"), dims, backbone && n + 1 < self.num_vlm_layers);
        }
        add(format!("{tp}.norm.weight"), vec![dt], false);
        add(LM_HEAD_KEY.into(), vec![t.vocab_size, dt], false);

        let ep = EXPERT_PREFIX;
        for n in 0..e.num_layers {
            let kv_in = if self.is_self_attn_layer(n) { de } else { kv };
            let dims = DecoderDims { d: de, q, kv, kv_in, mlp: e.intermediate_size };
            decoder_layer(add, &format!("{ep}.layers.{n}"), dims, true);
        }
        add(format!("{ep}.norm.weight"), vec![de], true);

        let shapes = [
            ([dt, self.max_state_dim], dt),
            ([de, self.max_action_dim], de),
            ([self.max_action_dim, de], self.max_action_dim),
            ([de, 2 * de], de),
            ([de, de], de),
        ];
        for (name, (w, b)) in PROJECTIONS.iter().zip(shapes) {
            let trained = self.train_state_proj || *name != "model.state_proj";
            add(format!("{name}.weight"), w.to_vec(), trained);
            add(format!("{name}.bias"), vec![b], trained);
        }
        specs
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use burn::tensor::Device;

    use crate::config::SmolVlaConfig;
    use crate::smolvla::SmolVla;
    use crate::weights::{ParamStore, init_random};

    #[test]
    fn the_loaders_read_exactly_the_listed_keys() {
        let configs = [
            SmolVlaConfig::tiny(),
            SmolVlaConfig::small(),
            SmolVlaConfig::small().with_trained_parts(false, false).with_image_size(64, 8),
        ];
        for cfg in configs {
            let specs = cfg.param_specs();
            let weights = init_random(&specs, 0);
            let (store, reads) = ParamStore::upload(weights.iter(), &Device::flex(), false).recording();
            SmolVla::new(&cfg, &store);
            let mut listed: BTreeSet<String> = specs.into_iter().map(|s| s.name).collect();
            // The checkpoint carries the language model head; SmolVLA never uses it.
            assert!(listed.remove(crate::config::LM_HEAD_KEY));
            assert_eq!(*reads.lock().unwrap(), listed);
        }
    }
}
