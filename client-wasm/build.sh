#!/usr/bin/env bash
# Builds the browser volunteer into www/pkg (served by `fedvla serve` at /pkg/): the wasm32 release build, then
# wasm-bindgen's ES-module glue. Needs the wasm32-unknown-unknown target and the wasm-bindgen CLI of the
# version in Cargo.lock (.ci/run installs both).
set -euo pipefail
cd "$(dirname "$0")/.."
target_dir="${CARGO_TARGET_DIR:-target}"
cargo build --locked --release -p fedvla-client-wasm --target wasm32-unknown-unknown
wasm-bindgen --target web --out-dir www/pkg "$target_dir/wasm32-unknown-unknown/release/fedvla_client_wasm.wasm"
# A gzip copy the server hands to browsers that take it (a sixth of the size).
gzip -k -f www/pkg/fedvla_client_wasm_bg.wasm
ls -l www/pkg/fedvla_client_wasm_bg.wasm www/pkg/fedvla_client_wasm_bg.wasm.gz
