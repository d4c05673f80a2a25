#!/usr/bin/env bash
# The project's test command (README "Run the tests"): every crate's tests natively, then the
# shared crates built for the browser target.
set -euo pipefail
cd "$(dirname "$0")/.."

cargo test --workspace --locked
# shared/ must build for wasm32 (the browser client); dataset file I/O stays native-only.
cargo check --locked --target wasm32-unknown-unknown \
  -p fedvla-policy -p fedvla-sim -p fedvla-federation -p fedvla-learner -p fedvla-data --no-default-features
