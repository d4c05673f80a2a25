//! Bytes as an update's payload, decoded under every encoding against a fixed spec: an error or a value, never
//! a panic; memory bounded by the spec and the bytes sent, whatever the payload's counts and shapes claim; what
//! is accepted has the spec's names and shapes and finite values, and survives being encoded again.

#![no_main]

use std::sync::LazyLock;

use fedvla_federation::codec::{UpdateValues, decode_payload, encode_delta_payload, encode_payload};
use fedvla_federation::{TensorSpec, UpdateEncoding};
use fedvla_fuzz::{ENCODINGS, peak_during};
use libfuzzer_sys::fuzz_target;

#[global_allocator]
static ALLOC: fedvla_fuzz::Counting = fedvla_fuzz::Counting;

static SPEC: LazyLock<TensorSpec> = LazyLock::new(fedvla_fuzz::spec);

fuzz_target!(|data: &[u8]| {
    let spec = &*SPEC;
    for encoding in ENCODINGS {
        let (decoded, peak) = peak_during(|| decode_payload(data, spec, encoding));
        // The decoded tensors (at most the spec's size), a name and an error message quoting it.
        let bound = spec.byte_size() + 2 * data.len() + 4096;
        assert!(peak <= bound, "{encoding:?}: decoding {} bytes held {peak} bytes (bound {bound})", data.len());
        let Ok(values) = decoded else { continue };
        let (UpdateValues::Model(tensors) | UpdateValues::Delta(tensors)) = values;
        assert_eq!(&tensors.spec(), spec, "{encoding:?}: an accepted update has the spec's names and shapes");
        tensors.validate(spec).expect("an accepted update is finite");
        let again = match encoding {
            UpdateEncoding::F32 => encode_payload(&tensors),
            _ => encode_delta_payload(&mut tensors.clone(), encoding),
        };
        let decoded_again = decode_payload(&again, spec, encoding)
            .unwrap_or_else(|e| panic!("{encoding:?}: an accepted update, encoded again, is refused: {e}"));
        // Int8 picks its own block scales, so its values move (within a step); the others come back exactly.
        if encoding != UpdateEncoding::Int8 {
            let (UpdateValues::Model(t) | UpdateValues::Delta(t)) = decoded_again;
            assert_eq!(t, tensors, "{encoding:?}: an accepted update changed on a round trip");
        }
    }
});
