//! What the fuzz targets share: the spec updates are decoded against, the limits frames are reassembled under, an
//! allocator that measures the most memory a call holds, and the seed inputs `seed_corpus` writes.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use fedvla_federation::codec::{UpdateLimits, encode_delta_payload, encode_frames, encode_payload};
use fedvla_federation::{ClientMessage, NamedTensors, ServerMessage, TensorSpec, UpdateEncoding};

/// Largest frame the reassembly target accepts, header included (small, so updates span many frames).
pub const MAX_FRAME_BYTES: usize = 96;
/// Bytes past the spec's longest payload the reassembly target accepts.
pub const HEADROOM: u64 = 64;

/// Every encoding a run can ask for (top-k at a small fraction and at all values).
pub const ENCODINGS: [UpdateEncoding; 6] = [
    UpdateEncoding::F32,
    UpdateEncoding::F16,
    UpdateEncoding::Bf16,
    UpdateEncoding::Int8,
    UpdateEncoding::Topk { fraction: 0.1 },
    UpdateEncoding::Topk { fraction: 1.0 },
];

/// The tensors updates are checked against: a matrix, a bias and a vector longer than one int8 block.
pub fn spec() -> TensorSpec {
    [("model.expert.b", vec![4]), ("model.expert.v", vec![300]), ("model.expert.w", vec![4, 33])]
        .into_iter()
        .map(|(name, shape)| (name.to_owned(), shape))
        .collect()
}

/// The reassembly target's limits: f32 updates of [`spec`] in frames of [`MAX_FRAME_BYTES`].
pub fn limits() -> UpdateLimits {
    UpdateLimits::for_spec(&spec(), UpdateEncoding::F32, MAX_FRAME_BYTES, HEADROOM)
}

/// Tensors of [`spec`] with varied values.
pub fn tensors() -> NamedTensors {
    let mut t = NamedTensors::new();
    for (i, (name, shape)) in spec().iter().enumerate() {
        let n: usize = shape.iter().product();
        let values = (0..n).map(|j| ((i * 7 + j) as f32 * 0.37).sin() * 3.0).collect();
        t.insert(name, shape.to_vec(), values).expect("values fit the shape");
    }
    t
}

/// Valid payloads of [`tensors`] under every encoding.
pub fn payloads() -> Vec<Vec<u8>> {
    ENCODINGS
        .iter()
        .map(|&encoding| match encoding {
            UpdateEncoding::F32 => encode_payload(&tensors()),
            _ => encode_delta_payload(&mut tensors(), encoding),
        })
        .collect()
}

/// Frames as the reassembly target reads them: each a little-endian `u16` length, then that many bytes (fewer
/// when the input ends first).
pub fn split_frames(mut data: &[u8]) -> impl Iterator<Item = &[u8]> {
    std::iter::from_fn(move || {
        if data.len() < 2 {
            return None;
        }
        let len = usize::from(u16::from_le_bytes([data[0], data[1]])).min(data.len() - 2);
        let frame = &data[2..2 + len];
        data = &data[2 + len..];
        Some(frame)
    })
}

/// Joins frames as [`split_frames`] reads them.
pub fn join_frames(frames: &[Vec<u8>]) -> Vec<u8> {
    frames.iter().flat_map(|f| (f.len() as u16).to_le_bytes().into_iter().chain(f.iter().copied())).collect()
}

/// Seed inputs for each target.
pub fn seeds(target: &str) -> Vec<Vec<u8>> {
    match target {
        "protocol_json" => {
            let client = [
                ClientMessage::Heartbeat,
                ClientMessage::UpdateHeader { round: 4, examples: 120, train_loss: 0.5, payload_bytes: 4096 },
                ClientMessage::EvalResult { round: 2, examples: 10, loss: 0.25 },
            ];
            let server = [
                ServerMessage::Challenge { nonce: "ab".repeat(16) },
                ServerMessage::Welcome { client_id: 3, protocol_version: 6, max_frame_bytes: 1 << 20 },
                ServerMessage::RoundClosed { round: 2, accepted: true, model_version: 2, updates: 5 },
                ServerMessage::Finished { rounds: 10 },
            ];
            let mut out: Vec<Vec<u8>> = client.iter().map(|m| serde_json::to_vec(m).expect("serializes")).collect();
            out.extend(server.iter().map(|m| serde_json::to_vec(m).expect("serializes")));
            // Messages whose fields are still moving, as text (a stale seed is only a less useful one).
            out.extend(
                [
                    r#"{"type":"identify","protocol_version":6,"auth_token":"t","name":"ada","public_key":"00","signature":"11","shard":1,"own_dataset":false}"#,
                    r#"{"type":"join","capabilities":{"backend":"webgpu","memory_bytes":1073741824},"data":null}"#,
                    r#"{"type":"rollout_result","round":2,"model_version":2,"episodes":[{"episode":0,"seed":20000,"success":true,"length":180}]}"#,
                    r#"{"type":"error","code":"bad_update","message":"no"}"#,
                ]
                .map(|s| s.as_bytes().to_vec()),
            );
            out
        }
        "update_codec" => {
            let mut out = payloads();
            // Empty tensors under names outside the spec (once held until the spec refused them), then a valid one.
            let mut empties = encode_payload(&NamedTensors::new());
            empties[1..5].copy_from_slice(&3u32.to_le_bytes());
            for name in ["x0", "x1"] {
                empties.extend((name.len() as u32).to_le_bytes());
                empties.extend(name.as_bytes());
                empties.extend(1u32.to_le_bytes());
                empties.extend(0u64.to_le_bytes());
            }
            empties.extend_from_slice(&out[0][5..]);
            out.push(empties);
            out
        }
        "reassembly" => {
            let f32_payload = encode_payload(&tensors());
            vec![
                join_frames(&encode_frames(&f32_payload, 3, MAX_FRAME_BYTES)),
                join_frames(&encode_frames(&f32_payload[..40], 1, MAX_FRAME_BYTES)),
                join_frames(&encode_frames(&[], 0, MAX_FRAME_BYTES)),
            ]
        }
        _ => Vec::new(),
    }
}

/// The global allocator of every target: the system's, counting the bytes held.
pub struct Counting;

static HELD: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

// SAFETY: every call is forwarded to the system allocator with the same arguments; only counters are added.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            grow(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            grow(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        HELD.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            // While moving, both blocks may be held.
            grow(new_size);
            HELD.fetch_sub(layout.size(), Ordering::Relaxed);
        }
        p
    }
}

fn grow(size: usize) {
    let held = HELD.fetch_add(size, Ordering::Relaxed) + size;
    PEAK.fetch_max(held, Ordering::Relaxed);
}

/// Runs `f` and returns what it returned and the most bytes it held at once beyond what was held before it.
pub fn peak_during<R>(f: impl FnOnce() -> R) -> (R, usize) {
    let before = HELD.load(Ordering::Relaxed);
    PEAK.store(before, Ordering::Relaxed);
    let out = f();
    (out, PEAK.load(Ordering::Relaxed).saturating_sub(before))
}
