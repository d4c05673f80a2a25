//! The browser volunteer, compiled to wasm32: [`volunteer::run_volunteer`] joins a federation from a web page and
//! runs the round loop shared with the native client (`fedvla_federation::run_client`) over a browser WebSocket,
//! training SmolVLA's trainable tensors with burn in wasm and rolling the global policy out in the in-page
//! SO-100 sim. The page (www/join.js) only draws what it is told and reconnects.
//!
//! Only the I/O lives here: transport ([`transport`]), cached downloads ([`download`]), the volunteer's own
//! dataset folder read and decoded in the page ([`own_dataset`]), filming rollouts on a canvas ([`film`]) and the
//! page's status ([`status`]); [`bench::bench_training`] times training steps in the
//! browser (www/bench.html).
#![cfg(target_arch = "wasm32")]

pub mod bench;
pub mod browser;
pub mod download;
pub mod film;
pub mod own_dataset;
pub mod status;
pub mod transport;
pub mod volunteer;
