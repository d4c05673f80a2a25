//! Training the tiny SmolVLA: the loss falls on a fixed batch and the frozen tensors never move.

use std::path::Path;

use burn::tensor::{DType, Device};
use fedvla_policy::batch::Prepared;
use fedvla_policy::vlm_with_expert::ContextKv;
use fedvla_policy::weights::{ParamStore, host_refs, init_random, parse_safetensors, safetensors_bytes_as};
use fedvla_policy::{Batch, SmolVlaConfig, StoredDtype, Trainer, WeightMap};

mod rules;

#[test]
fn tiny_model_loss_drops_tenfold_in_200_steps_and_frozen_weights_stay_bit_identical() {
    let cfg = SmolVlaConfig::tiny();
    let weights = init_random(&cfg.param_specs(), 1);
    let mut trainer = Trainer::new(&cfg, &weights, &Device::flex().autodiff(), 5).unwrap();
    let batch = Batch::random(&cfg, 4, 11);
    // A fixed batch means fixed noise and time too: the model can fit the exact targets.
    let (noise, time) = trainer.sample_noise_and_time(4);
    let first = trainer.forward(&batch, noise.clone(), &time).unwrap().loss.into_scalar::<f32>();
    let mut last = first;
    for _ in 0..200 {
        // LeRobot's optimizer preset with a constant lr of 1e-3 (no warmup) for a short run.
        let (report, _) = trainer.train_step_with(&batch, noise.clone(), &time, 1e-3).unwrap();
        last = report.loss;
    }
    let after = trainer.forward(&batch, noise, &time).unwrap().loss.into_scalar::<f32>();
    println!("loss {first} -> {last} (after update {after})");
    assert!(after * 10.0 <= first, "loss fell only from {first} to {after}");

    let trainable = trainer.trainable_weights();
    for spec in cfg.param_specs().iter().filter(|s| !s.trainable) {
        assert!(!trainable.contains_key(&spec.name), "{} must not be trainable", spec.name);
    }
    let frozen_after = trainer.frozen_weights();
    for spec in cfg.param_specs().iter().filter(|s| !s.trainable) {
        let before = &weights[&spec.name];
        let after = &frozen_after[&spec.name];
        assert!(before.data.iter().zip(&after.data).all(|(a, b)| a.to_bits() == b.to_bits()), "{} moved", spec.name);
    }
}

/// FedProx's term, by [`rules::proximal_term_adds_mu_times_the_distance_from_the_anchor`].
#[test]
fn the_proximal_term_adds_mu_times_the_distance_from_the_anchor_to_every_gradient() {
    rules::proximal_term_adds_mu_times_the_distance_from_the_anchor(&Device::flex().autodiff());
}

/// A shard stores every task padded to `tokenizer_max_length`; with `pad_language_to = "longest"` the model reads
/// only the columns some row uses, as LeRobot pads: the loss and every gradient are those of the unpadded batch.
#[test]
fn language_padding_no_row_uses_changes_neither_the_loss_nor_any_gradient() {
    let cfg = SmolVlaConfig::tiny();
    assert_eq!(cfg.pad_language_to, "longest");
    let weights = init_random(&cfg.param_specs(), 1);
    let device = Device::flex().autodiff();
    let mut batch = Batch::random(&cfg, 3, 4);
    // Row 1 uses 4 of the 6 columns, the others all 6.
    let len = batch.lang_len;
    for i in 4..len {
        batch.lang_mask[len + i] = false;
        batch.lang_tokens[len + i] = 0;
    }
    let mut padded = batch.clone();
    let width = cfg.tokenizer_max_length;
    padded.lang_len = width;
    padded.lang_tokens =
        batch.lang_tokens.chunks(len).flat_map(|r| r.iter().copied().chain([0].repeat(width - len))).collect();
    padded.lang_mask =
        batch.lang_mask.chunks(len).flat_map(|r| r.iter().copied().chain([false].repeat(width - len))).collect();
    let prepared = Prepared::new(&cfg, &padded, &Device::flex()).unwrap();
    assert_eq!((prepared.lang_len, prepared.lang_mask.len()), (len, 3 * len));
    let step = |batch: &Batch| {
        let mut trainer = Trainer::new(&cfg, &weights, &device, 5).unwrap();
        let (noise, time) = trainer.sample_noise_and_time(3);
        trainer.train_step_with(batch, noise, &time, 1e-3).unwrap()
    };
    let ((short_report, short), (long_report, long)) = (step(&batch), step(&padded));
    assert!((short_report.loss - long_report.loss).abs() <= 1e-6, "{} != {}", short_report.loss, long_report.loss);
    for (name, g) in &short {
        for (a, b) in g.data.iter().zip(&long[name].data) {
            assert!((a - b).abs() <= 1e-6 * (1.0 + a.abs()), "{name}: {a} != {b}");
        }
    }
}

/// A new set of trainable weights (a round's global model) keeps AdamW's moments and step count; after
/// `reset_optimizer` the next step is bit for bit a fresh trainer's first step from those weights.
#[test]
fn new_weights_keep_the_optimizer_state_until_it_is_reset() {
    let cfg = SmolVlaConfig::tiny();
    let weights = init_random(&cfg.param_specs(), 1);
    let device = Device::flex().autodiff();
    let batch = Batch::random(&cfg, 2, 3);
    let mut trainer = Trainer::new(&cfg, &weights, &device, 5).unwrap();
    let (noise, time) = trainer.sample_noise_and_time(2);
    for _ in 0..3 {
        trainer.train_step_with(&batch, noise.clone(), &time, 1e-3).unwrap();
    }
    let global = trainer.trainable_weights();
    // From `global`: a fresh trainer, the trained one keeping its moments, and the trained one reset.
    let step_from = |trainer: &mut Trainer| {
        trainer.set_trainable_weights(global.clone()).unwrap();
        trainer.train_step_with(&batch, noise.clone(), &time, 1e-3).unwrap();
        trainer.trainable_weights()
    };
    let mut fresh = Trainer::new(&cfg, &weights, &device, 5).unwrap();
    let first_step = step_from(&mut fresh);
    let kept = step_from(&mut trainer);
    assert_eq!(trainer.steps_taken(), 4, "the step count carries over");
    assert_ne!(kept, first_step, "kept moments must change the step");
    trainer.reset_optimizer();
    assert_eq!(trainer.steps_taken(), 0);
    assert_eq!(step_from(&mut trainer), first_step);
}

/// SCAFFOLD's correction, by [`rules::a_correction_shifts_the_step_by_lr_times_itself`].
#[test]
fn a_correction_shifts_each_step_by_lr_times_itself() {
    rules::a_correction_shifts_the_step_by_lr_times_itself(&Device::flex().autodiff());
}

/// The frozen-feature cache's arithmetic: each row's context keys and values computed alone (its own language
/// length), padded and stacked, give the loss and every gradient of the whole forward pass to 1e-6, over three
/// steps (each moving the trainable tensors the next one starts from).
#[test]
fn cached_context_rows_give_the_loss_and_gradients_of_the_full_forward() {
    let cfg = SmolVlaConfig::tiny();
    assert!(cfg.backbone_frozen());
    let weights = init_random(&cfg.param_specs(), 1);
    let device = Device::flex().autodiff();
    let mut batch = Batch::random(&cfg, 3, 4);
    // Rows of different task lengths: row 0 uses 2 columns, row 1 all, row 2 four.
    let len = batch.lang_len;
    for (n, used) in [(0, 2), (2, 4)] {
        for i in used..len {
            batch.lang_mask[n * len + i] = false;
            batch.lang_tokens[n * len + i] = 0;
        }
    }
    let mut full = Trainer::new(&cfg, &weights, &device, 5).unwrap();
    let mut cached = Trainer::new(&cfg, &weights, &device, 5).unwrap();
    let contexts: Vec<ContextKv> = (0..3).map(|n| cached.context_kv(&batch.rows(&[n])).unwrap()).collect();
    assert!(contexts[0].len() < contexts[1].len(), "rows keep their own language length");
    let stacked = ContextKv::stack(&contexts.iter().collect::<Vec<_>>());
    for step in 0..3 {
        let (noise, time) = full.sample_noise_and_time(3);
        let (a, grads_full) = full.train_step_with(&batch, noise.clone(), &time, 1e-3).unwrap();
        let (b, grads_cached) = cached.train_step_from_with(&batch, Some(&stacked), noise, &time, 1e-3).unwrap();
        assert!((a.loss - b.loss).abs() <= 1e-6, "step {step}: loss {} against {}", a.loss, b.loss);
        assert_eq!(grads_full.keys().collect::<Vec<_>>(), grads_cached.keys().collect::<Vec<_>>());
        for (name, g) in &grads_full {
            for (x, y) in g.data.iter().zip(&grads_cached[name].data) {
                assert!((x - y).abs() <= 1e-6, "step {step}, {name}: {x} against {y}");
            }
        }
    }
}

/// Frozen tensors kept in bf16 on the CPU (how a browser holds `smolvla_base`'s within wasm32's 4 GiB) train as the
/// same values decoded to f32: the layers cast each weight to f32 where they use it, and every bf16 is an f32.
#[test]
fn frozen_tensors_kept_in_bf16_train_as_the_same_values_decoded_to_f32() {
    let cfg = SmolVlaConfig::tiny();
    let specs = cfg.param_specs();
    let device = Device::flex().autodiff();
    let bf16_file = |trainable: bool| {
        let part: WeightMap = init_random(&specs, 1)
            .into_iter()
            .filter(|(k, _)| specs.iter().any(|s| s.name == *k && s.trainable == trainable))
            .collect();
        safetensors_bytes_as(host_refs(&part), StoredDtype::Bf16).unwrap()
    };
    let (frozen_file, trainable_file) = (bf16_file(false), bf16_file(true));
    let trainable = parse_safetensors(&trainable_file, Path::new("trainable")).unwrap();
    let mut decoded = parse_safetensors(&frozen_file, Path::new("frozen")).unwrap();
    decoded.extend(trainable.clone());

    let kept = ParamStore::from_safetensors(&frozen_file, Path::new("frozen"), &device, true).unwrap();
    assert!(kept.flat().all(|(_, t, _)| t.dtype() == DType::BF16), "the frozen tensors stay bf16");
    let mut in_bf16 = Trainer::with_frozen(&cfg, kept, trainable, &device, 5).unwrap();
    let mut in_f32 = Trainer::new(&cfg, &decoded, &device, 5).unwrap();
    let batch = Batch::random(&cfg, 2, 3);
    for step in 0..3 {
        let (noise, time) = in_f32.sample_noise_and_time(2);
        let (a, grads_f32) = in_f32.train_step_with(&batch, noise.clone(), &time, 1e-3).unwrap();
        let (b, grads_bf16) = in_bf16.train_step_with(&batch, noise, &time, 1e-3).unwrap();
        assert!((a.loss - b.loss).abs() <= 1e-6, "step {step}: loss {} in f32, {} from bf16", a.loss, b.loss);
        // The cast weights are contiguous where the f32 ones are transposed views, so matmuls sum in another order:
        // rounding, which each AdamW step (its per-coordinate scaling enlarges it on gradients near zero) carries
        // into the next step's gradients. A wrong value anywhere would be off by far more.
        for (name, g) in &grads_f32 {
            for (x, y) in g.data.iter().zip(&grads_bf16[name].data) {
                let tolerance = 1e-6 + 1e-4 * x.abs();
                assert!((x - y).abs() <= tolerance, "step {step}, {name}: gradient {x} in f32, {y} from bf16");
            }
        }
    }
    // The frozen tensors come back as the file's values, in f32.
    assert_eq!(in_bf16.frozen_weights(), parse_safetensors(&frozen_file, Path::new("frozen")).unwrap());
}

/// A checkpoint split with a trainable tensor among the frozen ones is refused, naming it.
#[test]
fn a_trainable_tensor_among_the_frozen_ones_is_refused_by_name() {
    let cfg = SmolVlaConfig::tiny();
    let device = Device::flex().autodiff();
    let mut frozen = init_random(&cfg.param_specs(), 1);
    let name = cfg.param_specs().into_iter().find(|s| s.trainable).unwrap().name;
    let trainable: WeightMap = frozen
        .iter()
        .filter(|(k, _)| cfg.param_specs().iter().any(|s| s.name == **k && s.trainable && **k != name))
        .map(|(k, t)| (k.clone(), t.clone()))
        .collect();
    frozen.retain(|k, _| !trainable.contains_key(k));
    let store = ParamStore::upload_owned(frozen, &device, false);
    let err = Trainer::with_frozen(&cfg, store, trainable, &device, 5).err().expect("refused").to_string();
    assert!(err.contains(&name), "{err}");
}

/// The instruction reaches the actions: in a batch whose rows come in pairs that share every input but one token of
/// their instruction (the images, the state, the time, and the noisy actions the expert sees, the noise chosen so),
/// while their target actions differ, a model can fit both rows of a pair only by reading that token. Trained on it,
/// the tiny SmolVLA, backbone trained (the embedded default from random weights) or frozen (LeRobot's default
/// switches: the expert reads the frozen backbone's keys and values), ends far below the same training on the same
/// batch with the token made equal, where no model can do better than each pair's mean.
#[test]
fn a_word_that_alone_tells_two_targets_apart_is_read() {
    for (freeze_vision_encoder, train_expert_only) in [(false, false), (true, true)] {
        let cfg = SmolVlaConfig::tiny().with_trained_parts(freeze_vision_encoder, train_expert_only);
        let (told, blind) = (fit_pairs(&cfg, true), fit_pairs(&cfg, false));
        println!("expert only {train_expert_only}: loss told the word {told}, blind {blind}");
        assert!(told * 5.0 < blind, "expert only {train_expert_only}: told {told} against blind {blind}");
    }
}

/// The loss after 120 steps on four rows, pairs (0, 1) and (2, 3) alike in every input but, when `told`, one token.
fn fit_pairs(cfg: &SmolVlaConfig, told: bool) -> f32 {
    let weights = init_random(&cfg.param_specs(), 1);
    let device = Device::flex().autodiff();
    let mut trainer = Trainer::new(cfg, &weights, &device, 5).unwrap();
    let mut batch = Batch::random(cfg, 4, 11);
    let (noise, mut time) = trainer.sample_noise_and_time(4);
    let mut noise = noise.into_data().try_into_vec::<f32>().unwrap();
    let actions = batch.actions.as_mut().unwrap();
    let (t, a, max_a) = (cfg.chunk_size, cfg.action_dim(), cfg.max_action_dim);
    for (first, second) in [(0, 1), (2, 3)] {
        for image in batch.images.iter_mut() {
            let per = image.data.len() / 4;
            image.data.copy_within(first * per..(first + 1) * per, second * per);
        }
        let per = batch.state.data.len() / 4;
        batch.state.data.copy_within(first * per..(first + 1) * per, second * per);
        let len = batch.lang_len;
        if told {
            batch.lang_tokens[second * len + 2] += 100;
        }
        // x_t = t noise + (1 - t) actions alike in both rows: noise_2 = noise_1 + (1 - t) / t (actions_1 - actions_2).
        time[second] = time[first];
        let ratio = (1.0 - time[first]) / time[first];
        for step in 0..t {
            for d in 0..a {
                let (i, j) = ((first * t + step) * a + d, (second * t + step) * a + d);
                noise[(second * t + step) * max_a + d] =
                    noise[(first * t + step) * max_a + d] + ratio * (actions.data[i] - actions.data[j]);
            }
            for d in a..max_a {
                noise[(second * t + step) * max_a + d] = noise[(first * t + step) * max_a + d];
            }
        }
    }
    batch.action_is_pad = Some(vec![false; 4 * t]);
    let noise = burn::tensor::Tensor::from_data(burn::tensor::TensorData::new(noise, [4, t, max_a]), &device);
    for _ in 0..120 {
        trainer.train_step_with(&batch, noise.clone(), &time, 1e-3).unwrap();
    }
    trainer.forward(&batch, noise, &time).unwrap().loss.into_scalar::<f32>()
}
