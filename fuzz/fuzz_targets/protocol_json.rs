//! Bytes as a WebSocket text message, parsed as what a client sends and as what a server sends: an error or a
//! value, never a panic; memory linear in the bytes sent; and what parses is written back to JSON that parses to
//! the same message.

#![no_main]

use fedvla_federation::{ClientMessage, ServerMessage};
use libfuzzer_sys::fuzz_target;
use serde::Serialize;
use serde::de::DeserializeOwned;

#[global_allocator]
static ALLOC: fedvla_fuzz::Counting = fedvla_fuzz::Counting;

fn check<T: Serialize + DeserializeOwned + PartialEq + std::fmt::Debug>(data: &[u8]) {
    let (parsed, peak) = fedvla_fuzz::peak_during(|| serde_json::from_slice::<T>(data));
    // Internally tagged enums buffer the message once before building it: a few tens of bytes per byte at most.
    let bound = 96 * data.len() + (64 << 10);
    assert!(peak <= bound, "parsing {} bytes held {peak} bytes (bound {bound})", data.len());
    if let Ok(message) = parsed {
        let text = serde_json::to_vec(&message).expect("a parsed message serializes");
        let again: T = serde_json::from_slice(&text).unwrap_or_else(|e| {
            panic!("{message:?} wrote {} that does not parse: {e}", String::from_utf8_lossy(&text))
        });
        assert_eq!(again, message, "the message changed on a round trip");
    }
}

fuzz_target!(|data: &[u8]| {
    check::<ClientMessage>(data);
    check::<ServerMessage>(data);
});
