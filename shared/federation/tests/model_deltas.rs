//! The chain of model deltas a volunteer downloads rebuilds the server's model to pinned bits (the same check runs
//! in wasm: `client-wasm/tests/web.rs`).

mod deltas;

#[test]
fn model_deltas_rebuild_the_pinned_models_natively() {
    assert_eq!(deltas::rebuilt_checksums(), deltas::PINNED);
}
