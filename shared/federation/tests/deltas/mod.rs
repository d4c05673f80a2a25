//! A server's chain of model deltas over three rounds, in every compressed encoding, and a volunteer's rebuilding of
//! the last model from it, checked against pinned checksums: `model_deltas.rs` runs it natively and
//! `client-wasm/tests/web.rs` (which includes this file) in Chromium, so a browser volunteer is held to the very bits
//! a native one and the server hold.

use fedvla_federation::codec::{apply_model_deltas, encode_model_delta, encode_model_deltas};
use fedvla_federation::{NamedTensors, UpdateEncoding};

/// CRC32 of the model of version 3 ([`NamedTensors::checksum`]) in each encoding, as the server makes it.
pub const PINNED: [(&str, u32); 4] =
    [("f16", 2809059220), ("bf16", 1585318428), ("int8", 465681917), ("topk", 3968163021)];

/// Seeded values of many magnitudes (f16's subnormals among them), made with integer arithmetic and exact
/// conversions only: no transcendental function, whose last bit may differ between the platforms' libms.
fn values(seed: u64, n: usize) -> Vec<f32> {
    let mut state = seed;
    (0..n)
        .map(|i| {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let unit = (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5;
            unit * [1.0, 1e-2, 1e-4, 1e-7][i % 4]
        })
        .collect()
}

fn model(seed: u64) -> NamedTensors {
    let mut t = NamedTensors::new();
    t.insert("model.expert.w", vec![3, 300], values(seed, 900)).unwrap();
    t.insert("model.expert.b", vec![7], values(seed + 1, 7)).unwrap();
    t
}

/// For each encoding: the server's models of versions 1 to 3 (each its last one plus the served delta towards an
/// aggregate that moves a third of the values, as a top-k run's does), and a volunteer holding version 0 rebuilds
/// version 3 from the chain, bit for bit; the version 3 checksum of each.
pub fn rebuilt_checksums() -> Vec<(&'static str, u32)> {
    let v0 = model(1);
    let encodings =
        [UpdateEncoding::F16, UpdateEncoding::Bf16, UpdateEncoding::Int8, UpdateEncoding::Topk { fraction: 0.01 }];
    encodings
        .into_iter()
        .map(|encoding| {
            let mut server = v0.clone();
            let mut payloads = Vec::new();
            for round in 1..=3u64 {
                let step = model(10 + round);
                let mut aggregate = NamedTensors::new();
                for ((name, s), (_, d)) in server.iter().zip(step.iter()) {
                    let moved = s.values.iter().zip(&d.values).enumerate();
                    let values = moved.map(|(i, (s, d))| if i % 3 == round as usize % 3 { s + d } else { *s });
                    aggregate.insert(name, s.shape.clone(), values.collect()).unwrap();
                }
                let (payload, next) = encode_model_delta(&server, &aggregate, encoding).unwrap().unwrap();
                payloads.push(payload);
                server = next;
            }
            let chain = encode_model_deltas(0, payloads.iter().map(Vec::as_slice));
            let rebuilt = apply_model_deltas(&v0, 0, 3, &chain).unwrap();
            assert_eq!(rebuilt, server, "{encoding:?}: the volunteer's model is the server's");
            assert_eq!(rebuilt.checksum(), server.checksum(), "{encoding:?}");
            (encoding.name(), server.checksum())
        })
        .collect()
}
