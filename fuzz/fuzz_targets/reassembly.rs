//! Bytes as a sequence of binary WebSocket frames (each a `u16` length and its bytes), reassembled under the
//! limits: an error or a payload, never a panic; never more memory than the payload limit, whatever a header
//! claims; and a payload only of the announced length, within the limit, made of the frames' chunks in order.

#![no_main]

use fedvla_federation::codec::{FrameHeader, HEADER_LEN, Reassembler, UpdateValues, decode_payload};
use fedvla_federation::{TensorSpec, UpdateEncoding};
use fedvla_fuzz::{limits, peak_during, split_frames};
use libfuzzer_sys::fuzz_target;
use std::sync::LazyLock;

#[global_allocator]
static ALLOC: fedvla_fuzz::Counting = fedvla_fuzz::Counting;

static SPEC: LazyLock<TensorSpec> = LazyLock::new(fedvla_fuzz::spec);

fuzz_target!(|data: &[u8]| {
    let limits = limits();
    let (payload, peak) = peak_during(|| {
        let mut frames = split_frames(data);
        let first = frames.next()?;
        let _ = FrameHeader::parse(first);
        let mut update = Reassembler::start(first, limits).ok()?;
        for frame in frames {
            // The server drops an update at its first bad frame.
            update.push(frame).ok()?;
        }
        update.finish().ok()
    });
    // The payload buffer, and an error message.
    let bound = limits.max_payload_bytes + 1024;
    assert!(peak as u64 <= bound, "reassembling {} bytes held {peak} bytes (bound {bound})", data.len());
    let Some(payload) = payload else { return };
    assert!(payload.len() as u64 <= limits.max_payload_bytes, "a payload past the limit");
    let header = split_frames(data).next().map(FrameHeader::parse).and_then(Result::ok).expect("a first frame");
    assert_eq!(payload.len() as u64, header.payload_len, "the payload has the announced length");
    let chunks: Vec<u8> = split_frames(data).flat_map(|f| f[HEADER_LEN..].iter().copied()).collect();
    assert_eq!(payload, chunks, "the payload is the frames' chunks in order");
    if let Ok(UpdateValues::Model(t) | UpdateValues::Delta(t)) = decode_payload(&payload, &SPEC, UpdateEncoding::F32) {
        assert_eq!(t.spec(), *SPEC, "a decoded update has the spec's names and shapes");
    }
});
