#!/usr/bin/env bash
# The project's test command (README "Run the tests"), on a fresh machine as on a warm one. It installs what is
# missing and prepares LeRobot's fixtures (tests/native-env.sh), checks formatting and lints (rustfmt.toml, the
# workspace's [workspace.lints] under clippy), builds the browser volunteer for wasm32 and runs its units in
# headless Chromium, then runs every crate's tests natively, the browser end-to-end tests, AV1 decoding and every
# fixture comparison included: here a missing browser, ffmpeg or fixture is a failure, not a skip. Builds and
# tools live outside the clone, in $FEDVLA_CACHE (~/.cache/fedvla).
set -euo pipefail
cd "$(dirname "$0")/.."
source tests/native-env.sh

# One style, checked first because it is instant; then the lints.
cargo fmt --check
cargo clippy --workspace --locked --features fedvla-server/av1,fedvla-server/gpu -- -D warnings
# The wasm volunteer into www/pkg, which the server serves and the browser tests load.
bash client-wasm/build.sh
# The wasm units (codec, sim, SmolVLA training on the CPU backend and on WebGPU) in a real Chromium.
WASM_BINDGEN_TEST_TIMEOUT=600 wasm-pack test --release --headless --chrome client-wasm

# Everything native.
cargo test --workspace --locked --features fedvla-server/av1
