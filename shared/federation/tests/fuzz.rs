//! A bounded property test of everything that parses a stranger's bytes: the protocol's JSON messages, the
//! binary update frames and their reassembly, payload decoding and safetensors models. Arbitrary bytes, and
//! valid inputs mutated (bit flips, truncation, splices, header fields set to extremes), must give an error or
//! a value, never a panic, and a payload is never accepted past the limits, whatever a header claims. The chains
//! of model deltas a client downloads are fuzzed the same way.
//! `FEDVLA_FUZZ_CASES` sets the number of cases per target (20,000 by default).

use fedvla_federation::codec::{
    FrameHeader, Reassembler, UpdateLimits, UpdateValues, apply_model_deltas, decode_payload, encode_delta_payload,
    encode_model_delta, encode_model_deltas, encode_payload, encode_update,
};
use fedvla_federation::protocol::RolloutEpisode;
use fedvla_federation::{
    Capabilities, ClientMessage, CodecError, DataReport, DatasetSignature, FeatureMoments, NamedTensors, OwnDataset,
    ServerMessage, TensorError, TensorSpec, UpdateEncoding,
};

/// SplitMix64: a seeded stream of cases, the same on every run.
struct Cases(u64);

impl Cases {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }

    fn bytes(&mut self, max_len: usize) -> Vec<u8> {
        (0..self.below(max_len + 1)).map(|_| self.next() as u8).collect()
    }

    /// `valid`, damaged in one of several ways.
    fn mutate(&mut self, valid: &[u8]) -> Vec<u8> {
        let mut out = valid.to_vec();
        match self.below(6) {
            0 if !out.is_empty() => {
                for _ in 0..=self.below(8) {
                    let i = self.below(out.len());
                    out[i] ^= 1 << self.below(8);
                }
            }
            1 => out.truncate(self.below(out.len() + 1)),
            2 => {
                let at = self.below(out.len() + 1);
                let noise = self.bytes(64);
                out.splice(at..at, noise);
            }
            3 if out.len() >= 8 => {
                // A little-endian field somewhere in the first bytes (the frame header) set to an extreme.
                let at = self.below(out.len().min(40) - 7);
                let extreme = [u64::MAX, u64::MAX / 2, 1 << 40, 0, u64::from(u32::MAX)][self.below(5)];
                out[at..at + 8].copy_from_slice(&extreme.to_le_bytes());
            }
            4 if !out.is_empty() => {
                let i = self.below(out.len());
                out[i] = [b'"', b'{', b'}', b'[', b'\\', b'0', 0xff][self.below(7)];
            }
            _ => out.extend(self.bytes(16)),
        }
        out
    }
}

fn cases() -> usize {
    std::env::var("FEDVLA_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(20_000)
}

/// Decodes `payload` as `encoding`; whatever is accepted has the spec's names and shapes.
fn check_decode(payload: &[u8], spec: &TensorSpec, encoding: UpdateEncoding) -> bool {
    match decode_payload(payload, spec, encoding) {
        Ok(UpdateValues::Model(t) | UpdateValues::Delta(t)) => {
            assert_eq!(&t.spec(), spec, "a decoded update has the spec's names and shapes");
            true
        }
        Err(_) => false,
    }
}

fn tensors() -> NamedTensors {
    let mut t = NamedTensors::new();
    t.insert("model.expert.w", vec![4, 33], (0..132).map(|i| i as f32 * 0.5 - 3.0).collect()).unwrap();
    t.insert("model.expert.b", vec![4], vec![1.0, -2.0, 3.5, 0.0]).unwrap();
    t
}

#[test]
fn update_frames_and_payloads_never_panic_nor_exceed_limits() {
    let valid = tensors();
    let spec = valid.spec();
    let limits = UpdateLimits::for_spec(&spec, UpdateEncoding::F32, 96, 64);
    let frames = encode_update(&valid, 3, 96);
    assert!(frames.len() > 3, "the valid update spans several frames");
    let mut rng = Cases(1);
    let mut accepted = 0;
    for case in 0..cases() {
        // A sequence of frames: valid ones, some damaged, some dropped, reordered or pure noise.
        let mut sequence: Vec<Vec<u8>> = Vec::new();
        for frame in &frames {
            match rng.below(10) {
                0 => {}
                1 => sequence.push(rng.bytes(128)),
                2 | 3 => sequence.push(rng.mutate(frame)),
                _ => sequence.push(frame.clone()),
            }
        }
        if rng.below(8) == 0 && sequence.len() > 1 {
            let (a, b) = (rng.below(sequence.len()), rng.below(sequence.len()));
            sequence.swap(a, b);
        }
        let Some(first) = sequence.first() else { continue };
        let _ = FrameHeader::parse(first);
        let Ok(mut update) = Reassembler::start(first, limits) else { continue };
        if sequence[1..].iter().try_for_each(|f| update.push(f)).is_err() {
            continue;
        }
        let Ok(payload) = update.finish() else { continue };
        assert!(payload.len() as u64 <= limits.max_payload_bytes, "case {case}: payload past the limit");
        if check_decode(&payload, &spec, UpdateEncoding::F32) {
            accepted += 1;
        }
    }
    assert!(accepted > 0, "some undamaged updates get through");

    // Payload decoding alone, on damaged and arbitrary payloads.
    let payload = {
        let mut update = Reassembler::start(&frames[0], limits).unwrap();
        frames[1..].iter().for_each(|f| update.push(f).unwrap());
        update.finish().unwrap()
    };
    for _ in 0..cases() {
        let input = if rng.below(2) == 0 { rng.mutate(&payload) } else { rng.bytes(700) };
        check_decode(&input, &spec, UpdateEncoding::F32);
    }
}

/// Found by the cargo-fuzz target `update_codec` (fuzz/), whose memory bound it broke: a payload of many empty
/// tensors (rank 1, dimension 0) under names outside the spec was read to its end, keeping each, before the
/// spec refused it: 18,895 bytes of payload held 162,256 bytes (8.6x; at the base model's 400 MB payload limit,
/// gigabytes). A name outside the spec is now refused where it stands, and a repeated one before its values.
#[test]
fn tensors_outside_the_spec_or_repeated_are_refused_before_they_are_read() {
    let spec = tensors().spec();
    let header = |out: &mut Vec<u8>, name: &str, shape: &[u64]| {
        out.extend((name.len() as u32).to_le_bytes());
        out.extend(name.as_bytes());
        out.extend((shape.len() as u32).to_le_bytes());
        for d in shape {
            out.extend(d.to_le_bytes());
        }
    };
    let mut empties = encode_payload(&NamedTensors::new());
    empties[1..5].copy_from_slice(&1000u32.to_le_bytes());
    for i in 0..1000 {
        header(&mut empties, &format!("x{i}"), &[0]);
    }
    match decode_payload(&empties, &spec, UpdateEncoding::F32) {
        Err(CodecError::Tensor(TensorError::Unexpected(name))) => assert_eq!(name, "x0"),
        other => panic!("the first tensor outside the spec is refused, not {other:?}"),
    }
    // A spec tensor, then its name again with a header claiming its size and no values.
    let mut bias = NamedTensors::new();
    bias.insert("model.expert.b", vec![4], vec![0.5; 4]).unwrap();
    let mut repeated = encode_payload(&bias);
    repeated[1..5].copy_from_slice(&2u32.to_le_bytes());
    header(&mut repeated, "model.expert.b", &[4]);
    match decode_payload(&repeated, &spec, UpdateEncoding::F32) {
        Err(CodecError::Malformed(why)) => assert!(why.contains("appears twice"), "{why}"),
        other => panic!("a repeated tensor is refused, not {other:?}"),
    }
}

#[test]
fn compressed_payloads_never_panic() {
    let valid = tensors();
    let spec = valid.spec();
    let mut rng = Cases(2);
    let encodings =
        [UpdateEncoding::F16, UpdateEncoding::Bf16, UpdateEncoding::Int8, UpdateEncoding::Topk { fraction: 0.1 }];
    for encoding in encodings {
        let payload = encode_delta_payload(&mut valid.clone(), encoding);
        assert!(check_decode(&payload, &spec, encoding), "{encoding:?}: the valid payload decodes");
        assert!(!check_decode(&encode_payload(&valid), &spec, encoding), "{encoding:?} refuses an f32 payload");
        for _ in 0..cases() / 4 {
            let input = if rng.below(4) > 0 { rng.mutate(&payload) } else { rng.bytes(700) };
            check_decode(&input, &spec, encoding);
        }
    }
}

/// Damaged and arbitrary chains of model deltas: refused, or a model of the held one's names and shapes, never a
/// panic.
#[test]
fn model_delta_chains_never_panic() {
    let held = tensors();
    let spec = held.spec();
    let mut rng = Cases(4);
    let encodings =
        [UpdateEncoding::F16, UpdateEncoding::Bf16, UpdateEncoding::Int8, UpdateEncoding::Topk { fraction: 0.1 }];
    for encoding in encodings {
        let mut models = vec![held.clone()];
        let mut payloads = Vec::new();
        for step in 1..=2 {
            let target = models[step - 1].zip_map(&held, |m, _| m * 0.9 + 0.01 * step as f32).unwrap();
            let (payload, model) = encode_model_delta(&models[step - 1], &target, encoding).unwrap().unwrap();
            payloads.push(payload);
            models.push(model);
        }
        let chain = encode_model_deltas(0, payloads.iter().map(Vec::as_slice));
        assert_eq!(apply_model_deltas(&held, 0, 2, &chain).unwrap(), models[2], "{encoding:?}: the valid chain");
        for _ in 0..cases() / 4 {
            let input = if rng.below(4) > 0 { rng.mutate(&chain) } else { rng.bytes(700) };
            if let Ok(model) = apply_model_deltas(&held, 0, 2, &input) {
                assert_eq!(model.spec(), spec, "{encoding:?}: a rebuilt model has the held one's names and shapes");
            }
        }
    }
}

#[test]
fn protocol_messages_never_panic() {
    let valid: Vec<String> = [
        ClientMessage::Identify {
            protocol_version: 6,
            auth_token: Some("token".into()),
            name: "ada".into(),
            public_key: "ab".repeat(32),
            signature: "cd".repeat(64),
            shard: Some(1),
            own_dataset: false,
        },
        ClientMessage::Join {
            capabilities: Capabilities { backend: "webgpu".into(), memory_bytes: 1 << 30 },
            data: Some(DataReport {
                own: Some(OwnDataset {
                    signature: DatasetSignature {
                        robot_type: Some("so100".into()),
                        fps: 30,
                        state_dim: 2,
                        state_names: vec!["a".into(), "b".into()],
                        action_dim: 2,
                        action_names: vec!["a".into(), "b".into()],
                        cameras: vec!["observation.images.top".into()],
                    },
                    train_examples: 40,
                }),
                moments: [("action".to_owned(), FeatureMoments::of_rows(2, [[0.5f32, -1.0].as_slice()]))].into(),
            }),
        },
        ClientMessage::Heartbeat,
        ClientMessage::UpdateHeader { round: 4, examples: 120, train_loss: 0.5, payload_bytes: 4096 },
        ClientMessage::EvalResult { round: 2, examples: 10, loss: 0.25 },
        ClientMessage::RolloutResult {
            round: 2,
            model_version: 2,
            episodes: vec![RolloutEpisode {
                episode: 0,
                seed: 20_000,
                success: true,
                length: 180,
                video: None,
                task: None,
            }],
        },
    ]
    .iter()
    .map(|m| serde_json::to_string(m).unwrap())
    .collect();
    for text in &valid {
        assert!(serde_json::from_str::<ClientMessage>(text).is_ok(), "{text} parses");
    }
    let mut rng = Cases(2);
    let mut still_valid = 0;
    for _ in 0..cases() {
        let input = match rng.below(3) {
            0 => rng.bytes(200),
            _ => {
                let sample = rng.below(valid.len());
                rng.mutate(valid[sample].as_bytes())
            }
        };
        still_valid += usize::from(serde_json::from_slice::<ClientMessage>(&input).is_ok());
        // Clients parse what a server (or whoever answers in its place) sends just the same.
        let _ = serde_json::from_slice::<ServerMessage>(&input);
    }
    assert!(still_valid > 0, "some mutations (a flipped digit) keep a message valid: the parser saw them through");
}

#[test]
fn safetensors_models_never_panic() {
    let bytes = tensors().to_safetensors().unwrap();
    assert!(NamedTensors::from_safetensors(&bytes).is_ok());
    let mut rng = Cases(3);
    for _ in 0..cases() {
        let input = if rng.below(4) == 0 { rng.bytes(600) } else { rng.mutate(&bytes) };
        let _ = NamedTensors::from_safetensors(&input);
    }
}
