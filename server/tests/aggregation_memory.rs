//! Streaming aggregation: a FedAvg round's memory does not grow with the number of clients. A real server, a
//! `fedvla aggregation-server` process of its own for each round, takes one round of the `small` model's tensors
//! (every one, 5.2 MB of f32) from 20 volunteers over loopback WebSockets, and another from 5; its peak resident
//! memory over each round (/proc/PID/status VmHWM, reset once the round's tasks are out), the least of three
//! rounds of each, is compared. Holding the updates until the round closes would add 15 models for the 15 extra
//! clients; the server's upload budget holds two, so at most two updates are decoded and not yet folded at once in
//! either round.

use std::path::Path;

use fedvla_server::aggregation_memory::{RoundMemory, measure_round};

/// What the 20-client round may grow beyond the 5-client one, in models: the two rounds differ only in when their
/// transients (at most two updates in flight, each reassembled, then decoded, then held until folded) happen to
/// coincide and in where the allocator places them, one to two updates' worth over repeated runs; holding the
/// extra updates would be 15.
const MARGIN_MODELS: f64 = 3.0;

/// Rounds measured for each number of clients.
const RUNS: usize = 3;

#[test]
fn fedavg_round_memory_does_not_grow_with_the_number_of_clients() {
    let fedvla = Path::new(env!("CARGO_BIN_EXE_fedvla"));
    let tmp = tempfile::tempdir().unwrap();
    // Each size three times, its least growth kept: the transients' coincidence and placement vary from run to run
    // by one to two models, either way, while what grows with the clients would be there every time.
    let least_growth = |clients: usize| -> RoundMemory {
        let runs = (0..RUNS).map(|run| {
            let dir = tmp.path().join(format!("{clients}-{run}"));
            let r = measure_round(fedvla, "small", clients, &dir).unwrap();
            let mb = |b: u64| b as f64 / 1e6;
            println!(
                "{} clients: model {:.1} MB, server before the round {:.1} MB, peak {:.1} MB (+{:.1} models), {:.1} s",
                r.clients,
                mb(r.model_bytes),
                mb(r.before_rss_bytes),
                mb(r.peak_rss_bytes),
                r.growth_in_models(),
                r.round_seconds
            );
            r
        });
        runs.min_by(|a, b| a.growth_in_models().total_cmp(&b.growth_in_models())).expect("at least one run")
    };
    let five = least_growth(5);
    let twenty = least_growth(20);
    assert!(
        twenty.growth_in_models() <= five.growth_in_models() + MARGIN_MODELS,
        "20 clients grew the server's memory over the round by {:.1} models at least, 5 by {:.1} (margin {MARGIN_MODELS})",
        twenty.growth_in_models(),
        five.growth_in_models()
    );
}
